"""Real-time scheduling for the threads on a frame's way to the robots (``run --realtime``).

On a shared machine the operating system may keep the loop off the CPU for several
milliseconds while other programs run (a browser, a compiler): measured here, the
frame-to-command latency's p99 was 10-20 ms at normal priority with a browser drawing on the
same two CPUs as an equal (its own session, hence its own autogroup, sched(7)), 3-7 ms with that
browser on idle CPU only, and 4-5 ms with the camera and loop threads on SCHED_FIFO and a 1 ms
GIL switch interval (``omniformation bench --latency``). Linux keeps 5 % of every second for other tasks however busy a real-time
thread is (``kernel.sched_rt_runtime_us``), and both threads sleep between frames.

Asking needs the right to (root, CAP_SYS_NICE, or an ``rtprio`` limit): refused, the thread
stays as it was and the reason is said once."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable

PRIORITY = 10  # SCHED_FIFO 1..99: above every normal task, below the kernel's own real-time threads
# Python hands the GIL between threads every 5 ms by default: a thread that holds it keeps it up to
# that long after a waiting one asks. Where waiting matters (the loop with --realtime, the fleet
# page's state callbacks) the process switches every 1 ms.
SWITCH_INTERVAL_S = 0.001


def make_realtime(native_id: int = 0, priority: int = PRIORITY) -> str:
    """SCHED_FIFO for the thread ``native_id`` (0: the calling thread); '' when granted, else why not."""
    if not hasattr(os, "sched_setscheduler"):
        return "this system has no SCHED_FIFO"
    try:
        os.sched_setscheduler(native_id, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return "not permitted (needs root, CAP_SYS_NICE or an rtprio limit)"
    except OSError as exc:
        return f"refused: {exc.strerror or exc}"
    return ""


def scheduling(native_id: int = 0) -> str:
    """How the thread is scheduled, for people: 'real-time (FIFO 10)' or 'normal'."""
    if not hasattr(os, "sched_getscheduler"):
        return "normal"
    policy = os.sched_getscheduler(native_id)
    if policy in (os.SCHED_FIFO, os.SCHED_RR):
        return f"real-time ({'FIFO' if policy == os.SCHED_FIFO else 'RR'} {os.sched_getparam(native_id).sched_priority})"
    return "normal"


class CpuReservation:
    """One CPU kept for the loop's thread, at normal priority and without any privilege.

    Measured here (2 CPUs, a browser on the same machine, `omniformation bench --latency`): the
    frame-to-command p99 was 8-20 ms whether the page ran in the loop's process or its own, and
    4.4 ms with no browser. In the slow ticks the loop's thread had waited 4-13 ms in the run queue
    while the browser's threads ran (a kernel trace of the scheduler's switches): the browser, in a
    session of its own, was an autogroup of its own, which the kernel shares CPU with as an equal
    of the service's whatever its threads' policy. With that browser held to idle CPU (as the
    bench now holds it, as if on the operator's own machine) p99 was 3-7 ms. A lower nice for the
    page, a 1 ms interpreter switch interval, a shorter scheduler slice for the loop or one OpenCV
    thread did not change it. A browser beside the service as an equal is kept off the loop only
    on a CPU the browser does not run on: with the loop's thread kept on a CPU of its own, every
    other thread of the service (and the page's process) off it, and the browser started off it,
    p99 was 3.6-5.3 ms. With the browser free to use every CPU, a loop held to one is worse
    (17-20 ms): it can no longer move away. Hence an option (`run --reserve-cpu`), not the default.

    ``take`` (on the loop's thread): the highest allowed CPU not kept by another loop on this
    machine (a lock file per CPU, released when the process ends), leaving at least one CPU for
    the rest; the loop's thread on it, every other thread of this process and of ``helpers`` (the
    page's process) off it. Threads made since are moved off by ``keep_off`` (the loop calls it
    once a second). Other programs may still use that CPU; the service's own threads do not.
    With one CPU, or every CPU but one kept by other loops, nothing is kept and ``why`` says so."""

    def __init__(self, helpers: Callable[[], Iterable[int]] = lambda: ()) -> None:
        self.helpers = helpers
        self.cpu: int | None = None
        self.others: set[int] = set()
        self.why = ""
        self._fd: int | None = None
        self._thread = 0

    def take(self) -> str:
        """Keep a CPU for the calling thread; '' when kept, else why not (said once by the caller)."""
        import fcntl
        import tempfile
        import threading

        if not hasattr(os, "sched_setaffinity"):
            self.why = "this system cannot keep a CPU for a thread"
            return self.why
        allowed = os.sched_getaffinity(0)
        if len(allowed) < 2:
            self.why = "one CPU: nothing to keep"
            return self.why
        for cpu in sorted(allowed, reverse=True)[:len(allowed) - 1]:
            try:
                fd = os.open(os.path.join(tempfile.gettempdir(), f"omniformation-cpu-{cpu}.lock"),
                             os.O_RDWR | os.O_CREAT, 0o600)
            except OSError:  # another user's loop made it: kept
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            self._fd, self.cpu, self.others = fd, cpu, allowed - {cpu}
            break
        else:
            self.why = "every CPU but one is kept by another loop on this machine"
            return self.why
        self._thread = threading.get_native_id()
        os.sched_setaffinity(0, {self.cpu})
        self.keep_off()
        return ""

    def keep_off(self) -> int:
        """Move every other thread of this process and of the helpers off the kept CPU; how many moved."""
        if self.cpu is None:
            return 0
        moved = 0
        for pid in (None, *self.helpers()):
            folder = "/proc/self/task" if pid is None else f"/proc/{pid}/task"
            try:
                tids = [int(t) for t in os.listdir(folder)]
            except OSError:  # a helper that ended
                continue
            for tid in tids:
                if tid == self._thread:
                    continue
                try:
                    if self.cpu in os.sched_getaffinity(tid):
                        os.sched_setaffinity(tid, self.others)
                        moved += 1
                except OSError:  # ended meanwhile
                    continue
        return moved

    def release(self) -> None:
        """The lock file let go (the CPU may be kept by another loop), and this process's threads
        that were kept off it allowed on it again (a process that serves again starts as it began)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self.cpu is None:
            return
        every = self.others | {self.cpu}
        for tid in os.listdir("/proc/self/task"):
            try:
                if os.sched_getaffinity(int(tid)) == self.others:
                    os.sched_setaffinity(int(tid), every)
            except OSError:  # ended meanwhile
                continue
        self.cpu = None
