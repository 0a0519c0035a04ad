"""`run --reserve-cpu`: a CPU kept for the loop's thread alone among the service's threads and its
page's, one loop per kept CPU on a machine, at least one CPU left for the rest; a second loop that
finds none free says so and runs as before. Real processes, their threads read from /proc."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.helpers import wait_for

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")


def _run(*extra: str) -> tuple[subprocess.Popen, list[str]]:
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--feedback",
                             "truth", *extra], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    return proc, lines


def _affinities(pid: int) -> dict[int, set[int]]:
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out[int(tid)] = os.sched_getaffinity(int(tid))
        except OSError:
            continue
    return out


def _pages(pid: int) -> list[int]:
    """The page's process among ``pid``'s children (multiprocessing's spawned child, not its resource tracker)."""
    kids = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        kids += [int(k) for k in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
    return [k for k in kids if b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes()]


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


def test_a_kept_cpu_runs_the_loop_alone_and_a_second_loop_finds_none_free():
    first, lines = _run("--reserve-cpu")
    second = None
    try:
        wait_for(lambda: any("kept for the loop" in line for line in lines), 120, "the first run's kept-CPU line")
        said = next(line for line in lines if "kept for the loop" in line)
        assert said.startswith("omniformation: CPU "), said
        cpu = int(said.split("CPU ", 1)[1].split()[0])
        others = set(os.sched_getaffinity(0)) - {cpu}
        pages = _pages(first.pid)
        assert pages, "the page's process"
        def on_cpu(pid: int) -> list[int]:
            return [tid for tid, cpus in _affinities(pid).items() if cpu in cpus]

        # the loop moves threads made since off its CPU once a second (later on a loaded machine)
        wait_for(lambda: len(on_cpu(first.pid)) == 1 and all(on_cpu(page) == [] for page in pages), 20,
                 "the kept CPU to hold the loop's thread alone")
        mine = on_cpu(first.pid)
        assert len(mine) == 1 and _affinities(first.pid)[mine[0]] == {cpu}, _affinities(first.pid)
        for page in pages:
            assert on_cpu(page) == [], (page, _affinities(page))
            assert all(cpus <= others for cpus in _affinities(page).values())
        # the loop keeps its rate (its page on the other CPUs is served and answers)
        assert first.poll() is None
        # a second loop on a two-CPU machine: the one CPU left stays for everything else
        second, second_lines = _run("--reserve-cpu")
        wait_for(lambda: any("CPU" in line and "loop" in line and "kept" in line for line in second_lines), 120,
                 "the second run's line")
        line = next(x for x in second_lines if "CPU" in x and "kept" in x)
        if len(os.sched_getaffinity(0)) == 2:
            assert "no CPU kept for the loop (every CPU but one is kept by another loop" in line, line
        else:
            assert line.startswith("omniformation: CPU ") and int(line.split("CPU ", 1)[1].split()[0]) != cpu, line
    finally:
        _stop(first)
        if second is not None:
            _stop(second)
    assert first.returncode == 0 and "all followers commanded to zero" in "".join(lines)


def test_without_the_option_nothing_is_kept():
    proc, lines = _run()
    try:
        wait_for(lambda: any("dashboard at" in line for line in lines), 120, "the page")
        wait_for(lambda: len(_affinities(proc.pid)) > 3, 30, "the loop's threads")
        time.sleep(2.0)
        every = set(os.sched_getaffinity(0))
        assert all(cpus == every for cpus in _affinities(proc.pid).values())
        assert not any("kept for the loop" in line for line in lines)
    finally:
        _stop(proc)
