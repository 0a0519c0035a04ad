"""`omniformation bench`: speed figures, as ratios and medians within one run.

These machines are shared and noisy, so nothing here is asserted by tests;
each figure is the median of several repeats. It lives in the app package
(not a loose script) so the installed console script can run it anywhere.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import time
from collections.abc import Callable

import argparse
from typing import Any

import numpy as np

from app.cli.args import Parser, float_in, int_in
from app.files import load_scenario


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    bench = sub.add_parser("bench", help="measure controller, vision, simulator and live-loop speed")
    bench.add_argument("--long-recording", type=float_in(1.0, 24 * 60, "min"), metavar="MINUTES",
                       help="instead: write a live-like recording this long (vision in the loop, 3 followers, frames at"
                            " 10 Hz) and measure report (peak memory, time) and replay (open, first frame, seeks) on it")
    bench.add_argument("--latency", type=float_in(2.0, 3600.0, "s"), metavar="SECONDS",
                       help="instead: frame-to-command latency for this long on a real rig's path: a 30 fps folder of"
                            " the synthetic rig's pictures, the serial link to emulated robots on a pty, recording on,"
                            " a browser attached; at normal priority, then as run --realtime")
    bench.set_defaults(func=cmd_bench)
    soak = sub.add_parser("soak", help="run the live service for a long time and measure memory growth and loop rate",
                          description="What `make run` serves (vision in the loop, recording on), one browser"
                                      " connected, for --minutes: the process's RSS and the loop's rate every"
                                      " 10 s, and the RSS growth per hour after the first two minutes.")
    soak.add_argument("--minutes", type=float_in(0.5, 24 * 60, "min"), default=60.0, help="how long (default 60)")
    soak.add_argument("--browsers", type=int_in(0, 3), default=1, help="browsers connected (default 1)")
    soak.add_argument("--scenario", help="run this scenario (e.g. obstacle_course: the scan, the filter and the goal mode"
                                         " all on) instead of the built-in team")
    soak.set_defaults(func=cmd_soak)


def cmd_soak(args: argparse.Namespace) -> int:
    run_soak(args.minutes, args.browsers, scenario=args.scenario)
    return 0


class _GcPauses:
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
    (/proc/stat's steal, all CPUs); 0 where there is no such count."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


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

    from app.files import load_scenario

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
    pauses = _GcPauses()
    try:
        if browsers and chromium:
            viewer = subprocess.Popen([sys.executable, "-c", _VIEWER, chromium, svc.url, str(browsers)],
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


def cmd_bench(args: argparse.Namespace) -> int:
    if args.latency is not None:  # as `run` does by default, then as `run --realtime`
        bench_latency(args.latency)
        bench_latency(args.latency, realtime=True)
    elif args.long_recording is not None:
        bench_long_recording(args.long_recording)
    else:
        run_bench()
    return 0


def bench_latency(seconds: float, print_fn: Callable[[str], None] = print, browsers: int = 1,
                  realtime: bool = False) -> dict[str, float]:
    """Frame-to-command latency on a real rig's path: a folder of the synthetic rig's pictures of a
    team driving (experiment 1's first seconds, rendered) played at 30 fps, the vision pipeline,
    the serial link to emulated followers on a pty, recording on, ``browsers`` Chromium pages
    attached (on idle CPU, as in the soak). Latency is each tick's ``latency_ms``: the frame's
    arrival to its commands written to the link. ``realtime``: as ``run --realtime`` (the loop's and
    the camera's threads on SCHED_FIFO, app.realtime)."""
    import shutil
    import subprocess
    import sys
    import tempfile
    import time as _time
    from pathlib import Path

    import cv2

    from app.backends.camera import FolderSource
    from app.backends.hardware import HardwareTeam
    from app.backends.serial_link import SerialLink
    from app.contracts import Rig
    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_camera
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.services.recording import start_recording
    from core.camera.render import Renderer
    from core.geometry import heading_world_to_leader, world_to_leader
    from core.sim.stepped import simulate_stepped

    folder = Path(tempfile.mkdtemp(prefix="omniformation-latency-"))
    frames_dir = folder / "frames"
    frames_dir.mkdir()
    scenario = load_scenario("experiment1")
    run = simulate_stepped(scenario.replace(duration_s=min(seconds, 20.0)))  # truth feedback: the team as it drives
    model = load_camera(SYNTHETIC_CAMERA)  # the pictures; the service reads them with the calibration
    rig = load_camera(SYNTHETIC_CALIBRATED)
    assert model.model is not None
    renderer = Renderer(model.model, model.render)
    rng = np.random.default_rng(0)
    log = run.log
    count = min(len(log.t), int(seconds * 30) + 1)
    for k in range(count):
        theta = float(log.leader[k, 2])
        p = world_to_leader(log.followers_world[k, :, :2], log.leader[k, :2], theta)
        a = heading_world_to_leader(log.followers_world[k, :, 2], theta)
        cv2.imwrite(str(frames_dir / f"f{k:05d}.png"),
                    renderer.render(np.array([0.0, 0.0, np.pi / 2]), np.column_stack([p, a]), k / 30, rng))
    print_fn(f"latency: {count} frames of the synthetic rig rendered; playing them at 30 fps"
             f" (looped) for {seconds:g} s")
    # the robots are not in the service's process on a real rig: the emulator runs in its own
    emu = subprocess.Popen([sys.executable, "-m", "app.cli", "emulate-follower", "--pty", "--followers", "2",
                            "--seed", "3"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert emu.stdout is not None
    pty_path = emu.stdout.readline().split(" on ", 1)[1].strip()
    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    link = SerialLink(pty_path, 2)
    source = FolderSource(frames_dir, fps=30.0, loop=True)
    camera = Rig(rig, rig.require_gamma())
    svc = Service(host="127.0.0.1", port=0, n_followers=2, rate_hz=30.0, camera=camera, frames=source,
                  hardware=HardwareTeam(2, link), realtime=realtime)
    recorder = start_recording(svc, config, None, None, camera, 10.0, folder / "latency.mcap")
    latencies: list[float] = []
    phases: list[str] = []
    fresh: list[bool] = []
    def keep(state: Any) -> None:
        latencies.append(state.latency_ms)
        phases.append(state.phase)
        fresh.append(state.fresh)

    svc.loop.subscribe(keep)
    svc.start()
    viewer = None
    chromium = shutil.which("chromium")
    try:
        if browsers and chromium:
            viewer = subprocess.Popen([sys.executable, "-c", _VIEWER, chromium, svc.url, str(browsers)],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert viewer.stdout is not None
            viewer.stdout.readline()  # "ready": the page is up
        else:
            print_fn("latency: no browser attached (needs Debian's chromium and playwright: make test installs both)")
        latencies.clear()
        phases.clear()
        fresh.clear()
        _time.sleep(seconds)
    finally:
        if viewer is not None:
            viewer.communicate("", timeout=60)
        svc.close()
        recorder.close()
        emu.terminate()
        emu.communicate(timeout=10)
        shutil.rmtree(folder, ignore_errors=True)
    n = min(len(latencies), len(phases), len(fresh))
    values = np.array([latencies[k] for k in range(n) if fresh[k] and np.isfinite(latencies[k])])
    stale = np.array([latencies[k] for k in range(n) if not fresh[k] and np.isfinite(latencies[k])])
    tracking = np.array([latencies[k] for k in range(n) if fresh[k] and phases[k] == "tracking"])
    p50, p99 = (float(np.percentile(values, q)) for q in (50, 99)) if len(values) else (float("nan"),) * 2
    how = f"the loop {svc.loop.priority}" if realtime else "normal priority"
    print_fn(f"frame-to-command latency ({how}): p50 {p50:.2f} ms, p99 {p99:.2f} ms ({len(values)} ticks on a"
             f" new frame, {len(values) / seconds:.1f} Hz; target p99 <= 5 ms)")
    if len(tracking):
        print_fn(f"  while tracking: p50 {np.percentile(tracking, 50):.2f} ms, p99 {np.percentile(tracking, 99):.2f} ms"
                 f" ({len(tracking)} ticks)")
    if len(stale):
        print_fn(f"  {len(stale)} ticks ran on a late camera (no new frame within 1.5 periods): the observation they"
                 f" acted on was {np.median(stale):.0f} ms old (median)")
    return {"p50_ms": p50, "p99_ms": p99, "ticks": float(len(values)), "late_ticks": float(len(stale))}


def write_long_recording(path: Any, minutes: float) -> tuple[int, float]:
    """A recording as `run` makes one: the live loop with vision in the loop on the synthetic
    camera (3 followers, the leader on eq. 39's turns, then straight), frames at 10 Hz, stepped as fast as
    the machine goes (lossless writer). (ticks, seconds it took)."""
    import time as _time

    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.live.loop import ServiceLoop
    from app.params import MAX_FOLLOWERS, ParamsStore, default_slots
    from app.recording.writer import Recorder

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    from app.params import Params

    store = ParamsStore(Params(n_followers=3, slots=default_slots(3), leader_mode="eq39"))
    loop = ServiceLoop(store, rate_hz=30.0, seed=3, dynamics=config.dynamics, camera=config.camera())
    rec = Recorder(path, {"scenario": "long", "command": "omniformation bench --long-recording"}, store.get(),
                   frame_rate_hz=10.0, lossless=True)
    loop.subscribe(rec.on_tick)
    n = int(minutes * 60 * 30)
    start = _time.monotonic()
    try:
        for _ in range(n):
            loop.tick()
    finally:
        loop.halt_followers()
        rec.close()
    return n, _time.monotonic() - start


def bench_long_recording(minutes: float, print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """report and replay on a long recording: peak memory and time of `report` (a fresh process),
    and the time replay takes to open it, to show the first frame and to seek."""
    import resource
    import subprocess
    import sys
    import tempfile
    import time as _time
    from pathlib import Path

    folder = Path(tempfile.mkdtemp(prefix="omniformation-long-"))
    path = folder / "long.mcap"
    print_fn(f"writing a {minutes:g}-minute live-like recording ...")
    ticks, took = write_long_recording(path, minutes)
    size = path.stat().st_size
    print_fn(f"  {ticks} ticks, {size / 1e6:.0f} MB in {took:.0f} s")
    damage_table(path, minutes, print_fn)
    t0 = _time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "app.cli", "report", str(path), "--out", str(folder / "report")],
                          capture_output=True, text=True)
    report_s = _time.monotonic() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e3
    if proc.returncode != 0:
        print_fn(f"report failed: {proc.stderr.strip()[-300:]}")
    print_fn(f"report: {report_s:.1f} s, peak RSS {peak_mb:.0f} MB (targets for a 1-hour recording: <= 90 s,"
             " <= 400 MB)")
    # replay in a fresh process too: its own peak memory, not this one's (which wrote the file)
    proc = subprocess.run([sys.executable, "-c", "import sys; from app.cli.bench import replay_probe;"
                           " replay_probe(sys.argv[1])", str(path)], capture_output=True, text=True)
    if proc.returncode != 0:
        print_fn(f"replay failed: {proc.stderr.strip()[-300:]}")
        return {"report_s": report_s, "report_peak_mb": peak_mb}
    probe = json.loads(proc.stdout.strip().splitlines()[-1])
    print_fn(f"replay: open and first frame {probe['first_s']:.2f} s (target <= 5 s; frame {probe['frame']});"
             f" seek anywhere median {probe['seek_median_s']:.2f} s, max {probe['seek_max_s']:.2f} s (target <= 1 s);"
             f" peak RSS {probe['peak_mb']:.0f} MB after {probe['seeks']} seeks")
    import shutil

    shutil.rmtree(folder, ignore_errors=True)
    return {"report_s": report_s, "report_peak_mb": peak_mb, "replay_first_s": probe["first_s"],
            "replay_seek_max_s": probe["seek_max_s"], "replay_peak_mb": probe["peak_mb"]}


def damage_table(path: Any, minutes: float, print_fn: Callable[[str], None] = print,
                 flip_counts: tuple[int, ...] = (10, 100), seed: int = 7) -> list[dict[str, float]]:
    """Random bytes of a long recording flipped (10, then 100): per file, the chunks damaged, the
    ticks and frames lost (said by the reader, and checked against the whole file), whether the
    loss stays within one second per damaged chunk, and whether replay opens it. Also the
    writer's chunk count per hour (each costs it 48 bytes of memory until the file closes)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from app.recording.reader import _Scan, read_recording

    whole = read_recording(Path(path))
    size = Path(path).stat().st_size
    with open(path, "rb") as f:
        f.read(8)
        scan = _Scan(f, size)
        scan.run()
    chunks = len(scan.places)
    print_fn(f"writer: {chunks} chunks in {minutes:g} min ({chunks * 60 / minutes:.0f} an hour: its chunk index"
             f" holds {chunks * 60 / minutes * 48 / 1e3:.0f} KB an hour until the file closes)")
    all_ticks = set(whole.tick_numbers.tolist())
    dt = whole.tick_dt()
    rows = []
    rng = np.random.default_rng(seed)
    for count in flip_counts:
        bad = Path(path).with_name(f"flipped-{count}.mcap")
        shutil.copyfile(path, bad)
        with open(bad, "r+b") as f:
            for at in rng.integers(8, size, count):
                f.seek(int(at))
                byte = f.read(1)
                f.seek(int(at))
                f.write(bytes([byte[0] ^ int(rng.integers(1, 256))]))
        rec = read_recording(bad)
        lost = len(all_ticks - set(rec.tick_numbers.tolist()))
        damaged = sum(1 for d in rec.damage if not d.why.startswith("cut off"))
        frames_lost = len(whole.frame_t) - len(rec.frame_t)
        probe = subprocess.run([sys.executable, "-c", "import sys; from app.cli.bench import replay_probe;"
                                " replay_probe(sys.argv[1], 5)", str(bad)], capture_output=True, text=True)
        row = {"flips": count, "damaged_chunks": damaged, "lost_ticks": lost, "lost_s": lost * dt,
               "said_ticks": rec.lost_ticks, "frames_lost": frames_lost, "replay_opens": probe.returncode == 0}
        rows.append(row)
        print_fn(f"damage: {count} random flips: {damaged} damaged chunks; {lost} ticks lost ({lost * dt:.2f} s; the"
                 f" reader says {rec.lost_ticks}, {rec.lost_s:.2f} s), {frames_lost} of {len(whole.frame_t)} frames"
                 f" lost; within 1 s per damaged chunk: {'yes' if lost * dt <= damaged * 1.0 + 1e-6 else 'NO'};"
                 f" replay opens it: {'yes' if probe.returncode == 0 else 'NO: ' + probe.stderr.strip()[-200:]}")
        rec.close()
        bad.unlink()
    whole.close()
    return rows


def replay_probe(path: str, seeks: int = 100) -> None:
    """Open a recording for replay, show its first tick, then seek to `seeks` random places (the
    timeline's seek: the plots' last 60 s and the state there); print the times and this
    process's peak RSS as one JSON line (bench --long-recording runs it in a fresh process)."""
    import resource
    from pathlib import Path

    from app.recording.reader import read_recording
    from app.services.replay import ReplayService

    t0 = time.monotonic()
    rec = read_recording(Path(path))
    svc = ReplayService(rec, host="127.0.0.1", port=0)
    first = svc.state_at(0)  # the first tick with its frame, as published when the page opens
    first_s = time.monotonic() - t0
    times = []
    rng = np.random.default_rng(0)
    for k in rng.integers(0, len(rec.ticks), seeks):
        t1 = time.monotonic()
        svc.seek(int(k))
        times.append(time.monotonic() - t1)
    svc.close()
    rec.close()
    print(json.dumps({"first_s": first_s, "frame": first.frame is not None, "seek_median_s": float(np.median(times)),
                      "seek_max_s": max(times), "seeks": seeks,
                      "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3}))


def _median_seconds(fn: Callable[[], object], repeats: int, inner: int) -> float:
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - t0) / inner)
    return statistics.median(samples)


def bench_controller(n: int, rng: np.random.Generator) -> float:
    """Median seconds of one compute_commands tick for n followers (per-tick API, as the loop calls it)."""
    from core.control.formation import ControllerState, compute_commands
    from core.types import Gains

    p = rng.uniform(-1.5, 1.5, (n, 2))
    a = rng.uniform(-np.pi, np.pi, n)
    p_d = rng.uniform(-1.5, 1.5, (n, 2))
    p_d_dot = np.zeros((n, 2))
    gains = Gains()
    state = ControllerState.initial(n)
    compute_commands(p, a, p_d, p_d_dot, 0.06, 0.02, gains, state, 0.01)  # compile / warm up
    inner = max(1, 20000 // max(n, 1))
    return _median_seconds(
        lambda: compute_commands(p, a, p_d, p_d_dot, 0.06, 0.02, gains, state, 0.01), 7, inner
    )


def bench_safety_filter(n: int) -> float:
    """Median ms of one safety-filter solve for n followers packed on a 0.3 m grid ahead of the
    leader, all driving forward (every pair constraint written, most active)."""
    from core.control.safety import filter_commands
    from core.types import Commands

    rng = np.random.default_rng(0)
    side = int(np.ceil(np.sqrt(n)))
    p = np.array([(i % side, i // side) for i in range(n)], dtype=float) * 0.3 - side * 0.15 + np.array([0.0, 2.0])
    a = rng.uniform(-np.pi, np.pi, n)
    c = Commands(np.full(n, 0.2), np.zeros(n))
    filter_commands(p, a, c, (0.05, 0.0), limits=(0.3, 2.0))  # imports and first solve
    return _median_seconds(lambda: filter_commands(p, a, c, (0.05, 0.0), limits=(0.3, 2.0)), 7, 10) * 1e3


def bench_paper_simulation() -> tuple[float, float]:
    """(wall seconds, simulated seconds) of paper_simulation at 100 Hz with ground truth."""
    from core.sim.run import simulate

    scenario = load_scenario("paper_simulation").replace(rate_hz=100.0)
    simulate(scenario.replace(duration_s=1.0))  # compile / warm up
    wall = _median_seconds(lambda: simulate(scenario), 5, 1)
    return wall, scenario.duration_s


def bench_render(n_followers: int = 6) -> tuple[float, float, float]:
    """Median ms of one synthetic 640x480 frame with n followers (default settings: noise, blur,
    drift, clutter), the same with a JPEG round trip, and one BGR->HSV conversion of it."""
    import math

    import cv2

    from app.files import SYNTHETIC_CAMERA, load_camera
    from core.camera.synthetic import renderer_for

    rig = load_camera(SYNTHETIC_CAMERA)
    plain = renderer_for(rig, jpeg_quality=0)
    jpeg = renderer_for(rig, jpeg_quality=85)
    rng = np.random.default_rng(1)
    ang = np.linspace(0, 2 * math.pi, n_followers, endpoint=False)
    followers = np.column_stack([np.cos(ang), np.sin(ang), ang])
    step = [0]

    def frame(r: Any) -> np.ndarray:
        step[0] += 1
        k = step[0]
        return np.asarray(r.render(np.array([0.01 * k, 0.0, 1.0 + 0.003 * k]), followers, k / 30.0, rng))

    frame(plain)
    img = frame(jpeg)
    render_s = _median_seconds(lambda: frame(plain), 9, 30)
    jpeg_s = _median_seconds(lambda: frame(jpeg), 5, 20)
    hsv_s = _median_seconds(lambda: cv2.cvtColor(img, cv2.COLOR_BGR2HSV), 9, 50)
    return render_s * 1e3, jpeg_s * 1e3, hsv_s * 1e3


def _ring_team(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n followers on rings 0.5..1.7 m from the leader, at least 0.35 m apart."""
    import math

    p: list[tuple[float, float]] = []
    a: list[float] = []
    radius, k = 0.5, 0
    while len(p) < n:
        per_ring = max(1, int(2 * math.pi * radius / 0.4))
        for j in range(per_ring):
            if len(p) == n:
                break
            ang = 2 * math.pi * j / per_ring + 0.3 * k
            p.append((-radius * math.sin(ang), radius * math.cos(ang)))
            a.append(ang + math.pi / 2)
        radius += 0.4
        k += 1
    return np.array(p), np.array(a)


def bench_pipeline(n: int) -> tuple[float, float]:
    """(median ms of one pipeline step in formation tracking for n followers at 640x480,
    median ms of one BGR->HSV conversion of the same frame). The pipeline gets there through
    its real start-up manoeuvres on rendered frames."""
    import cv2

    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_camera
    from core.camera.render import RenderSettings, Renderer
    from core.sim.team import make_team_state, step_team
    from core.geometry import heading_world_to_leader, world_to_leader
    from core.types import Commands
    from core.vision.pipeline import VisionPipeline

    rig = load_camera(SYNTHETIC_CAMERA)
    gamma = load_camera(SYNTHETIC_CALIBRATED).gamma
    assert rig.model is not None and gamma is not None
    hues = tuple(float(h) for h in np.linspace(0, 360, 12, endpoint=False)) if n > 8 else rig.render.hues_deg
    renderer = Renderer(rig.model, RenderSettings(**{**rig.render.__dict__, "hues_deg": hues, "clutter": False, "distractor": False}))
    p0, a0 = _ring_team(n)
    state = make_team_state(p0, a0)
    pipe = VisionPipeline(n, gamma, rig.working_area, rig.detect, (rig.model.width, rig.model.height), np.random.default_rng(0))
    rng = np.random.default_rng(0)
    dt, t = 1 / 30, 0.0
    cmd = np.zeros((n, 2))

    def frame() -> np.ndarray:
        th = float(state.leader[2])
        p = world_to_leader(state.followers[:, :2], state.leader[:2], th)
        a = np.asarray(heading_world_to_leader(state.followers[:, 2], th))
        return renderer.render(state.leader, np.column_stack([p, a]), t, rng)

    while True:
        out = pipe.step(frame(), dt, (0.0, 0.0, 0.0), cmd)
        if out.ready:
            break
        assert out.manoeuvre is not None  # not ready: the pipeline still drives
        cmd = out.manoeuvre
        state = step_team(state, Commands(cmd[:, 0].copy(), cmd[:, 1].copy()), (0.0, 0.0), dt, t, rng)
        t += dt
    frames = [frame() for _ in range(8)]
    i = [0]

    def one() -> None:
        i[0] += 1
        pipe.step(frames[i[0] % len(frames)], dt, (0.0, 0.0, 0.0), np.zeros((n, 2)))

    step_s = _median_seconds(one, 7, 20)
    hsv_s = _median_seconds(lambda: cv2.cvtColor(frames[0], cv2.COLOR_BGR2HSV), 7, 50)
    return step_s * 1e3, hsv_s * 1e3


def bench_vision_loop(seconds: float = 20.0, runs: int = 5) -> tuple[float, float, float]:
    """Vision-in-the-loop simulation of experiment1 at 30 Hz, start-up manoeuvres included,
    as multiples of real time: (best of ``runs`` runs, their median, the process's first run).

    The first run in a process also pays one-time costs (numba loading its compiled kernels
    from the disk cache, OpenCV's first calls) that a longer simulation spreads thinner, so
    it is kept out of the others. A whole run's wall time takes in every moment another tenant
    of this shared machine held the CPU; as ``timeit`` advises, the best run is the figure for
    the code, and the median shows the machine.
    """
    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_camera
    from core.sim.vision_run import simulate_vision

    rig = load_camera(SYNTHETIC_CAMERA)
    gamma = load_camera(SYNTHETIC_CALIBRATED).gamma
    assert gamma is not None
    scenario = load_scenario("experiment1").replace(rate_hz=30.0, duration_s=seconds)
    multiples = []
    for _ in range(runs + 1):
        t0 = time.perf_counter()
        run = simulate_vision(scenario, rig, gamma)
        wall = time.perf_counter() - t0
        multiples.append(float(run.log.t[-1] - run.log.t[0]) / wall)
    return max(multiples[1:]), float(np.median(multiples[1:])), multiples[0]


def bench_free_space_scan() -> float:
    """Median ms of one free-space scan of a whole 640 x 480 synthetic frame with three boxes
    and three followers (core.vision.freespace)."""
    import math
    import time as _time
    from dataclasses import replace

    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_synthetic_rig
    from core.camera.render import Renderer
    from core.obstacles import Obstacle
    from core.sim.stepped import scan_settings_for
    from core.vision.freespace import FreeSpaceScanner

    rig, gamma = load_synthetic_rig(SYNTHETIC_CAMERA, SYNTHETIC_CALIBRATED)
    assert rig.model is not None
    boxes = (Obstacle(0.8, 0.9, 0.4, 0.3, 0.3), Obstacle(-1.0, 0.3, 0.3, 0.6), Obstacle(0.2, -1.3, 0.5, 0.2, 1.0))
    renderer = Renderer(rig.model, replace(rig.render, clutter=False, distractor=False), boxes)
    followers = np.array([[0.5, -0.5, 1.0], [-0.6, -0.4, 2.0], [0.0, 1.0, 0.0]])
    frame = renderer.render(np.array([0.0, 0.0, math.pi / 2]), followers, 0.0, np.random.default_rng(0))
    scanner = FreeSpaceScanner(gamma, rig.working_area, scan_settings_for(rig))
    tracked = np.ones(3, dtype=bool)
    scanner.scan(frame, followers[:, :2], tracked)  # compiled code loads
    times = []
    for _ in range(200):
        t0 = _time.perf_counter()
        scanner.scan(frame, followers[:, :2], tracked)
        times.append(_time.perf_counter() - t0)
    return float(np.median(times)) * 1e3


def run_bench(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    rng = np.random.default_rng(0)
    results: dict[str, float] = {}
    print_fn("controller step (eq. 3-12, per tick, median):")
    for n in (3, 100, 10_000):
        s = bench_controller(n, rng)
        results[f"controller_{n}_us"] = s * 1e6
        print_fn(f"  {n:>6} followers: {s * 1e6:10.1f} us   ({s * 1e9 / n:8.1f} ns per follower)")
    wall, simulated = bench_paper_simulation()
    results["paper_simulation_x_realtime"] = simulated / wall
    print_fn(
        f"paper_simulation at 100 Hz, ground truth: {wall * 1e3:.1f} ms for {simulated:.0f} s"
        f" = {simulated / wall:,.0f}x real time (target >= 2000x)"
    )
    render_ms, jpeg_ms, hsv_ms = bench_render(6)
    results["render_ms"], results["render_jpeg_ms"] = render_ms, jpeg_ms
    print_fn(
        f"synthetic frame 640x480, 6 followers: {render_ms:.2f} ms (target <= 3 ms); with a JPEG round trip"
        f" {jpeg_ms:.2f} ms; one BGR->HSV conversion of it {hsv_ms:.2f} ms"
    )
    print_fn("vision pipeline, formation tracking, 640x480 (median per frame; ratio to one BGR->HSV of the frame):")
    for n in (3, 10, 50):
        step_ms, hsv_ms = bench_pipeline(n)
        results[f"pipeline_{n}_ms"] = step_ms
        target = {3: "target <= 1 ms and <= 25x", 10: "", 50: "target <= 8 ms"}[n]
        print_fn(f"  {n:>3} followers: {step_ms:6.2f} ms = {step_ms / hsv_ms:5.1f}x HSV ({hsv_ms:.2f} ms)  {target}")
    for n in (6, 50):
        ms = bench_safety_filter(n)
        results[f"safety_filter_{n}_ms"] = ms
        print_fn(f"safety filter (barrier QP, {n} followers packed 0.3 m apart, all constraints written): {ms:.2f} ms"
                 f" per tick (target <= {1 if n == 6 else 5} ms)")
    ms = bench_free_space_scan()
    results["free_space_scan_ms"] = ms
    print_fn(f"free-space scan (640 x 480 frame, three boxes, three followers): {ms:.2f} ms per frame (target <= 1 ms)")
    best, median, first = bench_vision_loop()
    results["vision_loop_x_realtime"] = best
    results["vision_loop_median_x_realtime"], results["vision_loop_first_run_x_realtime"] = median, first
    print_fn(f"vision-in-the-loop simulation (experiment1, 30 Hz, start-up manoeuvres + 20 s): {best:.1f}x real time,"
             f" best of 5 runs (target >= 30x); median {median:.1f}x; the process's first run {first:.1f}x")
    truth_s, vision_s, alone_hz, sweeping_hz, points = bench_sweeps()
    results.update(sweep_truth_s=truth_s, sweep_vision_s=vision_s, loop_hz_before_sweep=alone_hz,
                   loop_hz_during_sweep=sweeping_hz)
    print_fn(f"5 x 5 sweep (k_w2 x k_f1, offset step, experiment1): truth feedback {truth_s:.1f} s (target <= 10 s),"
             f" vision in the loop {vision_s:.1f} s (target <= 120 s)")
    print_fn(f"live loop at 30 Hz (vision in the loop) while the page's worker sweeps ({points} points, vision):"
             f" {sweeping_hz:.2f} Hz ({(sweeping_hz / 30 - 1) * 100:+.1f} % of 30; target within 1 %);"
             f" {alone_hz:.2f} Hz before it")
    rates: tuple[float, float, float] | None | str
    try:
        rates = bench_loop_with_browsers()
    except Exception as exc:  # noqa: BLE001 - a browser that does not come up is a skipped figure, not a crash
        rates = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
    if isinstance(rates, str):
        print_fn(f"live loop with browsers: failed to open the pages ({rates})")
    elif rates is None:
        print_fn("live loop with browsers: skipped (needs Debian's chromium and playwright: make test installs both)")
    else:
        alone, served, watched = rates
        results["loop_hz_no_browser"], results["loop_hz_3_browsers_served"] = alone, served
        results["loop_hz_3_browsers_same_machine"] = watched
        print_fn(
            f"live loop at 30 Hz (vision in the loop): {alone:.2f} Hz with no browser; serving 3 browsers"
            f" {served:.2f} Hz ({(served / alone - 1) * 100:+.1f} %, target within 5 %); 3 browsers rendering"
            f" software WebGL on this same machine {watched:.2f} Hz ({(watched / alone - 1) * 100:+.1f} %)"
        )
    from app.cli.bench_foxglove import bench_foxglove  # Foxglove live's cost: a module of its own
    results.update(bench_foxglove(print_fn))
    from app.cli.bench_loop import bench_loops  # the loop against the page's clients: a module of its own
    results.update(bench_loops(print_fn, latency=bench_latency))
    try:
        import zenoh  # noqa: F401
    except ImportError:
        print_fn("fleet: skipped (needs eclipse-zenoh: make test installs it)")
        return results
    for keyed in (False, True):
        p50, p99, samples = bench_fleet_latency(keyed=keyed)
        results["fleet_state_latency_p99_ms" + ("_keys" if keyed else "")] = p99
        how = "with --keys (mutual TLS, access control)" if keyed else "open (tcp, no keys)"
        print_fn(f"fleet: a leader's state to the fleet page on loopback, {how}: median {p50:.2f} ms, p99 {p99:.2f} ms"
                 f" over {samples} states (target p99 <= 5 ms)")
    tick_ms = bench_arena_tick(10, 10)
    results["arena_tick_ms_10x10"] = tick_ms
    print_fn(f"fleet: arena step for 10 leaders x 10 followers (dynamics, truth, publish): {tick_ms:.2f} ms per tick"
             f" ({tick_ms / (1000 / 30) * 100:.0f} % of a 30 Hz tick)")
    held, slowest = bench_leader_processes()
    results["leader_processes_at_30hz"] = held
    print_fn(f"fleet: leader processes of 3 followers in one arena (vision in the loop, each camera rendered from the"
             f" arena) this machine holds at 30 Hz (within 1 %): {held}; slowest loop with 1..{len(slowest)} running:"
             f" {', '.join(f'{r:.2f}' for r in slowest)} Hz")
    return results


def bench_fleet_latency(seconds: float = 15.0, feedback: str = "vision", keyed: bool = False) -> tuple[float, float, int]:
    """(median ms, p99 ms, states) from a leader process publishing its state (`run --fleet`, vision
    in the loop, 30 Hz) to the fleet page's subscriber (FleetView) in this process, on loopback;
    ``keyed``: both with the fleet's keys (mutual TLS and access control, fresh keys made here)."""
    import subprocess
    import sys
    import tempfile
    import time as _time
    from pathlib import Path

    from app.dashboard.gate import quietly, serve_gated
    from app.fleet.bridge import loopback_endpoint, open_session
    from app.fleet.security import load_fleet_keys, make_fleet_keys
    from app.realtime import SWITCH_INTERVAL_S
    from app.services.fleet_page import FleetView

    endpoint = loopback_endpoint()
    tmp = tempfile.TemporaryDirectory(prefix="omniformation-keys-") if keyed else None
    keys_args: list[str] = []
    page_keys = None
    if tmp is not None:
        make_fleet_keys(Path(tmp.name), "bench", ("L1",))
        endpoint = "tls/" + endpoint.split("/", 1)[1]
        keys_args = ["--keys", str(Path(tmp.name) / "L1")]  # each identity its own bundle
        page_keys = load_fleet_keys(Path(tmp.name) / "page", "page", "bench")
    page_session = open_session([endpoint], [], page_keys)
    server, gate = serve_gated("127.0.0.1", 0)
    switch = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)  # as `omniformation fleet` runs the page
    view = FleetView(server, page_session, "bench")
    leader = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--fleet", "bench",
                               "--leader-id", "L1", "--zenoh-connect", endpoint, "--feedback", feedback, *keys_args],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = _time.monotonic() + 120
        while view.received < 60 and _time.monotonic() < deadline:  # past its start-up
            _time.sleep(0.2)
        view.latencies.clear()
        _time.sleep(seconds)
        lat = np.array(list(view.latencies)) * 1e3
    finally:
        leader.send_signal(2)
        try:
            leader.wait(30)
        except subprocess.TimeoutExpired:
            leader.kill()
        view.close()
        gate.close()
        quietly(server.stop)
        page_session.close()
        sys.setswitchinterval(switch)
        if tmp is not None:
            tmp.cleanup()
    if lat.size == 0:
        return float("nan"), float("nan"), 0
    return float(np.median(lat)), float(np.percentile(lat, 99)), int(lat.size)


def bench_arena_tick(leaders: int, followers: int, ticks: int = 300) -> float:
    """Median ms of one arena step (every robot's dynamics, the truth built and published) for
    ``leaders`` x ``followers`` (built directly: more robots than one fleet's hues allow)."""
    import dataclasses
    import time as _time

    from app.fleet.arena import Arena
    from app.fleet.bridge import open_session
    from core.fleet import FleetLeader, FleetScenario
    from core.sim.team import FollowerDynamics

    sc = FleetScenario("bench", "", tuple(FleetLeader(f"L{i + 1}", (3.0 * i, 0.0, math.pi / 2), followers, "straight",
                                                      0.03, 0.0, tuple([0.0] * followers)) for i in range(leaders)),
                       30.0, FollowerDynamics(actuator_tau_s=0.3, speed_max_mps=0.35, turn_max_rps=2.5))
    session = open_session([], [])
    arena = Arena(sc, session, "bench")
    try:
        times = []
        for _ in range(ticks):
            for a, f in arena.robots.followers.items():  # every robot commanded this tick
                arena.robots.followers[a] = dataclasses.replace(f, target_l_mps=0.044, target_r_mps=0.056,
                                                                command_age_s=0.0)
            t0 = _time.perf_counter()
            arena.step()
            times.append(_time.perf_counter() - t0)
    finally:
        arena.close()
        session.close()
    return float(np.median(times[20:]) * 1e3)


def bench_leader_processes(max_processes: int = 8, seconds: float = 12.0) -> tuple[int, list[float]]:
    """Start an arena for ``max_processes`` teams of 3 (side by side, every robot in its
    fleet-wide hue), then leader processes one more at a time (`run --arena`, each rendering
    its camera from the arena with the other teams in view, the vision pipeline in the loop,
    its page served, no browser) and read every one's loop rate from the bus; how many run at
    once with every loop within 1 % of 30 Hz, and the slowest rate at each count. The arena
    steps every team, joined or not, all along."""
    import json
    import subprocess
    import sys
    import tempfile
    import threading
    import time as _time
    from pathlib import Path

    from app.fleet.bridge import loopback_endpoint, open_session

    endpoint = loopback_endpoint()
    tmp = tempfile.TemporaryDirectory(prefix="omniformation-bench-")
    fleet = Path(tmp.name) / "bench_fleet.toml"
    fleet.write_text('name = "bench"\nrate_hz = 30\n' + "".join(
        f'[[leaders]]\nid = "L{k + 1}"\nstart = [{2.2 * k:.1f}, 0.0]\nheading_deg = 90\nfollowers = 3\n'
        f'mode = "straight"\nspeed_mps = 0.03\n' for k in range(max_processes)))
    session = open_session([], [endpoint])
    rates: dict[str, list[tuple[float, float]]] = {}
    lock = threading.Lock()

    def on_state(sample: Any) -> None:
        msg = json.loads(sample.payload.to_bytes())
        with lock:
            rates.setdefault(msg["leader_id"], []).append((_time.monotonic(), float(msg.get("rate_hz") or 0.0)))

    sub = session.declare_subscriber("omniformation/bench/leader/*/state", on_state)
    arena = subprocess.Popen([sys.executable, "-m", "app.cli", "arena", str(fleet), "--zenoh-listen", endpoint,
                              "--status-every", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs: list[subprocess.Popen[bytes]] = []
    slowest: list[float] = []
    held = 0
    try:
        for k in range(1, max_processes + 1):
            procs.append(subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record",
                                           "--arena", str(fleet), "--leader-id", f"L{k}", "--feedback", "vision",
                                           "--zenoh-connect", endpoint],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            deadline = _time.monotonic() + 120
            while _time.monotonic() < deadline:  # every leader past its start-up (compiling, first frames)
                with lock:
                    ready = len(rates) == k and all(len(v) > 150 for v in rates.values())
                if ready:
                    break
                _time.sleep(0.5)
            t0 = _time.monotonic()
            _time.sleep(seconds)
            with lock:
                window = [min(r for t, r in v if t >= t0) for v in rates.values() if any(t >= t0 for t, _ in v)]
            low = min(window) if len(window) == k else 0.0
            slowest.append(low)
            if low < 29.7:
                break
            held = k
    finally:
        for p in procs:
            p.send_signal(2)
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
        arena.send_signal(2)
        try:
            arena.wait(30)
        except subprocess.TimeoutExpired:
            arena.kill()
        sub.undeclare()
        session.close()
        tmp.cleanup()
    return held, slowest


def bench_sweeps() -> tuple[float, float, float, float, int]:
    """Seconds for a 5 x 5 sweep on experiment1 (truth, then vision), and the live loop's rate
    (vision in the loop, as `make run`) before and while the page's worker process sweeps."""
    import time as _time

    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_scenario, load_synthetic_rig
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.live.sweep import run_sweep
    from core.control.tuning import StepTest, parse_gain_range
    from core.sim.sweep import settled_start

    scenario = load_scenario("experiment1")
    base = settled_start(scenario)
    test = StepTest("offset", 0, 0.10)
    ranges = [parse_gain_range("k_w2=1:4:5"), parse_gain_range("k_f1=0.05:0.3:5")]
    twist = (scenario.leader.twist(0.0)[0], 0.0)
    truth = run_sweep(base, test, twist, ranges, scenario.gains).seconds
    rig = load_synthetic_rig(SYNTHETIC_CAMERA, SYNTHETIC_CALIBRATED)
    vision = run_sweep(base.replace(rate_hz=30.0), test, twist, ranges, scenario.gains, rig).seconds

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics)
    svc.start()
    try:
        _time.sleep(3.0)
        tick0, t0 = svc.loop.tick_count, _time.monotonic()
        _time.sleep(6.0)
        alone = (svc.loop.tick_count - tick0) / (_time.monotonic() - t0)
        while svc.loop.last is None or svc.loop.last.phase != "tracking":
            _time.sleep(0.2)
        tuning = svc.dashboard.tuning
        assert tuning is not None
        why = tuning.start_sweep("vision")
        if why:
            raise RuntimeError(f"the sweep did not start: {why}")
        tick0, t0 = svc.loop.tick_count, _time.monotonic()
        result = svc.sweeps.wait(600)
        during = (svc.loop.tick_count - tick0) / (_time.monotonic() - t0)
    finally:
        svc.close()
    return truth, vision, alone, during, len(result.gains) if result is not None else 0


def bench_loop_with_browsers(seconds: float = 6.0, browsers: int = 3) -> tuple[float, float, float] | None:
    """Achieved loop rate (Hz) with no browser, serving ``browsers`` Chromium pages that render
    at low priority, and with the same pages rendering beside the loop at normal priority.

    Returns None when Debian's chromium or Playwright is not installed.
    """
    import shutil
    import time as _time

    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if chromium is None:
        return None
    from app.services.live import Service

    def measure(svc: Service) -> float:
        start_tick, start = svc.loop.tick_count, _time.monotonic()
        _time.sleep(seconds)
        return (svc.loop.tick_count - start_tick) / (_time.monotonic() - start)

    from app.params import MAX_FOLLOWERS
    from app.live.config import DEFAULT_CONFIG, load_service_config

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)  # what `make run` serves: vision in the loop
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics)
    svc.start()
    try:
        _time.sleep(3.0)  # past the first ticks, which load compiled code
        alone = measure(svc)
        # The browsers as if on the operators' own machines (_VIEWER), so the figure is what
        # serving them costs the loop.
        import subprocess
        import sys

        viewer = subprocess.Popen([sys.executable, "-c", _VIEWER, chromium, svc.url, str(browsers)],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            ready = viewer.stdout.readline() if viewer.stdout else ""
            if "ready" not in ready:
                raise RuntimeError(f"the low-priority browsers did not come up: {ready.strip()!r}")
            served = measure(svc)
        finally:
            if viewer.stdin:
                viewer.stdin.close()
            viewer.wait(60)
        with sync_playwright() as p:  # and the same pages rendered beside the loop on this machine
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            # One context (window) each: a background tab in a shared window is throttled.
            pages = [browser.new_context().new_page() for _ in range(browsers)]
            for page in pages:
                page.goto(svc.url)
                page.wait_for_selector(".uplot", state="attached", timeout=90_000)
            watched = measure(svc)
            browser.close()
    finally:
        svc.close()
    return alone, served, watched


# Chromium pages as if on the operators' own machines: the same pages and websocket traffic,
# their (software-WebGL) rendering on this machine's idle CPU only. `nice` does not hold: Chromium
# run as root sets its compositor and IO threads back to nice -8, ahead of the loop. SCHED_IDLE
# (sched(7)) is inherited by every process and thread the browser starts, and their
# setpriority() calls change only a nice value that SCHED_IDLE ignores.
_VIEWER = """
import os, sys
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
from playwright.sync_api import sync_playwright
chromium, url, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
with sync_playwright() as p:
    browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
    pages = [browser.new_context().new_page() for _ in range(n)]
    for page in pages:
        page.goto(url)
        page.wait_for_selector(".uplot", state="attached", timeout=240_000)
    print("ready", flush=True)
    sys.stdin.read()
    browser.close()
"""
