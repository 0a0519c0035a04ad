"""app.processes.cpu_seconds: what a process and the processes it started cost, read from /proc
(the leader bench's CPU per leader: its loop's process and its page process)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from app.processes import cpu_seconds, interrupt, read_stat, steal_seconds

# a parent that starts a child; the child burns about BURN_S of CPU, says so, and both then sleep
BURN_S = 0.6
_PARENT = f"""
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c",
    "import time, sys\\nend = time.process_time() + {BURN_S}\\nwhile time.process_time() < end: pass\\n"
    "print('burnt', flush=True)\\ntime.sleep(120)"], stdout=subprocess.PIPE, text=True)
print(child.pid, flush=True)
print(child.stdout.readline().strip(), flush=True)
time.sleep(120)
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc")
def test_a_process_is_charged_what_its_children_use_and_an_ended_one_nothing() -> None:
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdout=subprocess.PIPE, text=True)
    child: int | None = None
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        assert parent.stdout.readline().strip() == "burnt"
        used = cpu_seconds([parent.pid, child])
        own = read_stat(f"/proc/{parent.pid}/stat")[1]
        assert used[child] >= BURN_S * 0.9  # the child's own CPU (clock ticks round down)
        assert used[parent.pid] >= used[child] + own - 0.02  # the parent: its own and its child's
        assert own < used[child]  # the parent itself only started the child and waited
        assert read_stat(f"/proc/{child}/stat")[0] == parent.pid
    finally:
        if child is not None:
            try:
                os.kill(child, 9)  # the child first: the parent's Ctrl-C does not reach it
            except ProcessLookupError:
                pass
        interrupt(parent, grace_s=5)
    assert cpu_seconds([parent.pid]) == {parent.pid: 0.0}  # ended: nothing, and no error
    with pytest.raises(OSError):
        read_stat(f"/proc/{parent.pid}/stat")


def test_a_file_that_is_not_a_stat_file_is_refused_as_one(tmp_path):
    """read_stat's one error, whatever the file holds: no command name, too few fields, text for numbers."""
    for k, text in enumerate(("no command name here", "12 (cat) S 1 2", "12 (a) b) S x 1 1 1 1 1 1 1 1 1 1 1 1",
                              "12 (cat) S 1 1 1 1 1 1 1 1 1 1 u s")):
        bad = tmp_path / f"stat{k}"
        bad.write_text(text)
        with pytest.raises(OSError, match="not a stat file"):
            read_stat(str(bad))


def test_steal_is_read_from_the_machines_cpu_line_and_nothing_is_made_up(tmp_path):
    """steal_seconds: /proc/stat's eighth figure of the "cpu" line, in seconds; None for a file
    without it (not guessed as 0: a bench would then say the machine stole nothing)."""
    tick = os.sysconf("SC_CLK_TCK")
    good = tmp_path / "stat"
    good.write_text(f"cpu  10 0 5 900 1 0 2 {3 * tick} 0 0\ncpu0 5 0 2 450 1 0 1 {tick} 0 0\n")
    assert steal_seconds(str(good)) == pytest.approx(3.0)
    for k, text in enumerate(("cpu  10 0 5 900\n", "cpu0 1 2 3 4 5 6 7 8\n", "cpu  1 2 3 4 5 6 7 x\n", "")):
        bad = tmp_path / f"bad{k}"
        bad.write_text(text)
        assert steal_seconds(str(bad)) is None
    assert steal_seconds(str(tmp_path / "missing")) is None
    if os.path.isfile("/proc/stat"):  # this machine's: a count that never goes back
        first = steal_seconds()
        assert first is not None and first >= 0.0
        second = steal_seconds()
        assert second is not None and second >= first
