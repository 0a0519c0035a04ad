"""Real-time scheduling for the threads on a frame's way to the robots (``run --realtime``).

On a shared machine the operating system may keep the loop off the CPU for several
milliseconds while other programs run (a browser, a compiler): measured here, the
frame-to-command latency's p99 is 10-15 ms at normal priority with a browser attached and
4-5 ms with the camera and loop threads on SCHED_FIFO and a 1 ms GIL switch interval
(``omniformation bench --latency``). Linux keeps 5 % of every second for other tasks however busy a real-time
thread is (``kernel.sched_rt_runtime_us``), and both threads sleep between frames.

Asking needs the right to (root, CAP_SYS_NICE, or an ``rtprio`` limit): refused, the thread
stays as it was and the reason is said once."""

from __future__ import annotations

import os

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
