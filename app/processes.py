"""Stopping child processes as a person stops them: one helper for every command and test that starts some;
and what a process and its children cost in CPU, and what the machine's hypervisor took (the benches' figures)."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterable


def interrupt(*procs: subprocess.Popen, grace_s: float = 30.0) -> None:  # type: ignore[type-arg]
    """Ctrl-C (SIGINT) to every process still running, all first (they shut down side by side),
    then wait for each; one that has not ended within ``grace_s`` is killed."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(grace_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)


def read_stat(path: str) -> tuple[int, float]:
    """(parent pid, CPU seconds used: user and system) from a /proc stat file of a process or a
    thread (proc(5)); OSError when it has ended."""
    with open(path) as f:
        text = f.read()
    try:
        fields = text.rsplit(")", 1)[1].split()  # after the command's name, which may hold spaces
        return int(fields[1]), (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (IndexError, ValueError) as exc:
        raise OSError(f"{path}: not a stat file") from exc


def cpu_seconds(roots: Iterable[int]) -> dict[int, float]:
    """CPU seconds (user and system, from /proc) each process of ``roots`` has used, with every
    live process it started and theirs (a leader's page process): its children's CPU counts as
    its own. A process that is gone (or a system without /proc) counts 0.0. What a process's
    children used before they ended is not counted, so take the difference of two calls over a
    window in which its children live."""
    parent: dict[int, int] = {}
    used: dict[int, float] = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        names = []
    for name in names:
        if not name.isdigit():
            continue
        try:
            parent[int(name)], used[int(name)] = read_stat(f"/proc/{name}/stat")
        except OSError:
            continue  # ended meanwhile
    children: dict[int, list[int]] = {}
    for pid, ppid in parent.items():
        children.setdefault(ppid, []).append(pid)
    out: dict[int, float] = {}
    for root in roots:
        total, todo, seen = 0.0, [root], set()
        while todo:
            pid = todo.pop()
            if pid in seen:
                continue
            seen.add(pid)
            total += used.get(pid, 0.0)
            todo.extend(children.get(pid, ()))
        out[root] = total
    return out


def steal_seconds(path: str = "/proc/stat") -> float | None:
    """CPU seconds this machine's CPUs wanted to run but its hypervisor ran something else
    (``steal``, all CPUs together, from /proc/stat's first line: proc(5)); None where there is
    no such figure (no /proc, a kernel too old to count it). Take the difference of two calls:
    a bench tells the machine's own stalls from its code's by it."""
    try:
        with open(path) as f:
            fields = f.readline().split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != "cpu" or not fields[8].isdigit():
        return None
    return int(fields[8]) / os.sysconf("SC_CLK_TCK")
