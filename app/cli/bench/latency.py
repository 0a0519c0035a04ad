"""Frame-to-command latency on a real rig's path (`omniformation bench --latency`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.files import load_scenario

from app.cli.bench.browsers import VIEWER


def _render_team(frames_dir: Path, seconds: float) -> int:
    """The synthetic rig's pictures of a team driving (experiment 1's first seconds), one PNG a
    frame at 30 fps into ``frames_dir``; how many."""
    import cv2

    from app.files import SYNTHETIC_CAMERA, load_camera
    from core.camera.render import Renderer
    from core.geometry import heading_world_to_leader, world_to_leader
    from core.sim.stepped import simulate_stepped

    run = simulate_stepped(load_scenario("experiment1").replace(duration_s=min(seconds, 20.0)))  # truth: as it drives
    model = load_camera(SYNTHETIC_CAMERA)  # the pictures; the service reads them with the calibration
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
    return count


def bench_latency(seconds: float, print_fn: Callable[[str], None] = print, browsers: int = 1,
                  realtime: bool = False, page_process: bool = False, reserve_cpu: bool = False,
                  idle_browser: bool = True) -> dict[str, float]:
    """Frame-to-command latency on a real rig's path: a folder of the synthetic rig's pictures of a
    team driving (experiment 1's first seconds, rendered) played at 30 fps, the vision pipeline,
    the serial link to emulated followers on a pty, recording on, ``browsers`` Chromium pages
    attached (on idle CPU, as in the soak). Latency is each tick's ``latency_ms``: the frame's
    arrival to its commands written to the link. ``realtime``: as ``run --realtime`` (the loop's and
    the camera's threads on SCHED_FIFO, app.realtime). ``page_process``: as `run` serves now, the
    page in a process of its own (False: `run --one-process`). ``reserve_cpu``: as `run
    --reserve-cpu`, a CPU kept for the loop's thread, and the browser started off it.
    ``idle_browser``: the browser's rendering on this machine's idle CPU only, as if on the
    operator's own machine (app.cli.bench.browsers.VIEWER); False: its session an equal of the
    service's, as a browser beside the service on one desktop is."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile
    import time as _time


    from app.backends.camera import FolderSource
    from app.backends.hardware import HardwareTeam
    from app.backends.serial_link import SerialLink
    from app.contracts import Rig
    from app.files import SYNTHETIC_CALIBRATED, load_camera
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.services.recording import start_recording

    folder = Path(tempfile.mkdtemp(prefix="omniformation-latency-"))
    frames_dir = folder / "frames"
    frames_dir.mkdir()
    count = _render_team(frames_dir, seconds)
    rig = load_camera(SYNTHETIC_CALIBRATED)
    print_fn(f"latency: {count} frames of the synthetic rig rendered; playing them at 30 fps"
             f" (looped) for {seconds:g} s")
    # the robots are not in the service's process on a real rig: the emulator runs in its own
    emu = subprocess.Popen([sys.executable, "-m", "app.cli", "emulate-follower", "--pty", "--followers", "2",
                            "--seed", "3"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert emu.stdout is not None
        pty_path = emu.stdout.readline().split(" on ", 1)[1].strip()
        config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
        link = SerialLink(pty_path, 2)
        source = FolderSource(frames_dir, fps=30.0, loop=True)
        camera = Rig(rig, rig.require_gamma())
        svc = Service(host="127.0.0.1", port=0, n_followers=2, rate_hz=30.0, camera=camera, frames=source,
                      hardware=HardwareTeam(2, link), realtime=realtime, page_process=page_process,
                      reserve_cpu=reserve_cpu)
        recorder = start_recording(svc, config, None, None, camera, 10.0, folder / "latency.mcap")
    except BaseException:  # a service that did not come up leaves no robot emulator behind
        emu.terminate()
        emu.communicate(timeout=10)
        shutil.rmtree(folder, ignore_errors=True)
        raise
    latencies: list[float] = []
    phases: list[str] = []
    fresh: list[bool] = []
    ran: list[float] = []  # each tick's own time from its start to its commands written (ms)

    def keep(state: Any) -> None:
        latencies.append(state.latency_ms)
        phases.append(state.phase)
        fresh.append(state.fresh)
        ran.append(sum(state.stage_ms.get(k, 0.0) for k in TICK_STAGES))

    svc.loop.subscribe(keep)
    svc.start()
    viewer = None
    chromium = shutil.which("chromium")
    kept: int | None = None  # the CPU the loop kept (reserve_cpu)
    try:
        if browsers and chromium:
            cpus = ""
            if reserve_cpu and svc.loop.cpu is not None:  # the browser off the kept CPU, once the loop keeps it
                deadline = _time.monotonic() + 120
                while svc.loop.tick_count < 1 and _time.monotonic() < deadline:
                    _time.sleep(0.1)
                kept = svc.loop.cpu.cpu
                cpus = ",".join(map(str, sorted(svc.loop.cpu.others)))
                for tid in os.listdir(f"/proc/{emu.pid}/task"):  # the robots are not on a real rig's computer
                    os.sched_setaffinity(int(tid), svc.loop.cpu.others)
            viewer = subprocess.Popen([sys.executable, "-c", VIEWER, chromium, svc.url, str(browsers), cpus,
                                       "" if idle_browser else "equal"],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert viewer.stdout is not None
            viewer.stdout.readline()  # "ready": the page is up
        else:
            print_fn("latency: no browser attached (needs Debian's chromium and playwright: make test installs both)")
        for series in (latencies, phases, fresh, ran):
            series.clear()
        _time.sleep(seconds)
    finally:
        if viewer is not None:
            viewer.communicate("", timeout=60)
        svc.close()
        recorder.close()
        emu.terminate()
        emu.communicate(timeout=10)
        shutil.rmtree(folder, ignore_errors=True)
    how = f"the loop {svc.loop.priority}" if realtime else "normal priority"
    how += ", the page in its own process" if page_process else ""
    if reserve_cpu:
        how += f", CPU {kept} kept for the loop, the browser off it" if kept is not None else ", no CPU could be kept"
    if browsers and not idle_browser:
        how += ", the browser's session an equal of the service's"
    return _report(latencies, phases, fresh, ran, seconds, how, print_fn)


# The stages of a tick from its start to its commands written (app.live.loop, TickState.stage_ms):
# what a tick's latency is beyond them is the wait from the frame's arrival to the tick's start.
TICK_STAGES = ("observe", "control", "link")


def _report(latencies: list[float], phases: list[str], fresh: list[bool], ran: list[float], seconds: float,
            how: str, print_fn: Callable[[str], None]) -> dict[str, float]:
    """The latency's p50 and p99 over the ticks on a new frame, said in one line (and while tracking,
    and the ticks on a late camera). Where the slowest one percent spent their time: waiting from the
    frame's arrival for the loop's thread to start the tick (another program or thread had the CPU
    or the interpreter), or in the tick itself (its own work, or a tick interrupted)."""
    n = min(len(latencies), len(phases), len(fresh), len(ran))
    on_new = [k for k in range(n) if fresh[k] and np.isfinite(latencies[k])]
    values = np.array([latencies[k] for k in on_new])
    stale = np.array([latencies[k] for k in range(n) if not fresh[k] and np.isfinite(latencies[k])])
    tracking = np.array([latencies[k] for k in range(n) if fresh[k] and phases[k] == "tracking"])
    p50, p99 = (float(np.percentile(values, q)) for q in (50, 99)) if len(values) else (float("nan"),) * 2
    print_fn(f"frame-to-command latency ({how}): p50 {p50:.2f} ms, p99 {p99:.2f} ms ({len(values)} ticks on a"
             f" new frame, {len(values) / seconds:.1f} Hz; target p99 <= 5 ms)")
    if len(tracking):
        print_fn(f"  while tracking: p50 {np.percentile(tracking, 50):.2f} ms, p99 {np.percentile(tracking, 99):.2f} ms"
                 f" ({len(tracking)} ticks)")
    if len(stale):
        print_fn(f"  {len(stale)} ticks ran on a late camera (no new frame within 1.5 periods): the observation they"
                 f" acted on was {np.median(stale):.0f} ms old (median)")
    out = {"p50_ms": p50, "p99_ms": p99, "ticks": float(len(values)), "late_ticks": float(len(stale))}
    slow = [k for k in on_new if latencies[k] >= p99]
    if slow:
        lat = np.array([latencies[k] for k in slow])
        work = np.minimum(np.array([ran[k] for k in slow]), lat)
        wait = lat - work
        out.update(slow_ticks=float(len(slow)), slow_latency_ms=float(lat.mean()), slow_wait_ms=float(wait.mean()),
                   slow_tick_ms=float(work.mean()))
        print_fn(f"  the slowest {len(slow)} (at or over p99): {lat.mean():.2f} ms on average, of which"
                 f" {wait.mean():.2f} ms from the frame's arrival to the tick's start (the loop's thread"
                 f" waiting to run) and {work.mean():.2f} ms in the tick (its work, or the tick interrupted)")
    return out

