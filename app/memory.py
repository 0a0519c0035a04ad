"""Bounded native memory for a service that runs for hours.

glibc's malloc raises its mmap threshold each time a large block is freed (up to 32 MiB), so
after the first camera frame (640 × 480 × 3 = 900 KiB) is freed, frames come from the heap
arenas instead of fresh mappings; with several threads (the loop, the web server, the
recorder) each holding an arena, the freed space is fragmented and the resident size creeps
up over hours though nothing leaks. A fixed threshold keeps every block over 64 KiB in its
own mapping, returned to the system when freed (the recorder's second-long chunks of ticks,
100-200 KiB each, and the buffers that grow to hold them among them: at 256 KiB they stayed in
the heaps, and the heaps' free space grew 1.6 MB an hour), and two arenas bound the fragmentation
(mallopt(3), M_MMAP_THRESHOLD and M_ARENA_MAX). What is freed inside a heap's pages is given
back once a minute (malloc_trim(3), from a thread of its own: never the robots' loop).
Elsewhere than glibc this does nothing.

Python's own heap (``bound_python_heap``): the service starts with some 700,000 objects the
garbage collector tracks (modules, compiled kernels, the page's elements), so its automatic
full collection (the oldest generation, due when a quarter of that many objects more have
aged into it) does not come in hours: a one-hour soak saw none. Only a full collection empties
the interpreter's free lists (about 18,000 blocks here) and frees the cycles that aged into the
oldest generation, so until then the small-object heap creeps up. Once the service has run a
minute, what start-up made is frozen (gc.freeze: never scanned again, kept for the process's
life, as it would be anyway) and a full collection runs once a minute: it scans only what was
made since (about 2 ms here), from a thread of its own (the soak reports its pauses).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys
import threading

M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
MMAP_THRESHOLD_BYTES = 64 * 1024
ARENAS = 2
TRIM_EVERY_S = 60.0

FREEZE_AFTER_S = 60.0
COLLECT_EVERY_S = 60.0

_done = False
_trimmer: threading.Thread | None = None
_collector: threading.Thread | None = None
_collector_lock = threading.Lock()  # services may be made on several threads (a fleet's)


def bound_native_heap() -> bool:
    """Set glibc's malloc for a long-running service, once per process; whether it took."""
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    _done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_ARENA_MAX, ARENAS))
    trim = getattr(libc, "malloc_trim", None)
    global _trimmer
    if _done and trim is not None and _trimmer is None:
        trim.argtypes = [ctypes.c_size_t]
        trim.restype = ctypes.c_int
        stop = threading.Event()

        def trimming() -> None:
            while not stop.wait(TRIM_EVERY_S):
                trim(0)

        _trimmer = threading.Thread(target=trimming, name="omniformation-malloc-trim", daemon=True)
        _trimmer.start()
    return _done


def bound_python_heap() -> None:
    """Freeze what start-up made after ``FREEZE_AFTER_S`` and run a full garbage collection every
    ``COLLECT_EVERY_S`` from then on (see the module's notes), once per process."""
    global _collector

    def collecting() -> None:
        done = threading.Event()  # never set: the thread lives as long as the process (a daemon)
        done.wait(FREEZE_AFTER_S)
        gc.freeze()  # no full collection first: over all of start-up's objects it would hold the loop
        while not done.wait(COLLECT_EVERY_S):
            gc.collect()

    with _collector_lock:
        if _collector is not None:
            return
        _collector = threading.Thread(target=collecting, name="omniformation-gc", daemon=True)
        _collector.start()


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def native_heap_mb() -> tuple[float, float, float] | None:
    """glibc's own account of its heap (mallinfo2(3), glibc 2.33+): (MB in use in the heap
    arenas, MB free inside them, MB in mmapped blocks); None elsewhere. Growth of the first is
    memory held natively (by a C library); of the second, fragmentation."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    fn.restype = _MallInfo2
    info = fn()
    return info.uordblks / 1e6, info.fordblks / 1e6, info.hblkhd / 1e6


def python_heap_mb() -> tuple[float, float, int] | None:
    """Python's own small-object allocator (pymalloc), as ``sys._debugmallocstats()`` reports it:
    (MB in the arenas it holds from the system, MB of those in live objects, the process's
    threads); None where that report is missing. Growth of the second is live Python objects;
    of the first alone, arenas kept by a few objects each (fragmentation); of the threads,
    stacks. The report goes to file descriptor 2, so for the moment it takes (milliseconds)
    that descriptor points at a temporary file; whatever else was written meanwhile is passed on.
    For a measuring run (the soak), not for a service."""
    import os
    import re
    import tempfile

    report = getattr(sys, "_debugmallocstats", None)
    if report is None:
        return None
    with tempfile.TemporaryFile() as tmp:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            os.dup2(tmp.fileno(), 2)
            report()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode("utf-8", "replace")
    start, end = text.find("Small block threshold"), text.find("arena map counts")
    tails = list(re.finditer(r"[^\n]*each =\s*[\d,]+\n", text))  # the report's last part: free lists
    if start < 0 or end < 0:
        if text:
            os.write(2, text.encode())
        return None
    stop = tails[-1].end() if tails else len(text)
    others = text[:start] + text[stop:]
    if others.strip():  # another thread's words, written meanwhile
        os.write(2, others.encode())

    def number(label: str) -> int | None:
        m = re.search(rf"# {label}\s*=\s*([\d,]+)", text[start:end])
        return int(m.group(1).replace(",", "")) if m else None

    arenas, in_blocks = number("arenas allocated current"), number("bytes in allocated blocks")
    if arenas is None or in_blocks is None:
        return None
    try:
        with open("/proc/self/status") as f:
            threads = next(int(line.split()[1]) for line in f if line.startswith("Threads:"))
    except (OSError, StopIteration, ValueError):
        threads = threading.active_count()
    return arenas * 1048576 / 1e6, in_blocks / 1e6, threads
