"""A recording is the session as it was: one clock over the whole of it (a reset sets the
loop's clock back, not the session's), the settings in force at any moment, a report that
splits at resets instead of drawing lines back to the start. The live loop ticked by hand,
the real writer, the real reader, the report, and a real replay server."""

from __future__ import annotations

import json

import numpy as np

from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import Params, ParamsStore
from app.recording.reader import params_from_recording, read_recording, session_clock
from app.recording.report import scan, summarise, write_report
from app.recording.writer import Recorder


def session_with_a_reset(path):
    """60 ticks; k_f1 to 0.15 at tick 30; STOP at 45; a reset at tick 60 (the loop's clock back
    to 0); 90 ticks more, released."""
    store = ParamsStore(Params(n_followers=2, leader_mode="straight"))
    loop = ServiceLoop(store, Backends(seed=4), rate_hz=30.0)
    rec = Recorder(path, {"scenario": "reset-test"}, store.get(), frame_rate_hz=0.0)
    loop.subscribe(rec.on_tick)
    store.subscribe(rec.on_params)
    loop_t = []
    for k in range(150):
        if k == 30:
            store.update("browser:1", k_f1=0.15)
        if k == 45:
            store.update("browser:1", stop=True)
        if k == 60:
            store.update("browser:1", reset_requests=True, stop=False, leader_hold=False)
        loop_t.append(loop.tick().t)
    loop.close_team()
    rec.close()
    return np.array(loop_t)


def test_a_reset_sets_back_the_loops_clock_not_the_sessions(tmp_path):
    loop_t = session_with_a_reset(tmp_path / "s.mcap")
    assert np.any(np.diff(loop_t) < 0)  # the loop's own clock did go back
    back = read_recording(tmp_path / "s.mcap")
    assert len(back.t) == 150 and np.all(np.diff(back.t) > 0)  # the session's never does
    assert abs(back.t[-1] - back.t[0] - 149 / 30) < 1e-6  # one tick apart, the reset included
    resets = [e for e in back.events if e["kind"] == "reset"]
    assert len(resets) == 1 and abs(resets[0]["t"] - back.t[59]) < 1e-6, back.events  # asked at the tick before
    assert np.allclose([back.ticks[k]["t"] for k in (59, 60)], loop_t[59:61], atol=1e-5)  # each tick keeps the loop's own t
    # the settings in force at a moment, not those at the start
    assert params_from_recording(back, float(back.t[10])).gains.k_f1 == 0.1
    assert params_from_recording(back, float(back.t[40])).gains.k_f1 == 0.15
    assert params_from_recording(back, float(back.t[50])).stop
    assert params_from_recording(back, float(back.t[149])).gains.k_f1 == 0.15  # a reset keeps the settings


def test_the_report_splits_a_reset_session_and_never_steps_back_in_time(tmp_path):
    session_with_a_reset(tmp_path / "s.mcap")
    back = read_recording(tmp_path / "s.mcap")
    sc = scan(back)
    t = sc.shown.t[np.isfinite(sc.shown.t)]
    assert np.all(np.diff(t) > 0)  # no line drawn back to the start
    assert np.isnan(sc.shown.t).sum() == 1  # one break, at the reset
    summary = summarise(back, sc)
    assert [g["reset"] for g in summary["segments"]] == [False, True]
    assert summary["segments"][1]["from_s"] > summary["segments"][0]["to_s"]
    assert summary["duration_s"] <= 150 / 30  # the whole session, not the clock after the reset
    for f in summary["followers"]:  # settling measured on the session's clock: within it
        assert f["settling_time_s"] is None or 0 <= f["settling_time_s"] <= summary["duration_s"] + 1e-6, f
    (tmp_path / "out").mkdir()
    written = write_report(back, tmp_path / "out", fmt="svg")
    assert (tmp_path / "out" / "trajectory.svg").read_text(encoding="utf-8").lstrip().startswith("<?xml")
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["segments"]
    assert all(p.suffix in (".svg", ".json", ".md") for p in written)


def test_older_recordings_that_set_time_back_read_on_one_clock():
    t = np.array([0.0, 1 / 30, 2 / 30, 3 / 30, 0.0, 1 / 30, 2 / 30])
    out = session_clock(t)
    assert np.all(np.diff(out) > 0) and np.allclose(np.diff(out), 1 / 30)
    same = np.array([0.0, 0.5, 0.5, 1.0])
    assert session_clock(same) is same


