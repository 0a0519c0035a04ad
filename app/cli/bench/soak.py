"""The soak: the live service for a long time, its memory growth and loop rate (`omniformation soak`)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from app.files import load_scenario
from app.processes import steal_seconds

from app.cli.bench.browsers import VIEWER


class GcPauses:
    """How long each of Python's garbage collections held the interpreter (gc.callbacks): a
    full collection walks every tracked object holding the GIL: no other Python thread runs,
    the loop's included."""

    def __init__(self) -> None:
        import gc

        self._gc = gc
        self._began = 0.0
        self.window: list[float] = []  # seconds of each collection since the last take()
        self.worst = (0.0, 0)  # seconds, generation
        self.counts = [0, 0, 0]
        gc.callbacks.append(self._on)

    def _on(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._began = time.perf_counter()
            return
        took, gen = time.perf_counter() - self._began, info["generation"]
        self.window.append(took)
        self.counts[gen] += 1
        if took > self.worst[0]:
            self.worst = (took, gen)

    def take(self) -> float:
        """The longest collection since the last take(), in seconds."""
        worst, self.window = max(self.window, default=0.0), []
        return worst

    def close(self) -> None:
        self._gc.callbacks.remove(self._on)


def _stolen_s() -> float:
    """CPU time the hypervisor gave to others while this machine's CPUs wanted it, since boot
    (app.processes.steal_seconds); 0 where there is no such count."""
    stolen = steal_seconds()
    return 0.0 if stolen is None else stolen


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def _per_hour(minutes: Any, values: Any) -> float:
    """The least-squares slope of ``values`` against ``minutes``, per hour."""
    return float(np.polyfit(np.asarray(minutes, dtype=float), np.asarray(values, dtype=float), 1)[0]) * 60


def run_soak(minutes: float, browsers: int = 1, print_fn: Callable[[str], None] = print,
             scenario: str | None = None) -> dict[str, float]:
    """The live service as `make run` serves it (or `run --scenario SCENARIO`), recording to a
    temporary folder, with ``browsers`` low-priority Chromium pages connected; samples every 10 s."""
    import shutil
    import subprocess
    import sys
    import tempfile
    import time as _time
    from pathlib import Path

    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.live.loop import CATCH_UP_S
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.services.recording import start_recording


    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    sc = load_scenario(scenario) if scenario else None
    svc = Service(host="127.0.0.1", port=0, scenario=sc, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics)
    folder = Path(tempfile.mkdtemp(prefix="omniformation-soak-"))
    recorder = start_recording(svc, config, sc, scenario, config.camera(), 10.0, folder / "soak.mcap")
    svc.start()
    viewer = None
    chromium = shutil.which("chromium")
    from app.memory import native_heap_mb, python_heap_mb

    samples: list[tuple[float, float, float]] = []  # (minutes, RSS MB, loop Hz over the last 10 s)
    stalls: list[tuple[float, float, float, int]] = []  # the window's longest tick gap, steal, longest gc (s), ticks skipped
    heaps: list[tuple[float, float, float]] = []  # glibc's heap: in use, free inside, mmapped (MB)
    pythons: list[tuple[float, float, float, int]] = []  # each minute: (minutes, pymalloc's arenas MB, in objects MB, threads)
    pauses = GcPauses()
    try:
        if browsers and chromium:
            viewer = subprocess.Popen([sys.executable, "-c", VIEWER, chromium, svc.url, str(browsers)],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            ready = viewer.stdout.readline() if viewer.stdout else ""
            if "ready" not in ready:
                raise RuntimeError(f"the browser did not come up: {ready.strip()!r}")
        start = _time.monotonic()
        tick0, t0, stolen0, dropped0 = svc.loop.tick_count, start, _stolen_s(), svc.loop.ticks_dropped
        svc.loop.take_longest_gap()
        while _time.monotonic() - start < minutes * 60:
            _time.sleep(10.0)
            now, ticks = _time.monotonic(), svc.loop.tick_count
            samples.append(((now - start) / 60, _rss_mb(), (ticks - tick0) / (now - t0)))
            stolen = _stolen_s()
            dropped = svc.loop.ticks_dropped
            stalls.append((svc.loop.take_longest_gap(), stolen - stolen0, pauses.take(), dropped - dropped0))
            tick0, t0, stolen0, dropped0 = ticks, now, stolen, dropped
            m, rss, hz = samples[-1]
            gap, steal, gc_s, skipped = stalls[-1]
            heap = native_heap_mb()
            if heap is not None:
                heaps.append(heap)
            print_fn(f"  {m:6.1f} min  RSS {rss:7.1f} MB  loop {hz:6.2f} Hz (longest gap {gap * 1e3:4.0f} ms,"
                     f" steal {steal * 1e3:4.0f} ms, gc {gc_s * 1e3:5.1f} ms" + (f", {skipped} ticks skipped" if skipped else "") + ")"
                     + ("" if heap is None else f"  heap: in use {heap[0]:6.1f} MB, free {heap[1]:5.1f} MB,"
                                                f" mmapped {heap[2]:5.1f} MB"))
            if len(samples) % 6 == 0:  # once a minute: pymalloc's report walks every arena
                py = python_heap_mb()
                if py is not None:
                    pythons.append((m, *py))
                    print_fn(f"  {m:6.1f} min  python: arenas {py[0]:6.1f} MB, in objects {py[1]:6.1f} MB; threads {py[2]}")
    finally:
        pauses.close()
        if viewer is not None:
            if viewer.stdin:
                viewer.stdin.close()
            viewer.wait(60)
        svc.close()
        recorder.close()
        size = sum(p.stat().st_size for p in folder.glob("*.mcap"))
        shutil.rmtree(folder, ignore_errors=True)
    # Warm-up: the charts keep their longest window (5 min) of ticks, so the first minutes grow by
    # design; the fit starts once that history is full, a minute later.
    from app.dashboard.plots import KEPT_S

    warm_min = KEPT_S / 60 + 1.0
    steady = [s for s in samples if s[0] >= warm_min] or samples
    minutes_at = np.array([s[0] for s in steady])
    rss_at = np.array([s[1] for s in steady])
    slope = _per_hour(minutes_at, rss_at) if len(steady) >= 2 else 0.0
    rates = [s[2] for s in samples[1:]] or [s[2] for s in samples] or [0.0]
    if len(heaps) == len(samples) and len(steady) >= 2:  # where the growth is: held by C code, or fragmentation
        cut = len(samples) - len(steady)
        grow = [_per_hour(minutes_at, [h[k] for h in heaps[cut:]]) for k in range(3)]
        print_fn(f"soak: glibc heap per hour: in use {grow[0]:+.2f} MB, free inside {grow[1]:+.2f} MB,"
                 f" mmapped {grow[2]:+.2f} MB (the rest of RSS: Python's own arenas, libraries' own allocators)")
    later = [p for p in pythons if p[0] >= warm_min]
    if len(later) >= 2:
        at = np.array([p[0] for p in later])
        arenas, objects = (_per_hour(at, [p[k] for p in later]) for k in (1, 2))
        print_fn(f"soak: Python's allocator per hour: arenas {arenas:+.2f} MB, live objects {objects:+.2f} MB;"
                 f" threads {later[0][3]} -> {later[-1][3]}")
    slow = [(s, st) for s, st in zip(samples[1:], stalls[1:]) if abs(s[2] - 30.0) > 0.3]
    print_fn(f"soak: {len(slow)} of {len(rates)} windows outside 29.7..30.3 Hz" + "".join(
        f"; {s[0]:.1f} min {s[2]:.2f} Hz (longest gap {st[0] * 1e3:.0f} ms, steal {st[1] * 1e3:.0f} ms, gc {st[2] * 1e3:.0f} ms,"
        f" {st[3]} ticks skipped)" for s, st in slow[:10]))
    print_fn(f"soak: {svc.loop.ticks_dropped} ticks skipped in all (the loop more than {CATCH_UP_S * 1e3:.0f} ms behind its"
             f" schedule, in {sum(1 for st in stalls if st[3])} windows), {svc.loop.tick_count} run")
    if len(steady) >= 4:  # does the growth slow down (filling up) or hold (a leak)?
        half = len(steady) // 2
        late = _per_hour(minutes_at[half:], rss_at[half:])
        print_fn(f"soak: RSS growth over the later half (from {minutes_at[half]:.0f} min) {late:+.2f} MB per hour")
    print_fn(f"soak: garbage collections {pauses.counts[0]} / {pauses.counts[1]} / {pauses.counts[2]} (generation 0 / 1"
             f" / 2), the longest {pauses.worst[0] * 1e3:.1f} ms (generation {pauses.worst[1]})")
    print_fn(f"soak: {minutes:g} min, {browsers} browser(s), recording {size / 1e6:.0f} MB: RSS growth {slope:+.2f} MB"
             f" per hour after the first {warm_min:g} min (the charts' 5-min history full; target <= 2); loop {min(rates):.2f}..{max(rates):.2f} Hz in 10 s"
             " windows (target within 1 % of 30 Hz: 29.7..30.3)")
    return {"rss_growth_mb_per_h": slope, "hz_min": min(rates), "hz_max": max(rates),
            "ticks_skipped": float(svc.loop.ticks_dropped)}
