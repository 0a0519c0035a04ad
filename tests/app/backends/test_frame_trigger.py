"""With a camera, the loop's ticks start on its frames: a frame never waits for the loop's own
schedule, and the loop never uses a frame twice unless the camera is late. Each tick records how
long it took from the frame's arrival to its commands on the link (latency_ms)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from app.backends.camera import ThreadedSource
from app.backends.hardware import HardwareTeam
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import ParamsStore
from tests.helpers import wait_for


class PacedCamera(ThreadedSource):
    """A camera delivering the synthetic rig's picture at ``hz``; it remembers which frame number
    each latest() call handed out."""

    def __init__(self, frame: np.ndarray, hz: float) -> None:
        super().__init__(f"paced {hz:g} Hz")
        self.picture, self.hz = frame, hz
        self.handed: list[int] = []
        self.start()

    def _run(self) -> None:
        self._set_state(f"camera {self.name}: ok")
        next_t = time.monotonic()
        while not self._stop.is_set():
            self._put(self.picture)
            next_t += 1.0 / self.hz
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def latest(self):
        frame, t, count = super().latest()
        self.handed.append(count)
        return frame, t, count


@pytest.fixture(scope="module")
def rig_and_frame():
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from core.camera.render import Renderer

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    rig, gamma = config.camera()
    picture = np.asarray(Renderer(rig.model, rig.render).frame(
        np.array([0.0, 0.0, np.pi / 2]), np.array([[0.5, 0.3, 1.5], [-0.5, 0.6, 1.0]]), 0.0, np.random.default_rng(0)))
    return (rig, gamma), picture


@pytest.mark.parametrize("hz", [25.0, 40.0])
def test_ticks_follow_the_cameras_frames(rig_and_frame, hz):
    camera, picture = rig_and_frame
    source = PacedCamera(picture, hz)
    loop = ServiceLoop(ParamsStore(), Backends(frames=source, hardware=HardwareTeam(2), camera=camera), rate_hz=30.0)
    ticks: list = []
    loop.subscribe(ticks.append)
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: len(ticks) >= 60, 60, "60 ticks")
    finally:
        loop.stop()
        thread.join(10)
        source.close()
    handed = source.handed[:len(ticks)]  # one latest() a tick (VisionFeedback.observe)
    repeats = sum(1 for a, b in zip(handed, handed[1:]) if b == a)
    print(f"\n{hz:g} Hz camera: {len(ticks)} ticks, loop {loop.achieved_rate_hz:.1f} Hz (configured 30),"
          f" {repeats} frames used twice, {loop.late_frames} late, frames skipped"
          f" {handed[-1] - handed[0] + 1 - len(set(handed))}; frame to command p50"
          f" {np.nanmedian([t.latency_ms for t in ticks]):.2f} ms")
    assert len(handed) == len(ticks) and handed == sorted(handed)
    assert repeats <= loop.late_frames  # a frame is used again only when the camera was late
    # a tick has a frame-to-command time, or had no fresh frame (a loaded machine kept the camera's
    # thread off the CPU for STALE_FRAME_S, seen in CI): then it says so and moves nothing
    for t in ticks:
        if np.isfinite(t.latency_ms):
            assert t.latency_ms >= 0, t.latency_ms
        else:
            assert t.phase.startswith("camera: ") and not t.commands.any(), (t.phase, t.commands)
    assert sum(np.isfinite(t.latency_ms) for t in ticks) >= len(ticks) // 2


def test_the_latency_is_recorded_and_reported(tmp_path):
    """Every tick of a live recording carries latency_ms; report's summary gives its p50, p95, p99
    over every tick."""
    from app.params import Params
    from app.recording.reader import read_recording
    from app.recording.report import summarise
    from app.recording.writer import Recorder

    store = ParamsStore(Params(leader_mode="straight"))
    loop = ServiceLoop(store, Backends(seed=1), rate_hz=30.0)
    rec = Recorder(tmp_path / "s.mcap", {"scenario": "latency"}, store.get(), lossless=True)
    loop.subscribe(rec.on_tick)
    states = [loop.tick() for _ in range(40)]
    rec.close()
    assert all(np.isfinite(s.latency_ms) and s.latency_ms >= 0 for s in states)
    back = read_recording(tmp_path / "s.mcap")
    recorded = [t["latency_ms"] for t in back.ticks]
    assert recorded == pytest.approx([s.latency_ms for s in states], rel=1e-6, abs=1e-6)
    summary = summarise(back)["latency_ms"]
    assert summary["ticks"] == 40 and summary["p50"] <= summary["p95"] <= summary["p99"] <= summary["max"]
    assert summary["p99"] >= np.percentile(recorded, 99) - 0.05  # to the bin (0.05 ms)


def test_the_latency_bench_measures_ticks_on_new_frames_over_the_serial_link():
    """bench --latency's own path, short and without a browser: frames from a folder, the serial
    link to emulated robots (their own process), recording on, as `run --realtime`; it prints the
    latency line the README quotes, saying how the loop was scheduled, and where the slowest ticks
    spent their time (the wait before the tick and the tick itself add up to their latency)."""
    from app.cli.bench import bench_latency

    lines: list[str] = []
    out = bench_latency(3.0, lines.append, browsers=0, realtime=True)
    line = next(ln for ln in lines if ln.startswith("frame-to-command latency (the loop "))
    assert "real-time (FIFO 10)" in line or "real-time refused" in line, line
    assert " ms, p99 " in line and out["ticks"] > 30 and out["p50_ms"] <= out["p99_ms"]
    slow = next(ln for ln in lines if ln.startswith("  the slowest "))
    assert "from the frame's arrival to the tick's start" in slow, slow
    assert 1 <= out["slow_ticks"] <= 0.05 * out["ticks"] + 1
    assert out["slow_wait_ms"] >= 0 and out["slow_tick_ms"] > 0
    assert out["slow_wait_ms"] + out["slow_tick_ms"] == pytest.approx(out["slow_latency_ms"])
    assert out["slow_latency_ms"] >= out["p99_ms"]


def test_realtime_is_asked_for_one_thread_and_said_when_refused():
    """app.realtime: SCHED_FIFO for the calling thread only (the others stay normal), or one
    reason why not; how a thread is scheduled reads back."""
    import os
    import threading

    from app.realtime import make_realtime, scheduling

    got: dict[str, str] = {}

    def worker() -> None:
        got["why"] = make_realtime()
        got["mine"] = scheduling()

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert scheduling() == "normal"  # this thread was not touched
    if got["why"]:
        assert got["mine"] == "normal" and ("not permitted" in got["why"] or "refused" in got["why"]), got
    else:
        assert got["mine"] == "real-time (FIFO 10)", got
    assert make_realtime(native_id=2**22 + 12345) != ""  # no such thread: a reason, not an exception
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_a_real_rig_predicts_its_followers_over_the_measured_latency(rig_and_frame, tmp_path):
    """The observation is as old as its frame, and a command acts half the link's round trip
    after it is written: the loop runs each follower forward over the commands it sent since the
    frame, then over the last one held, to when this tick's command acts."""
    import cv2

    from app.backends.camera import FolderSource
    from core.control.prediction import predict_poses

    class Stats:
        rtt_mean_ms = 100.0  # half of it, 50 ms, is the radio's share: 2 ticks at 30 Hz

    class Link:
        stats = [Stats(), Stats()]

    camera, picture = rig_and_frame
    cv2.imwrite(str(tmp_path / "f.png"), picture)
    source = FolderSource(tmp_path, fps=30.0)
    team = HardwareTeam(2)
    team.link = Link()  # only its measured round trip is read here
    loop = ServiceLoop(ParamsStore(), Backends(frames=source, hardware=team, camera=camera), rate_hz=30.0)
    try:
        sent = [np.array([[0.1 * k, 0.2], [0.05, -0.1 * k]]) for k in range(5)]
        for c in sent:
            loop._sent.append((c, (0.06, 0.02)))
        p, a = np.array([[0.5, -0.3], [-0.5, -0.3]]), np.array([1.5, 1.6])
        got_p, got_a = loop._over_latency(p, a, 100.0 - 3 / 30, (0.06, 0.0), now=100.0)  # the frame: 3 ticks old
        want_p, want_a = predict_poses(p, a, np.array(sent[-3:] + [sent[-1]] * 2),
                                       np.array([(0.06, 0.02)] * 3 + [(0.06, 0.0)] * 2), 1 / 30)
        assert np.allclose(got_p, want_p) and np.allclose(got_a, want_a)
        assert not np.allclose(got_p, p)  # it moved them: the latency is bridged, not ignored
    finally:
        source.close()