def test_the_replay_shows_the_settings_in_force_at_the_moment_shown(tmp_path):
    from app.services.replay import ReplayService

    session_with_a_reset(tmp_path / "s.mcap")
    back = read_recording(tmp_path / "s.mcap")
    replay = ReplayService(back, host="127.0.0.1", port=0)
    try:
        replay.seek(10)
        assert replay.store.get().gains.k_f1 == 0.1
        assert replay.dashboard.controls.gains["k_f1"].value == 0.1
        replay.seek(40)
        assert replay.store.get().gains.k_f1 == 0.15
        assert replay.dashboard.controls.gains["k_f1"].value == 0.15
        replay.seek(120)  # after the reset: on the timeline, with what was in force then
        assert abs(float(replay.timeline.value) - round(float(back.t[120]), 3)) < 1e-6
        assert replay.store.get().gains.k_f1 == 0.15 and not replay.store.get().stop
        replay.seek(5)  # and back
        assert replay.dashboard.controls.gains["k_f1"].value == 0.1
        # every event listed in time order and marked on the timeline; choosing one goes there
        labels = list(replay.event_list.options)[1:]
        assert len(labels) == len(back.events) and any("reset" in label for label in labels)
        assert len(replay.timeline._impl.props._marks or ()) == len(back.events)  # (viser keeps them private)
        k = next(i for i, label in enumerate(labels) if "reset" in label)
        t = replay.go_to_event(k)
        assert float(back.t[replay.index]) >= t - 1e-6 and replay.index > 0
    finally:
        replay.close()


def test_the_recordings_panel_says_what_this_session_records(tmp_path):
    """While a session records, its own file is not offered (it is being written) and the panel
    says so, instead of "(no recordings yet)"."""
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.services.recording import start_recording

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(port=0, n_followers=2, recordings=tmp_path)
    recorder = start_recording(svc, config, None, None, None, 0.0, tmp_path / "now.mcap", tmp_path)
    try:
        assert list(svc.recordings.menu.options) == ["(no recordings yet)"]
        assert svc.recordings.links.content.startswith("Recording now: ") and "now.mcap" in svc.recordings.links.content
    finally:
        svc.close()
        recorder.close()


def test_the_status_says_start_up_while_the_camera_finds_the_team_not_lost(tmp_path):
    """During the vision start-up the followers are being found, not lost: the status says
    what the overlay says."""
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(port=0, n_followers=2, camera=config.camera(), recordings=tmp_path)
    try:
        state = svc.loop.tick()
        assert state.phase in ("base", "probe", "heading", "find")
        svc.dashboard.controls.update_status(state)
        text = svc.dashboard.controls.status.content
        assert "start-up (" in text and "found so far" in text and ", lost " not in text, text
    finally:
        svc.close()


def test_a_robot_chosen_in_the_3d_view_is_described_each_tick(tmp_path):
    """Its pose in the leader frame, its slot and error, its command and the link, as the tick
    has them (``select`` is what a click on a robot's body or marker runs)."""
    from app.services.live import Service
    from app.dashboard.widgets import on_page_thread

    svc = Service(port=0, n_followers=2, recordings=tmp_path)
    try:
        svc.publisher.close()  # the page drawn here only, tick by tick (no other thread draws meanwhile)
        scene = svc.dashboard.scene
        state = svc.loop.tick()
        assert on_page_thread(svc.server, lambda: scene.update(state))
        assert "click a robot" in svc.dashboard.controls.selected.content
        scene.select(1)
        state = svc.loop.tick()
        scene._trail_at = -1.0  # the next update is a tenth of a second on: it describes
        assert on_page_thread(svc.server, lambda: scene.update(state))
        text = svc.dashboard.controls.selected.content
        err = float(np.hypot(*(state.p_d[1] - state.p_est[1]))) * 100
        assert text.startswith("**F2** (tracked)") and f"estimated error {err:.1f} cm" in text, text
        assert f"x {state.p_est[1][0] * 100:+.1f} cm" in text and f"v {state.commands[1][0]:+.3f} m/s" in text
        assert scene.picked[1].visible and not scene.picked[0].visible  # the one clicked is ringed in 3D
        true_err = float(np.hypot(*(state.p_d[1] - state.p_true[1]))) * 100
        assert f"estimated error {err:.1f} cm · true error {true_err:.1f} cm" in text, text
    finally:
        svc.close()


def test_a_recorded_parameter_set_of_any_shape_becomes_valid_settings():
    """A damaged or hostile params record never stops a replay: every field that is not what
    the page could set is skipped (the default stays), the rest is clamped as the page would."""
    from app.recording.reader import params_from_payload

    default = Params()
    for bad in (None, [], "gains", 3, {"gains": [1, 2]}, {"gains": {"k_f1": "x", "reset_requests": 5, "stop": True}},
                {"slots": [[float("nan"), 0.0]], "n_followers": 2.5, "leader_mode": "warp", "goal": "far"},
                {"leader_speed_mps": 1e308, "leader_turn_deg_s": float("-inf"), "safety_distance_m": [0.3]}):
        p = params_from_payload(bad)  # type: ignore[arg-type]
        assert p.gains == default.gains and not p.stop and p.reset_requests == 0, bad
        assert p.leader_mode == default.leader_mode and p.n_followers == default.n_followers
    clamped = params_from_payload({"leader_speed_mps": 1e308, "gains": {"k_f1": 50.0}})
    assert clamped.leader_speed_mps == 0.3 and clamped.gains.k_f1 == 1.0
