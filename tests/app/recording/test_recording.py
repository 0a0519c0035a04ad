"""Recording to MCAP, reading back (also cut-off files), report, and the commands around them."""

import json
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import Params, ParamsStore
from app.recording.reader import RecordingError, read_recording
from app.recording.schema import tick_from_payload, tick_payload
from app.recording.writer import Recorder
from tests.helpers import main_cli, run_cli, serve_then_signal
from tests.mcap_doctor import doctor

from pathlib import Path

from tests.helpers import ROOT
from tests.helpers import SAMPLES


def _close(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return abs(a - b) <= 1e-6 * max(1.0, abs(a))
    return a == b


def test_round_trip_every_tick_as_published(tmp_path):
    store = ParamsStore(Params(n_followers=3, leader_mode="circle", slots=np.array([[-0.5, -0.3], [0.5, -0.3], [0.0, -0.8]])))
    loop = ServiceLoop(store, Backends(seed=1), rate_hz=30.0)
    published = []
    rec = Recorder(tmp_path / "s.mcap", {"scenario": "test"}, store.get())
    loop.subscribe(rec.on_tick)
    loop.subscribe(published.append)
    store.subscribe(rec.on_params)
    for k in range(200):
        if k == 60:
            store.update("browser:1", k_f1=0.12)
        if k == 120:
            store.update("browser:1 preset column", slots=np.array([[0.0, -0.5], [0.0, -1.0], [0.0, -1.5]]))
        if k == 150:
            store.update("browser:1", stop=True)
        loop.tick()
    rec.close()
    back = read_recording(tmp_path / "s.mcap")
    assert back.complete and back.loss_note() == ""
    assert len(back.ticks) == len(published) == 200
    for s, d in zip(published, back.ticks):
        assert _close(tick_payload(s), d)
        assert _close(tick_payload(tick_from_payload(d)), d)
    kinds = [e["kind"] for e in back.events]
    assert kinds == ["gain", "preset", "stop"], back.events
    assert "k_f1 0.1 -> 0.12" in back.events[0]["detail"]
    assert len(back.params) == 4  # at the start and after each change
    assert back.metadata["scenario"] == "test"
    assert back.channels["/camera/image"] == "foxglove.CompressedImage"
    assert back.channels["/tf"] == "foxglove.FrameTransforms"


def test_foxglove_channels_carry_foxgloves_own_schemas_and_decode_from_the_file_alone(tmp_path):
    """/tf, /camera/image and /scan are protobuf with the FileDescriptorSet of Foxglove's
    published package; a reader that knows nothing of ours (only the file) decodes them, and
    the image's frame is one /tf defines, so Foxglove's 3D panel can place it."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.recording.foxglove import PROTOBUF_TOPICS, schema_data

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    store = ParamsStore(Params(n_followers=2))
    loop = ServiceLoop(store, Backends(seed=2, camera=config.camera()), rate_hz=30.0)
    rec = Recorder(tmp_path / "f.mcap", {"scenario": "test"}, store.get(), frame_rate_hz=10.0)
    loop.subscribe(rec.on_tick)
    for _ in range(40):
        loop.tick()
    rec.close()
    frames: dict[str, set[str]] = {"defined": set(), "used": set()}
    seen = set()
    with (tmp_path / "f.mcap").open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=list(PROTOBUF_TOPICS)):
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            assert schema.data == schema_data(PROTOBUF_TOPICS[channel.topic])  # the package's own
            fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
            pool = descriptor_pool.DescriptorPool()
            for fd in fds.file:
                pool.Add(fd)
            cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
            msg = cls.FromString(message.data)  # from the file alone
            seen.add(channel.topic)
            if channel.topic == "/tf":
                for t in msg.transforms:
                    frames["defined"] |= {t.parent_frame_id, t.child_frame_id}
            else:
                frames["used"].add(msg.frame_id)
            if channel.topic == "/camera/image":
                assert msg.format == "jpeg" and msg.data[:2] == b"\xff\xd8"
    assert seen == {"/tf", "/camera/image"}  # no obstacles: no scan
    assert frames["used"] <= frames["defined"], frames
    back = read_recording(tmp_path / "f.mcap")
    assert len(back.frames) >= 3 and back.frames[0][1][:2] == b"\xff\xd8"  # replay reads them


# The service as `run` starts it, its loop's tick() made to print each tick's session time as it
# ends (stdout, flushed): the parent then knows what the session had done when it killed it. Only
# the loop that has subscribers (the recorder) prints: the warm-up's throwaway loop has none.
_TICKING_RUN = """
import sys
from app.live import loop
tick = loop.ServiceLoop.tick
def printing(self):
    s = tick(self)
    if self._subscribers:
        print(f"tick {s.tick} {s.t:.4f}", flush=True)
    return s
loop.ServiceLoop.tick = printing
from app.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _killed_at(tmp_path: Path, feedback: str, seconds: float) -> tuple[float, float]:
    """(session time of the last tick the loop ran, of the last tick the file holds) after a
    SIGKILL ``seconds`` of session time into `run --record`."""
    path = tmp_path / f"killed-{feedback}-{seconds:g}.mcap"
    # the recorder is the loop's: its page in the same process (four of these start side by side)
    proc = subprocess.Popen([sys.executable, "-c", _TICKING_RUN, "run", "--port", "0", "--feedback", feedback,
                             "--record", str(path), "--one-process"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    last = -1.0
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            if line.startswith("tick "):
                last = float(line.split()[2])
                if last >= seconds:
                    break
    finally:
        proc.send_signal(signal.SIGKILL)
        rest, err = proc.communicate(timeout=30)
    for line in rest.splitlines():  # what it printed before it died: ticks that ran
        if line.startswith("tick "):
            last = float(line.split()[2])
    assert last >= seconds, err[-2000:]
    rec = read_recording(path)
    assert not rec.complete and "cut off" in rec.loss_note()
    assert np.all(np.diff(rec.t) > 0) and rec.lost_ticks == 0 and rec.tick_numbers[0] == 0
    return last, float(rec.t[-1])


@pytest.mark.slow
@pytest.mark.parametrize("feedback", ["truth", "vision"])
def test_a_session_killed_at_any_moment_keeps_all_but_its_last_second_and_a_half(tmp_path, feedback):
    """SIGKILL at 1.3, 2.6, 3.9 and 5.2 s of session (0.3, 0.6, 0.9 and 0.2 s into a 1 s chunk:
    the kill lands anywhere in one): the file holds every tick up to at most 1.5 s before the last
    one the loop ran (every chunk is flushed to the OS as it closes, at 1 s)."""
    from concurrent.futures import ThreadPoolExecutor

    times = (1.3, 2.6, 3.9, 5.2)
    with ThreadPoolExecutor(len(times)) as pool:  # four services at once: each is judged by its own session time
        results = list(pool.map(lambda sec: _killed_at(tmp_path, feedback, sec), times))
    for ran, kept in results:
        print(f"\n{feedback}: killed at t = {ran:.2f} s, the file holds up to t = {kept:.2f} s"
              f" (lost {ran - kept:.2f} s)")
        assert ran - kept <= 1.5


def test_a_killed_recording_is_reported_as_cut_off(tmp_path):
    _killed_at(tmp_path, "truth", 2.0)
    path = next(tmp_path.glob("killed-*.mcap"))
    out = run_cli("report", str(path), "--out", str(tmp_path / "rep"))
    assert out.returncode == 0, out.stderr
    assert "cut off" in out.stderr
    summary = json.loads((tmp_path / "rep" / "summary.json").read_text())
    assert summary["complete"] is False and summary["ticks_written"] is None


def test_sigterm_finishes_the_file(tmp_path):
    path = tmp_path / "term.mcap"
    run = serve_then_signal("--port", "0", "--feedback", "truth", "--record", str(path), hold_s=2.0)
    assert run.returncode == 0, run.stderr
    assert "recording finished" in run.stdout
    rec = read_recording(path)
    assert rec.complete and len(rec.ticks) > 30
    assert doctor(path) == []  # MCAP's own checks: a live service's recording (tests/mcap_doctor.py)


@pytest.mark.parametrize("content, message", [
    (b"this is not a recording at all" * 10, "not an MCAP file"),
    (b"", "not an MCAP file"),
])
def test_garbage_gets_one_line_and_exit_2(tmp_path, content, message):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    for cmd in (["report", str(bad), "--out", str(tmp_path / "r")], ["replay", str(bad), "--port", "0"]):
        out = main_cli(*cmd)
        assert out.returncode == 2
        assert message in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_a_file_cut_in_its_first_chunk_is_refused_clearly(tmp_path):
    sample = SAMPLES / "experiment2-vision.mcap"
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(sample.read_bytes()[:3000])
    with pytest.raises(RecordingError, match="no complete tick|not a readable|not an MCAP"):
        read_recording(cut)
    out = main_cli("report", str(cut), "--out", str(tmp_path / "r"))
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("name", ["paper_simulation-vision.mcap", "experiment2-vision.mcap"])
def test_samples_are_small_and_complete(name):
    path = SAMPLES / name
    assert path.stat().st_size <= 5 * 1024 * 1024
    rec = read_recording(path)
    assert rec.complete and len(rec.frames) > 100 and len(rec.ticks) > 3000
    assert "scenario_toml" in rec.metadata and "working_area" in rec.metadata


def test_report_writes_figures_and_summary(tmp_path):
    from app.recording.statistics import SETTLED_M

    out = run_cli("report", str(SAMPLES / "experiment2-vision.mcap"), "--out", str(tmp_path / "rep"))
    assert out.returncode == 0, out.stderr
    import cv2

    for name in ("trajectory.png", "errors.png", "headings.png", "lyapunov_commands.png", "safety.png", "lyapunov.png"):
        img = cv2.imread(str(tmp_path / "rep" / name))
        assert img is not None and img.shape[0] > 300 and img.std() > 10, name  # a real picture, not a blank
    assert "[7/7]" in out.stdout
    summary = json.loads((tmp_path / "rep" / "summary.json").read_text())
    f1, f2 = summary["followers"]
    assert f1["settling_time_s"] is not None and f1["settling_time_s"] < 30
    assert f1["time_not_tracked_s"] == 0.0 and f2["time_not_tracked_s"] == 0.0
    assert summary["errors_from"] == "true poses"
    safety = summary["safety"]  # experiment 2: followers 0.7 m before and behind the leader, never near each other
    assert safety["collisions"] == 0 and safety["near_misses"] == 0 and safety["min_distance_cm"] > 50
    assert safety["filter_acting_s"] == 0.0  # nobody near anybody: the filter never acted
    assert "safety (true poses): closest two robots" in (tmp_path / "rep" / "summary.md").read_text()
    # the numbers again, straight from the raw tick channel
    rec = read_recording(SAMPLES / "experiment2-vision.mcap")
    start = float(rec.metadata["scenario_start_s"])
    t = np.array([tk["t"] for tk in rec.ticks]) - start
    nan = lambda x: np.array([[np.nan if v is None else v for v in row] for row in x])  # JSON null = NaN
    err = np.array([np.linalg.norm(nan(tk["p_d"]) - nan(tk["p_true"]), axis=1) for tk in rec.ticks])
    for i, f in enumerate((f1, f2)):
        after = (t >= 0) & np.isfinite(err[:, i])
        above = t[after][err[after, i] >= SETTLED_M]
        assert f["settling_time_s"] == pytest.approx(t[after][t[after] > above.max()][0], abs=0.01)
        steady = err[after & (t >= f["settling_time_s"] - 0.005), i]
        assert f["steady_error_rms_cm"] == pytest.approx(np.sqrt(np.mean(steady**2)) * 100, abs=2e-3)
        assert f["steady_error_max_cm"] == pytest.approx(steady.max() * 100, abs=2e-3)
    md = (tmp_path / "rep" / "summary.md").read_text()
    assert f"| 2 | {f2['settling_time_s']} | {f2['steady_error_rms_cm']} |" in md
    # experiment 2: follower 2 is stuck at 58-62 s (the paper's disturbance), so it settles only after it
    assert f2["settling_time_s"] > 62


def test_simulate_record_then_replay_reads_back(tmp_path):
    path = tmp_path / "sim.mcap"
    out = main_cli("simulate", "experiment1", "--duration", "5", "--record", str(path))
    assert out.returncode == 0, out.stderr
    rec = read_recording(path)
    assert len(rec.ticks) == 5 * 30 + 1 and rec.frames == []
    assert doctor(path) == []  # MCAP's own checks: no scan, no trial, no frame, and still every summary record in the data


@pytest.fixture(scope="module")
def vision_recording(tmp_path_factory):
    """A short vision-in-the-loop session with every camera frame kept (30 Hz)."""
    path = tmp_path_factory.mktemp("rerun") / "e1.mcap"
    out = main_cli("simulate", "experiment1", "--vision", "--duration", "12", "--frames-hz", "30", "--record", str(path))
    assert out.returncode == 0, out.stderr
    return path


def test_rerun_the_frames_reproduces_the_recorded_estimates(vision_recording, tmp_path):
    new = tmp_path / "again.mcap"
    out = main_cli("rerun", str(vision_recording), "--out", str(new))
    assert out.returncode == 0, out.stderr
    rows = re.findall(r"F(\d): position ([\d.]+) cm, heading ([\d.]+) deg; tracked (\d+) %.*?error vs truth "
                      r"([\d.]+) -> ([\d.]+) cm", out.stdout)
    assert len(rows) == 2, out.stdout
    for _, dp, da, tracked, err_old, err_new in rows:
        # same settings: the same estimates up to the JPEG frames and the re-learned colours
        assert float(dp) < 1.0 and float(da) < 5.0 and int(tracked) == 100
        assert float(err_new) < 1.5 * float(err_old) + 0.2
    rec, back = read_recording(vision_recording), read_recording(new)
    assert back.complete and back.metadata["rerun_of"] == vision_recording.name
    assert len(back.ticks) == len(back.frames) and len(back.frames) > 200
    assert back.metadata["calibration_toml"] == rec.metadata["calibration_toml"]  # the Γ it was recorded with
    assert doctor(vision_recording) == [] and doctor(new) == []  # MCAP's own checks: simulate --vision, rerun


def test_rerun_with_other_pipeline_settings_changes_the_headings(vision_recording, tmp_path):
    cfg = tmp_path / "pipeline.toml"
    cfg.write_text("[pipeline]\nkalman_measurement_deg = 60.0\nkalman_process_deg = 0.5\n")
    same, other = tmp_path / "same.mcap", tmp_path / "other.mcap"
    assert main_cli("rerun", str(vision_recording), "--out", str(same)).returncode == 0
    out = main_cli("rerun", str(vision_recording), "--pipeline-config", str(cfg), "--out", str(other))
    assert out.returncode == 0, out.stderr
    a_same = np.array([tk["a_est"] for tk in read_recording(same).ticks], dtype=float)
    a_other = np.array([tk["a_est"] for tk in read_recording(other).ticks], dtype=float)
    assert np.nanmax(np.abs(a_same - a_other)) > np.radians(0.5)  # a much slower filter: other headings
    settings = json.loads(read_recording(other).metadata["pipeline_settings"])
    assert settings["kalman_measurement_deg"] == 60.0


def test_rerun_with_other_gains_resimulates_from_the_same_start(tmp_path):
    rec_path, new = tmp_path / "truth.mcap", tmp_path / "fast.mcap"
    assert main_cli("simulate", "experiment1", "--duration", "40", "--record", str(rec_path)).returncode == 0
    out = main_cli("rerun", str(rec_path), "--gains", "k_f1=0.2", "--out", str(new))
    assert out.returncode == 0, out.stderr
    settle = [(float(a), float(b)) for a, b in re.findall(r"settling ([\d.]+) -> ([\d.]+)", out.stdout)]
    assert len(settle) == 2 and all(b < a for a, b in settle), out.stdout  # a stiffer pose term settles sooner
    old, back = read_recording(rec_path), read_recording(new)
    assert back.ticks[0]["p_true"] == old.ticks[0]["p_true"]  # the same start
    assert back.ticks[0]["gains"]["k_f1"] == 0.2 and len(back.ticks) == len(old.ticks)
    assert doctor(new) == []  # MCAP's own checks: a re-simulated rerun


def test_rerun_settings_are_checked_with_one_clear_line():
    from app.files import UserError
    from app.recording.rerun import parse_gains
    from core.config import ConfigError
    from core.types import Gains
    from core.vision.pipeline import parse_pipeline_settings

    assert parse_gains("k_f1=0.12, k_w2=2", Gains()) == Gains(k_f1=0.12, k_w2=2.0)
    for text, message in [("k_f9=1", "must be NAME=NUMBER"), ("k_f1", "must be NAME=NUMBER"),
                          ("k_f1=fast", "'fast' is not a number"), ("k_f1=7", r"k_f1 = 7.0: must be a number in \(0, 1\] m/s")]:
        with pytest.raises(UserError, match=message):
            parse_gains(text, Gains())
    assert parse_pipeline_settings("[pipeline]\nlost_after_frames = 5\n", "p.toml").lost_after_frames == 5
    for text, message in [("[pipeline]\nkalman_measurement_deg = -3\n", r"p.toml: pipeline.kalman_measurement_deg = -3:"
                                                                         r" must be a number in \[0.01, 180\] deg"),
                          ("[pipeline]\nkalman = 3\n", "kalman"), ("[pipeline]\nlost_after_frames = 2.5\n", "lost_after_frames"),
                          ("[other]\n", "pipeline"), ("[pipeline\n", "not valid TOML")]:
        with pytest.raises(ConfigError, match=message):
            parse_pipeline_settings(text, "p.toml")


def test_rerun_refuses_bad_input_in_one_line(vision_recording, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[pipeline]\nkalman_measurement_deg = -3\n")
    truth = tmp_path / "t.mcap"
    assert main_cli("simulate", "experiment1", "--duration", "2", "--record", str(truth)).returncode == 0
    for args, message in [
        ((str(vision_recording), "--pipeline-config", str(bad)), "kalman_measurement_deg = -3: must be a number"),
        ((str(truth),), "has no camera frames"),
        ((str(truth), "--gains", "k_f1=0.2", "--out", str(truth)), "would overwrite"),
    ]:
        extra = () if "--out" in args else ("--out", str(tmp_path / "x.mcap"))
        out = main_cli("rerun", *args, *extra)
        assert out.returncode == 2 and message in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_live_camera_frames_are_recorded_at_the_frame_rate(tmp_path):
    from app.params import MAX_FOLLOWERS
    from app.live.config import DEFAULT_CONFIG, load_service_config

    import cv2

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    store = ParamsStore(Params(n_followers=2))
    loop = ServiceLoop(store, Backends(seed=2, camera=config.camera()), rate_hz=30.0)
    rec = Recorder(tmp_path / "v.mcap", {"scenario": "test"}, store.get(), frame_rate_hz=10.0)
    published = []
    loop.subscribe(rec.on_tick)
    loop.subscribe(published.append)
    for _ in range(21):
        loop.tick()
    rec.close()
    back = read_recording(tmp_path / "v.mcap")
    assert len(back.frames) == 7 and rec.dropped == 0  # every third tick at 30 Hz
    by_t = {round(s.t, 6): s.frame for s in published}
    for t, jpeg in back.frames:
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        original = np.asarray(by_t[round(t, 6)])
        assert img.shape == original.shape
        assert np.abs(img.astype(int) - original.astype(int)).mean() < 6  # the same frame, JPEG-compressed


def test_the_safety_summary_counts_collisions_near_misses_and_limit_hits():
    from types import SimpleNamespace

    from app.recording.report import Series, safety_summary

    T = 300
    t = np.arange(T) / 30.0
    gap = np.concatenate([np.linspace(1.0, 0.10, 100), np.full(50, 0.10), np.linspace(0.10, 1.0, 150)])
    p = np.zeros((T, 2, 2))
    p[:, 0] = np.column_stack([-gap / 2, np.full(T, 1.0)])
    p[:, 1] = np.column_stack([gap / 2, np.full(T, 1.0)])
    commands = np.zeros((T, 2, 2))
    commands[10:20, 0, 0] = 0.3  # at v_max for a third of a second
    s = Series(t, np.zeros((T, 3)), np.zeros((T, 2, 3)), p, p, np.zeros((T, 2)), np.zeros((T, 2)), np.ones((T, 2), bool),
               np.zeros(T), commands, True, np.zeros(T, bool))
    rec = SimpleNamespace(params=[(0.0, {"gains": {"v_max": 0.3, "w_max": 2.0}})], metadata={})
    out = safety_summary(rec, s, 1 / 30)["safety"]
    assert out["collisions"] == 1 and out["near_misses"] == 1 and out["min_distance_cm"] == 10.0
    assert out["actuator_limit_hits"] == 1 and out["filter_acting_s"] == 0.0
    assert out["time_under_min_distance_s"] > 1.0


def test_a_run_with_obstacles_records_the_scan_and_the_report_counts_the_clearance(tmp_path):
    """narrow_gap with vision in the loop, recorded: the free-space scan as foxglove.LaserScan
    on /scan (leader frame, 10 a second), the known obstacle points and the goal in the
    ticks; `report` draws the minimum distance over time and says how close a follower got."""
    from mcap.reader import make_reader

    path = tmp_path / "gap.mcap"
    out = run_cli("simulate", "narrow_gap", "--vision", "--duration", "40", "--frames-hz", "2", "--record", str(path))
    assert out.returncode == 0, out.stderr
    assert "goal" in out.stdout and "closest follower body to an obstacle" in out.stdout
    rec = read_recording(path)
    assert rec.channels["/scan"] == "foxglove.LaserScan"
    from app.recording.foxglove import decode

    scans = []
    with path.open("rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(topics=["/scan"]):
            scans.append(decode("/scan", message.data))
    assert len(scans) > 200  # 10 a second once the start-up is over
    scan = scans[-1]
    assert scan.frame_id == "leader" and len(scan.ranges) == 360
    assert scan.end_angle - scan.start_angle == pytest.approx(np.radians(359.0))
    assert any(np.isfinite(r) for s_ in scans for r in s_.ranges)  # the boxes were seen
    ticks = [tick_from_payload(t) for t in rec.ticks[-5:]]
    assert all(t.goal == (0.0, 5.0) and t.obstacles is not None for t in ticks)
    rep = run_cli("report", str(path), "--out", str(tmp_path / "rep"))
    assert rep.returncode == 0, rep.stderr
    summary = json.loads((tmp_path / "rep" / "summary.json").read_text())["safety"]
    assert summary["obstacle_clearance_cm"] >= 10.0 and summary["obstacle_hits"] == 0
    assert summary["collisions"] == 0 and summary["boundary_exits"] == 0
    assert (tmp_path / "rep" / "safety.png").stat().st_size > 10_000


def test_recordings_made_before_the_published_schemas_still_replay_their_frames(tmp_path):
    """Older recordings carry /camera/image as JSON with the JPEG in base64: still read."""
    import base64

    import cv2
    from mcap.writer import Writer

    store = ParamsStore(Params(n_followers=2))
    loop = ServiceLoop(store, Backends(seed=1), rate_hz=30.0)
    state = loop.tick()
    jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 90, np.uint8))[1].tobytes()
    with (tmp_path / "old.mcap").open("wb") as f:
        w = Writer(f)
        w.start(profile="", library="omniformation")
        tick_ch = w.register_channel("/omniformation/tick", "json", w.register_schema("omniformation.Tick", "jsonschema", b"{}"))
        img_ch = w.register_channel("/camera/image", "json",
                                    w.register_schema("foxglove.CompressedImage", "jsonschema", b"{}"))
        w.add_message(tick_ch, log_time=0, publish_time=0, data=json.dumps(tick_payload(state), separators=(",", ":")).encode())
        w.add_message(img_ch, log_time=0, publish_time=0, data=json.dumps(
            {"timestamp": {"sec": 0, "nsec": 0}, "frame_id": "camera", "format": "jpeg",
             "data": base64.b64encode(jpeg).decode()}).encode())
        w.finish()
    back = read_recording(tmp_path / "old.mcap")
    assert len(back.frames) == 1 and back.frames[0][1] == jpeg


def test_the_closest_two_robots_are_found_in_blocks_as_in_one_piece():
    """report's pairwise distances go block by block (bounded memory on an hour's recording):
    the same answer as one (T, m, m) array, across block edges and with a follower unseen (NaN)."""
    from app.recording.report import DISTANCE_BLOCK, Series

    rng = np.random.default_rng(5)
    T, n = 2 * DISTANCE_BLOCK + 77, 3
    p = rng.uniform(-2, 2, (T, n, 2))
    p[DISTANCE_BLOCK - 1, 1] = np.nan
    z = np.zeros((T, n))
    s = Series(np.arange(T) / 30, np.zeros((T, 3)), np.zeros((T, n, 3)), p, p, z, z, z.astype(bool), np.zeros(T),
               np.zeros((T, n, 2)), True)
    pts = np.concatenate([np.zeros((T, 1, 2)), p], axis=1)
    d = np.linalg.norm(pts[:, :, None] - pts[:, None], axis=-1)
    d[:, np.arange(n + 1), np.arange(n + 1)] = np.inf
    np.testing.assert_array_equal(s.min_distance(), np.nanmin(d.reshape(T, -1), axis=1))


def test_the_report_tallies_the_same_summary_whatever_the_block_and_plots_every_kth_tick():
    """report reads a recording once, a block of ticks at a time (bounded memory on a long
    recording): settling, steady error, episodes of collisions and limit hits carry across block
    edges, so one tick per block gives the summary of one block for the whole file; the figures
    get every k-th tick, at most max_plotted of them."""
    from app.recording.report import scan, summarise

    rec = read_recording(SAMPLES / "experiment2-vision.mcap")
    whole = summarise(rec, scan(rec, block=len(rec.ticks)))
    assert all(f["settling_time_s"] is not None for f in whole["followers"])
    for block in (1, 7, 4096):
        assert summarise(rec, scan(rec, block=block)) == whole, block
    few = scan(rec, block=50, max_plotted=100)
    k = -(-len(rec.ticks) // 100)
    assert len(few.shown.t) == -(-len(rec.ticks) // k) <= 100
    np.testing.assert_allclose(np.diff(few.shown.t), k / 30, atol=1e-3)
    assert summarise(rec, few) == whole


def test_the_tally_counts_episodes_and_settling_across_block_edges():
    """The summary's tally fed a series whole or in pieces of 1, 7 or 50 ticks: the same numbers
    (two collision episodes, one crossing a block edge; limit hits; a follower whose last error
    above 2 cm is a block's last tick; one that never settles)."""
    from dataclasses import fields, replace

    from app.recording.report import Series, Tally

    T = 300
    t = np.arange(T) / 30.0
    gap = np.full(T, 1.0)
    gap[40:60] = 0.10
    gap[200:215] = 0.12
    p = np.zeros((T, 2, 2))
    p[:, 0] = np.column_stack([-gap / 2, np.full(T, 1.0)])
    p[:, 1] = np.column_stack([gap / 2, np.full(T, 1.0)])
    p_d = p.copy()
    p_d[:49, 0, 0] += np.linspace(0.5, 0.04, 49)  # follower 1: above 2 cm up to tick 48, then 1 cm
    p_d[49:, 0, 0] += 0.01
    p_d[:, 1, 1] += 0.05 + 0.01 * np.sin(t)  # follower 2: never settles
    p[100:110, 1] = np.nan  # follower 2 unseen for a third of a second
    commands = np.zeros((T, 2, 2))
    commands[10:20, 0, 0] = 0.3
    commands[48:52, 1, 1] = -2.0
    tracked = np.ones((T, 2), bool)
    tracked[100:110, 1] = False
    s = Series(t, np.zeros((T, 3)), np.zeros((T, 2, 3)), p, p_d, np.zeros((T, 2)), np.zeros((T, 2)), tracked,
               np.zeros(T), commands, True, np.arange(T) % 9 == 0)

    def tally(block: int) -> tuple:
        tl = Tally(2, float(t[-1]), {"v_max": 0.3, "w_max": 2.0}, np.zeros((0, 4)), True)
        for a in range(0, T, block):
            tl.add(replace(s, **{f.name: getattr(s, f.name)[a:a + block] for f in fields(s)
                                 if isinstance(getattr(s, f.name), np.ndarray)}))
        return tl.followers(1 / 30), tl.safety(1 / 30)

    followers, safety = tally(T)
    assert safety["safety"]["collisions"] == 2 and safety["safety"]["actuator_limit_hits"] == 2
    assert followers[0]["settling_time_s"] == round(t[49], 2) and followers[0]["steady_error_max_cm"] == 1.0
    assert followers[1]["settling_time_s"] is None and followers[1]["time_not_tracked_s"] == round(10 / 30, 2)
    for block in (1, 7, 49, 50):
        assert tally(block) == (followers, safety), block


def test_next_event_always_moves_forward_and_previous_back():
    """From t = 0, Next event four times visits four later event times, each further on (it was
    stuck on an event between two ticks); Previous then walks back."""
    from app.services.replay import ReplayService

    rec = read_recording(SAMPLES / "experiment2-vision.mcap")
    svc = ReplayService(rec, host="127.0.0.1", port=0)
    try:
        svc.seek(0)
        seen = [svc.jump_to_event(+1) for _ in range(4)]
        assert all(t is not None for t in seen) and seen == sorted(seen) and len(set(seen)) == 4, seen
        assert all(float(svc.t[svc.index]) >= seen[-1] - 1e-6 for _ in [0])  # showing the event's moment
        back = [svc.jump_to_event(-1) for _ in range(3)]
        assert back == sorted(back, reverse=True) and len(set(back)) == 3 and back[0] < seen[-1], back
    finally:
        svc.close()
        rec.close()


def test_the_summary_counts_stops_and_releases_apart_and_gives_each_segment(tmp_path):
    """A short real session (the loop, the recorder, a file): two STOPs, two releases and a reset
    between them. summary.md says `STOPs: 2` and `releases: 2` (not "4 STOP events"), a table row
    per segment and follower with the figures summary.json has, and one meaning of "settled";
    errors.png is in cm on a scale that fits the errors; no event says the filter changed 0.00 m/s."""
    import cv2

    from app.recording.report import error_limit_cm, write_report
    from app.recording.statistics import SETTLED_M
    from core.control.tuning import SETTLE_TOL_M

    store = ParamsStore(Params(n_followers=2, leader_mode="straight"))
    loop = ServiceLoop(store, Backends(seed=3), rate_hz=30.0)
    rec = Recorder(tmp_path / "s.mcap", {"scenario": "counts"}, store.get())
    seen = []
    loop.subscribe(rec.on_tick)
    loop.subscribe(seen.append)
    store.subscribe(rec.on_params)
    changes = {40: {"stop": True}, 60: {"stop": False}, 90: {"reset_requests": 1}, 130: {"stop": True},
               150: {"stop": False}}
    for k in range(180):
        if k in changes:
            store.update("browser:1", **changes[k])
        loop.tick()
    rec.close()
    back = read_recording(tmp_path / "s.mcap")
    assert [e["kind"] for e in back.events if e["kind"] in ("stop", "reset")] == ["stop", "stop", "reset", "stop", "stop"]
    assert not any("0.00 m/s" in e["detail"] for e in back.events), back.events
    # the filter "changing" a command by less than the event's two decimals show is no event; 0.04 m/s is one
    import dataclasses

    from app.recording.writer import tick_events

    quiet = dataclasses.replace(seen[-1], safety="on, inactive", safety_changed=np.zeros(2))
    noop = dataclasses.replace(seen[-1], safety="on, changed F1 0.00 m/s", safety_changed=np.array([0.001, 0.0]))
    moved = dataclasses.replace(seen[-1], safety="on, changed F1 0.04 m/s", safety_changed=np.array([0.04, 0.0]))
    assert [k for k, _ in tick_events(quiet, noop)] == []
    assert tick_events(noop, moved) == [("safety", "safety filter on, changed F1 0.04 m/s")]
    out = tmp_path / "rep"
    out.mkdir()
    write_report(back, out)
    md = (out / "summary.md").read_text()
    sm = json.loads((out / "summary.json").read_text())
    assert "- STOPs: 2\n" in md and "- releases: 2\n" in md and "STOP events" not in md
    assert sm["stops"] == 2 and sm["releases"] == 2 and len(sm["stop_events"]) == 4
    assert SETTLED_M == SETTLE_TOL_M and f"under {SETTLED_M * 100:.0f} cm" in md  # one "settled", the page's
    assert len(sm["segments"]) == 2
    for k, g in enumerate(sm["segments"], 1):
        for f in g["followers"]:
            settle = f["settling_time_s"] if f["settling_time_s"] is not None else "not settled"
            assert (f"| {k} | {g['from_s']} | {g['to_s']} | {f['follower']} | {settle} |"
                    f" {f['steady_error_rms_cm']} | {f['steady_error_max_cm']} |") in md
    img = cv2.imread(str(out / "errors.png"))
    assert img is not None and img.std() > 10
    err = np.array([[np.linalg.norm(np.subtract(d, p)) for d, p in zip(tk["p_d"], tk["p_true"])] for tk in back.ticks])
    lim = error_limit_cm(err * 100)
    assert 1.0 <= lim <= max(1.0, 1.2 * np.nanmax(err) * 100)  # cm, and no wider than the data
