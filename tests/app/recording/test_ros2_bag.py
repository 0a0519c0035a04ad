"""`omniformation export FILE.mcap --ros2 DIR` (docs/foxglove.md, ROS 2 bags): rosbags' own
AnyReader reads the bag back, every message deserialises with the ROS 2 Jazzy types, each
per-tick topic has one message per recorded tick at the tick's session time, a damaged
recording exports what it still holds and says what was lost, and bad input is one line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from app.live.config import DEFAULT_CONFIG, load_service_config
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import MAX_FOLLOWERS, Params, ParamsStore
from app.recording.reader import read_recording
from app.recording.writer import Recorder
from tests.helpers import main_cli

TICKS = 120  # four chunks of ticks at 30 Hz


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    store = ParamsStore(Params(n_followers=2, leader_mode="circle"))
    loop = ServiceLoop(store, Backends(seed=3, camera=config.camera()), rate_hz=30.0)
    path = tmp_path_factory.mktemp("ros2") / "s.mcap"
    rec = Recorder(path, {"scenario": "test"}, store.get(), frame_rate_hz=10.0, start_ns=1_700_000_000_000_000_000,
                   lossless=True)
    loop.subscribe(rec.on_tick)
    for _ in range(TICKS):
        loop.tick()
    rec.close()
    return path


def _read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message of the bag, deserialised by rosbags with the ROS 2 Jazzy types."""
    out: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        assert {c.msgtype for c in reader.connections} <= {
            "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/PoseArray", "sensor_msgs/msg/CompressedImage",
            "geometry_msgs/msg/Twist", "geometry_msgs/msg/Vector3Stamped"}
        for conn, ts, raw in reader.messages():
            out.setdefault(conn.topic, []).append((ts, reader.deserialize(raw, conn.msgtype)))
    return out


def test_the_bag_reads_back_with_a_message_per_tick_at_the_sessions_time(recording, tmp_path):
    bag = tmp_path / "bag"
    r = main_cli("export", str(recording), "--ros2", str(bag))
    assert r.returncode == 0, r.stderr
    assert (bag / "metadata.yaml").is_file() and list(bag.glob("*.mcap"))
    rec = read_recording(recording)
    msgs = _read_bag(bag)
    per_tick = ["/tf", "/omniformation/followers", "/omniformation/slots", "/cmd_vel",
                "/omniformation/follower1/error", "/omniformation/follower2/error",
                "/omniformation/follower1/cmd_vel", "/omniformation/follower2/cmd_vel"]
    assert sorted(msgs) == sorted([*per_tick, "/camera/image/compressed"])
    start_ns = int(rec.metadata["start_ns"])
    tick_ns = [start_ns + int(round(t * 1e9)) for t in rec.t]
    for topic in per_tick:
        assert [ts for ts, _ in msgs[topic]] == tick_ns, topic  # one per tick, at its session time
    assert len(rec.ticks) == TICKS
    assert [ts for ts, _ in msgs["/camera/image/compressed"]] == [start_ns + int(round(t * 1e9)) for t in rec.frame_t]
    assert len(msgs["/camera/image/compressed"]) == len(rec.frames) >= 10
    for k in (0, TICKS // 2, TICKS - 1):
        d = rec.ticks[k]
        poses = msgs["/omniformation/followers"][k][1]
        assert poses.header.frame_id == "leader"
        assert poses.header.stamp.sec * 1_000_000_000 + poses.header.stamp.nanosec == tick_ns[k]
        for i, p in enumerate(poses.poses):
            want = [math.nan if v is None else v for v in d["p_est"][i]]
            np.testing.assert_allclose([p.position.x, p.position.y], want, atol=1e-9)
        cmd = msgs["/omniformation/follower2/cmd_vel"][k][1]
        np.testing.assert_allclose([cmd.linear.x, cmd.angular.z], d["commands"][1], atol=1e-9)
        lead = msgs["/cmd_vel"][k][1]
        np.testing.assert_allclose([lead.linear.x, lead.angular.z], d["leader_twist"], atol=1e-9)
        tf = msgs["/tf"][k][1]
        children = {t.child_frame_id: t for t in tf.transforms}
        assert children["leader"].header.frame_id == "world"
        np.testing.assert_allclose([children["leader"].transform.translation.x,
                                    children["leader"].transform.translation.y], d["leader"][:2], atol=1e-9)
    jpeg = msgs["/camera/image/compressed"][0][1]
    assert jpeg.format == "jpeg" and bytes(jpeg.data[:2]) == b"\xff\xd8"
    rec.close()


def test_a_damaged_recording_exports_what_it_holds_and_says_what_was_lost(recording, tmp_path):
    data = bytearray(recording.read_bytes())
    whole = read_recording(recording)
    held = len(whole.ticks) + len(whole.frames)
    whole.close()
    for at, name in ((0.45, "flipped"), (0.7, "cut")):
        bad = tmp_path / f"{name}.mcap"
        if name == "flipped":
            damaged = bytearray(data)
            for k in range(int(len(data) * at), int(len(data) * at) + 64):
                damaged[k] ^= 0x5A
            bad.write_bytes(bytes(damaged))
        else:
            bad.write_bytes(bytes(data[: int(len(data) * at)]))
        rec = read_recording(bad)
        assert rec.loss_note(), name
        out = tmp_path / f"{name}-bag"
        r = main_cli("export", str(bad), "--ros2", str(out))
        assert r.returncode == 0, r.stderr
        assert rec.loss_note() in r.stderr and "lost" in r.stderr
        msgs = _read_bag(out)
        assert len(msgs["/tf"]) == len(msgs["/cmd_vel"]) == len(rec.ticks)
        assert len(msgs.get("/camera/image/compressed", [])) == len(rec.frames)
        assert len(rec.ticks) + len(rec.frames) < held  # something was lost, and the bag has the rest
        rec.close()


def test_bad_input_is_one_line_and_exit_2_and_nothing_is_lost(recording, tmp_path):
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("keep me")
    bag = tmp_path / "bag"
    assert main_cli("export", str(recording), "--ros2", str(bag)).returncode == 0
    cases = [
        (("export", str(text), "--ros2", str(tmp_path / "a")), "not an MCAP file"),
        (("export", str(tmp_path / "none.mcap"), "--ros2", str(tmp_path / "b")), "no such recording"),
        (("export", str(recording), "--ros2", str(bag)), "exists; give --overwrite"),
        (("export", str(recording), "--ros2", str(mine), "--overwrite"), "not a ROS 2 bag"),
        (("export", str(recording), "--ros2", str(tmp_path / "no" / "bag")), "does not exist"),
        (("export", str(recording)), "--ros2"),
    ]
    for args, words in cases:
        r = main_cli(*args)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and "Traceback" not in r.stderr, (args, r.stderr)
    assert (mine / "thesis.tex").read_text() == "keep me"  # never replaced
    assert not (tmp_path / "a").exists() and not list(tmp_path.glob(".*partial*"))
    before = (bag / "metadata.yaml").stat().st_mtime_ns
    r = main_cli("export", str(recording), "--ros2", str(bag), "--overwrite")  # a bag may be replaced
    assert r.returncode == 0, r.stderr
    assert (bag / "metadata.yaml").stat().st_mtime_ns != before and len(_read_bag(bag)["/tf"]) == TICKS
