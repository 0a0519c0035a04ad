"""The loop's start-up and its process: what `run` promises (docs/safety.md, README)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
from websockets.exceptions import ConnectionClosed

from app.services.page_process import ORPHAN_S
from tests.helpers import RawPage

if TYPE_CHECKING:
    from app.services.live import Service

WARM = "warmed the loop's kernels"  # app.live.warmup.WARM_LINE, as a reader of the output sees it


def _run(cache: Path, until: str = "dashboard at") -> tuple[str, str]:
    """`omniformation run` on the simulator (no recording) with numba's cache in ``cache``, until a line
    with ``until`` and a second of ticks; then Ctrl-C. Its stdout and stderr."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--feedback",
                             "truth"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    lines = []
    watchdog = threading.Timer(600.0, proc.kill)  # a run that never says so fails, it does not hang
    watchdog.start()
    for line in proc.stdout:
        lines.append(line)
        if until in line:
            break
    watchdog.cancel()
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return "".join(lines) + out, err


def test_a_fresh_cache_is_compiled_before_the_clock_starts_and_only_once(tmp_path: Path) -> None:
    out, err = _run(tmp_path, WARM)
    assert out.count(WARM) == 1, out  # one line, with how long it took
    assert "compiled while the loop's clock ran" not in err, err  # no kernel left for a paced tick to compile
    out, err = _run(tmp_path)
    assert WARM not in out, out  # the cache keeps them: the second run says nothing
    assert "compiled while the loop's clock ran" not in err, err


def test_the_warm_up_step_refuses_arguments_in_one_line(tmp_path: Path) -> None:
    """`python -m app.services.warmup` (a step of `make test`) warms what `run` reaches with the default
    config: an argument is a mistake, said in one line with exit code 2, before anything is compiled."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    done = subprocess.run([sys.executable, "-m", "app.services.warmup", "--config", "x.toml"], capture_output=True,
                          text=True, env=env, timeout=120)
    assert done.returncode == 2, done
    assert done.stderr.strip().splitlines() == ["python -m app.services.warmup: takes no arguments (got '--config x.toml')"]
    assert done.stdout == "" and not any(tmp_path.iterdir())  # nothing compiled into the cache


# A vision loop as `make run` serves it, warmed and run for 90 ticks with numba's cache where the
# environment says; prints the loop's own counts (with `list`: each kernel's cache folder and source file, after
# the warm-up alone).
_VISION_RUN = """
import json, sys, threading, time
from app.live import warmup
from app.live.config import DEFAULT_CONFIG, load_service_config
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import MAX_FOLLOWERS, Params, ParamsStore, default_slots
config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
loop = ServiceLoop(ParamsStore(Params(n_followers=3, slots=default_slots(3))),
                   Backends(camera=config.camera(), dynamics=config.dynamics), rate_hz=30.0)
warmup.warm_up(loop)
at_start = warmup.compiled()
files = sorted({(fn._cache._cache_path, fn.py_func.__code__.co_filename) for fn in warmup.kernels()})
if sys.argv[1:] == ["list"]:
    print(json.dumps({"files": files}))
    sys.exit(0)
runner = threading.Thread(target=loop.run)
runner.start()
while loop.tick_count < 90 and runner.is_alive():
    time.sleep(0.05)
loop.stop()
runner.join()
print(json.dumps({"late": warmup.compiled() - at_start, "dropped": loop.ticks_dropped,
                  "ticks": loop.tick_count}))
"""


def _vision_run(env: dict[str, str], *args: str) -> tuple[dict[str, Any], str]:
    import json

    done = subprocess.run([sys.executable, "-c", _VISION_RUN, *args], capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, **env))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    return json.loads(lines[-1]), "\n".join(lines[:-1])


def test_a_cache_cold_for_one_module_is_warmed_before_the_clock_and_no_tick_is_skipped(tmp_path: Path) -> None:
    """numba's cache warm for every kernel but the tracker's (its module's files removed, as an edit
    of that module would invalidate them): the tracker is first used only once the pipeline's
    start-up is over, and it must still be compiled before the loop's clock starts."""
    import shutil

    from numba.core.caching import _CacheLocator

    warm, _ = _vision_run({}, "list")  # the cache the environment keeps (compiled here if it was cold)
    cold = 0
    for folder, source in warm["files"]:
        into = tmp_path / _CacheLocator.get_suitable_cache_subpath(source)  # where NUMBA_CACHE_DIR puts it
        into.mkdir(parents=True, exist_ok=True)
        stem = Path(source).stem + "."
        for f in Path(folder).glob(stem + "*"):
            if Path(source).name == "tracking.py":
                cold += 1  # left out: this module's cache is cold
            else:
                shutil.copy2(f, into / f.name)
    assert cold, warm["files"]  # the tracker's module had cached kernels to leave out
    counts, said = _vision_run({"NUMBA_CACHE_DIR": str(tmp_path)})
    assert said.count(WARM) == 1, said  # one line: something was compiled, and how long it took
    assert counts["late"] == 0, counts  # nothing left for a paced tick to compile
    assert counts["ticks"] >= 90 and counts["dropped"] == 0, counts  # the loop's own count of skipped ticks

# -- the page in a process of its own (docs/safety.md, "The page in a process of its own") ---------------

def _until(what: Callable[[], bool], timeout: float = 120.0) -> bool:
    end = time.monotonic() + timeout
    while not what():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


@pytest.fixture
def service() -> Iterator[Service]:
    from app.services.live import Service

    svc = Service(host="127.0.0.1", port=0, n_followers=2, rate_hz=30.0, page_process=True)  # truth feedback
    svc.start()
    yield svc
    svc.close()


def test_killing_the_page_process_stops_the_robots_until_released_on_the_new_page(service: Service) -> None:
    page = service.page
    assert page is not None
    port, first = page.port, page.pid
    assert _until(lambda: service.loop.tick_count > 3)
    client = RawPage(port)
    assert client.wait_for("STOP")  # the page serves the loop's state
    client.close()
    assert not service.store.get().stop
    os.kill(first, signal.SIGKILL)
    assert _until(lambda: service.store.get().stop)  # the dead man's switch
    ticks = service.loop.tick_count
    assert _until(lambda: page.restarts == 1 and page.served == 2)
    newcomer = RawPage(port)  # the same address and port
    assert newcomer.wait_for("STOPPED")  # the new page shows the hold
    assert service.loop.tick_count > ticks  # the loop went on observing all along
    last = service.loop.last
    assert last is not None and last.stopped and not last.commands.any()  # every follower at zero
    assert service.store.get().stop  # held: nothing but a Release lifts it
    newcomer.click("Release STOP")
    assert _until(lambda: not service.store.get().stop)  # an operator's Release, through the loop's store
    newcomer.close()


def test_stop_from_a_second_client_reaches_the_loop_during_a_flood(service: Service) -> None:
    from app.cli.bench.loop import FLOODER, FLOODER_ADDRESS

    page = service.page
    assert page is not None
    flooder = subprocess.Popen([sys.executable, "-c", FLOODER, str(page.port), "refused", "8", FLOODER_ADDRESS,
                                "no-such-control"],
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert flooder.stdout is not None
        flooder.stdout.readline()  # flooding
        operator = RawPage(page.port, source="127.0.0.61")
        assert operator.wait_for("STOP")
        time.sleep(1.0)  # well into the flood
        ticks = service.loop.tick_count
        operator.click("STOP")
        assert _until(lambda: service.store.get().stop)  # through the pipe, the loop's store
        assert operator.wait_for("STOPPED")  # and back on the page
        assert _until(lambda: service.loop.last is not None and service.loop.last.stopped
                      and not service.loop.last.commands.any())
        assert service.loop.tick_count > ticks
        operator.close()
    finally:
        flooder.kill()
        flooder.wait(30)


@contextlib.contextmanager
def _served(*args: str, pattern: str = r"dashboard at http://127\.0\.0\.1:(\d+)/",
            stderr: int = subprocess.DEVNULL) -> Iterator[tuple[subprocess.Popen[str], int]]:
    """`run --port 0 --loop-process ARGS` as a real process: (the process, its page's port once it
    says where it serves); killed on the way out, whatever happened (a watchdog ends a hang)."""
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", *args, "--loop-process"],
                            stdout=subprocess.PIPE, stderr=stderr, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.stdout is not None
    watchdog = threading.Timer(300.0, proc.kill)
    watchdog.start()
    try:
        port = 0
        for line in proc.stdout:
            found = re.search(pattern, line)
            if found:
                port = int(found.group(1))
                break
        assert port
        yield proc, port
    finally:
        watchdog.cancel()
        proc.kill()
        proc.wait(30)


def test_when_the_loop_process_dies_the_page_says_so_at_once(tmp_path: Path) -> None:
    with _served("--no-record", "--feedback", "truth") as (proc, port):
        page = RawPage(port)
        assert page.wait_for("running")  # the loop's state on the page
        proc.kill()  # the loop's process, at once (SIGKILL: no goodbye)
        assert page.wait_for("THE LOOP HAS ENDED", timeout=30.0)
        # and it stays said until the page ends (ORPHAN_S): no tick queued before the loop died is
        # drawn over it (one fresh-clone run saw the page close without the notice ever arriving)
        after: list[str] = []
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            for msg in page.messages(ORPHAN_S + 30.0):
                after.append(str(msg))
        assert not [m for m in after if "**running**" in m or "**STOPPED" in m]
        page.close()


def test_camera_frames_travel_to_the_page_at_its_camera_panels_rate_only() -> None:
    """With vision and a browser on the page, every tick's state goes to the page, and one in every
    ``frame_every`` ticks carries the camera's frame (the camera panel's redraw rate); the page
    shows them. With nobody on the page: one state in UNWATCHED_EVERY, and no frame."""
    from app.services.page_process import UNWATCHED_EVERY
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(host="127.0.0.1", port=0, n_followers=2, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics, page_process=True)
    svc.start()
    try:
        page = svc.page
        assert page is not None and page.frame_every == 3  # 30 Hz ticks, the panel redraws every 0.1 s
        assert _until(lambda: svc.loop.tick_count > 30)
        assert page.frames_sent == 0 and page.states_sent > 0  # nobody has the page open: no frame rendered
        handed, ticks = page.handed, svc.loop.tick_count
        assert _until(lambda: svc.loop.tick_count > ticks + 30)
        assert page.handed - handed <= (svc.loop.tick_count - ticks) // UNWATCHED_EVERY + 2  # and one state in ten
        client = RawPage(page.port)
        image, shown = "", 0
        for msg in client.messages(60.0):
            if (msg.get("props") or {}).get("label") == "leader's camera":
                image = msg["uuid"]
            elif image and msg.get("uuid") == image and "_data" in msg.get("updates", {}):
                shown += 1  # a frame drawn on the page
                if shown >= 3:
                    break
        assert shown >= 3
        assert _until(lambda: page.frames_sent >= 3)
        ticks = svc.loop.tick_count  # read after the count: the ticks it may have come from are all in
        assert page.frames_sent <= ticks // page.frame_every + 1  # never more than one in frame_every ticks
        assert page.states_sent > page.frames_sent  # the states between went without a frame
        handed, ticks = page.handed, svc.loop.tick_count
        assert _until(lambda: svc.loop.tick_count > ticks + 30)
        assert page.handed - handed >= svc.loop.tick_count - ticks - 2  # watched: every tick's state
        client.close()  # the page closed: no frame is rendered or sent again
        assert _until(lambda: page.clients == 0)
        sent, ticks = page.frames_sent, svc.loop.tick_count
        assert _until(lambda: svc.loop.tick_count > ticks + 30)
        assert page.frames_sent <= sent + 1  # (one may have been on its way)
    finally:
        svc.close()


def test_an_unwatched_pages_state_carries_the_longest_frame_to_command_of_the_ticks_it_stands_for() -> None:
    """With no browser on the page, one state in UNWATCHED_EVERY goes to it; the page's health rule
    raises an alarm for a tick longer than a period, so the state that goes carries the longest
    frame-to-command of the ticks since the last one went (one long tick among the skipped ones
    is not lost), and its own when it is the longest or when none of them observed anything."""
    import dataclasses

    from app.params import Params, ParamsStore
    from app.services.page_process import UNWATCHED_EVERY, PageProcess
    from tests.app.dashboard.test_health import tick as state_at

    page = PageProcess(ParamsStore(Params()), "127.0.0.1", 0, None, None)
    handed: list[Any] = []
    page._sender.close()
    page._sender = handed.append  # what goes to the page's process, in order
    every = UNWATCHED_EVERY
    latencies = [5.0] * (3 * every)
    latencies[every + 3] = 80.0  # a long tick among the second window's skipped ones
    latencies[2 * every + 2] = float("nan")  # in the third: one that observed nothing, then a short one
    for k, ms in enumerate(latencies):
        page.on_tick(dataclasses.replace(state_at(k / 30), tick=k, latency_ms=ms))
    assert [s.tick for s in handed] == [0, every, 2 * every]
    assert [s.latency_ms for s in handed] == [5.0, 5.0, 80.0]
    page.on_tick(dataclasses.replace(state_at(1.0), tick=3 * every, latency_ms=float("nan")))  # its own: none
    assert handed[-1].latency_ms == 5.0
    page.clients = 1  # a browser: every state as it is
    page.on_tick(dataclasses.replace(state_at(1.0), tick=3 * every + 1, latency_ms=float("nan")))
    assert handed[-1].tick == 3 * every + 1 and handed[-1].latency_ms != handed[-1].latency_ms


def test_a_real_camera_runs_in_the_loops_process_and_its_frames_show_on_the_page(tmp_path: Path) -> None:
    """`run --camera VIDEO --loop-process`: the camera, the vision pipeline and the recorder in the
    loop's process, the frames drawn by the page's process (its Calibration panel finds the mirror in
    them); Ctrl-C ends both, the recording is one file."""

    from tests.app.backends.test_real_rig import render_frames

    import cv2

    frames = render_frames(tmp_path, 6)
    video = tmp_path / "rig.avi"  # 20 s at 30 fps: it plays on through the start-up and its warm-up
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (frames[0].shape[1], frames[0].shape[0]))
    for k in range(600):
        writer.write(frames[k % len(frames)])
    writer.release()
    with _served("--camera", str(video), "--link", "none", "--followers", "3", "--record", str(tmp_path / "run.mcap"),
                 pattern=r"dashboard at http://127\.0\.0\.1:(\d+)/ .*vision pipeline on camera",
                 stderr=subprocess.PIPE) as (proc, port):
        page = RawPage(port)
        image, shown, recording = "", 0, False
        for msg in page.messages(60.0):
            recording = recording or "Recording now: " in str(msg)  # the file being written, told by the loop
            if (msg.get("props") or {}).get("label") == "leader's camera":
                image = msg["uuid"]
            elif image and msg.get("uuid") == image and "_data" in msg.get("updates", {}):
                shown += 1
            if shown >= 3 and recording and "Propose from image" in page.buttons:
                break
        assert shown >= 3  # the camera's frames, drawn by the page's process
        page.click("Propose from image")  # the Calibration panel, on the full-size frames the loop sent
        assert page.wait_for("mirror circle: centre")
        assert recording and "Replay in a new tab" in page.buttons  # the Recordings panel, served by the page
        page.click("Replay in a new tab")  # the newest of recordings/ (the samples): served by the page's process
        assert page.wait_for("](http://127.0.0.1:")  # the replay's link, for this operator
        page.close()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        assert "all followers commanded to zero" in out and "Traceback" not in err, (out, err)
        from app.recording.reader import read_recording

        assert len(read_recording(tmp_path / "run.mcap").ticks) > 0  # the session recorded, as one file


def test_a_fleet_leader_with_the_page_in_its_own_process_shows_the_bus_on_the_page() -> None:
    """`run --fleet --loop-process`: the bridge runs in the loop's process (its states go on the bus,
    its STOP reaches the loop's store); the bus's status line travels over the pipe to the page."""
    import json

    import zenoh

    from app.fleet.bridge import loopback_endpoint

    endpoint = loopback_endpoint()
    session = None
    with contextlib.ExitStack() as stack:
        proc, port = stack.enter_context(_served("--feedback", "truth", "--no-record", "--fleet", "lp", "--leader-id", "L1",
                                                 "--zenoh-connect", endpoint))
        stack.callback(lambda: session.close() if session is not None else None)
        page = RawPage(port)
        assert page.wait_for("fleet lp/L1: disconnected")  # no peer yet: said on the page
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", json.dumps([endpoint]))
        session = zenoh.open(c)
        states: list[dict[str, Any]] = []
        sub = session.declare_subscriber("omniformation/lp/leader/L1/state",
                                         lambda s: states.append(json.loads(s.payload.to_bytes())))
        assert page.wait_for("fleet lp/L1: connected (1 peer)")  # the bus came up: the line changed
        assert _until(lambda: len(states) > 5)  # the loop's states on the bus
        page.close()
        sub.undeclare()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0 and "all followers commanded to zero" in out, out


def test_an_arena_leader_with_the_page_in_its_own_process_drives_its_robots_and_shows_its_page() -> None:
    """`run --arena --loop-process`: the arena team, the bridge and the adopter in the loop's process
    (its states on the bus, its commands to the arena); the page in its own, showing the loop running."""
    import json

    from app.fleet.bridge import loopback_endpoint
    from tests.helpers import ROOT, fleet_session, interrupt

    endpoint = loopback_endpoint()
    arena = subprocess.Popen([sys.executable, "-m", "app.cli", "arena", "three_teams", "--zenoh-listen", endpoint,
                              "--status-every", "0"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                             text=True)
    session = None
    try:
        assert arena.stdout is not None and "arena three_teams" in arena.stdout.readline()
        session = fleet_session(None, None, endpoint)
        states: list[dict[str, Any]] = []
        sub = session.declare_subscriber("omniformation/three_teams/leader/L1/state",
                                         lambda s: states.append(json.loads(s.payload.to_bytes())))
        with _served("--arena", "three_teams", "--leader-id", "L1", "--zenoh-connect", endpoint,
                     "--no-record") as (proc, port):
            page = RawPage(port)
            assert page.wait_for("running")  # the loop's state, drawn by the page's process
            assert _until(lambda: len(states) > 5)  # the loop's states on the bus
            assert _until(lambda: any(s.get("robots") and not s["stopped"] and _moving(s["commands"])
                                      for s in states[-5:]))  # it leads robots and drives them
            page.close()
            proc.send_signal(signal.SIGINT)
            out, _ = proc.communicate(timeout=60)
            assert proc.returncode == 0 and "all followers commanded to zero" in out, out
        sub.undeclare()
    finally:
        if session is not None:
            session.close()
        interrupt(arena)


def _moving(commands: list[list[float | None]]) -> bool:
    return any(abs(x) > 0 for row in commands for x in row if x is not None)


def test_the_pages_health_banner_judges_the_loops_rate_and_skipped_ticks(service: Service) -> None:
    """The page's health rules (docs/page-access.md) know the loop's target rate and its count of
    skipped ticks: a loop held back raises both alarms, which come back to the loop's process."""
    heard: list[str] = []
    service.dashboard.controls.health.listeners.append(lambda _t, text: heard.append(text))
    held = threading.Event()

    def slow(s: Any) -> None:  # a loop held back: 45 ms a tick for a 33 ms period (20 Hz), until both are heard
        if s.tick > 30 and not held.is_set():
            time.sleep(0.045)

    service.loop.subscribe(slow)
    try:
        assert _until(lambda: any("ticks skipped" in h for h in heard) and any("of its 30 Hz" in h for h in heard))
    finally:
        held.set()
    skipped = sum(int(h.split(" ")[0]) for h in heard if h.endswith("ticks skipped (the loop fell behind)"))
    assert 0 < skipped <= service.loop.ticks_dropped  # the loop's own count, none made up


def test_the_tuning_panel_runs_its_step_tests_and_sweeps_on_the_loops_side(service: Service) -> None:
    """The page's Tuning panel (in the page's process): a step test and a sweep asked from the page
    run on the loop's side (its StepTests and SweepRunner), their row and result come back and show,
    and show again on the page started after a crash."""
    page = service.page
    assert page is not None
    client = RawPage(page.port)
    assert client.wait_for("Run sweep")  # the panel is served
    client.set("Measure for (s)", 3.0)
    client.set("Range 1", "1:4:2")
    client.set("Gain 2", "none")
    assert _until(lambda: service.loop.tick_count > 30)
    client.click("Run test")
    assert client.wait_for("step test: trial 1 done")  # the row, measured on the loop's side, on the page
    assert [t.status for t in service.tests.trials] == ["done"] and service.tests.trials[0].test.window_s == 3.0
    client.click("Run sweep")
    assert client.wait_for("sweep: done, 2 of 2 points")  # the result came back; the page drew its figure
    result = service.sweeps.last
    assert result is not None and [float(v) for v in result.ranges[0].values] == [1.0, 4.0]
    client.close()
    os.kill(page.pid, signal.SIGKILL)  # a new page is told the rows and the last sweep
    assert _until(lambda: page.restarts == 1 and page.served == 2)
    newcomer = RawPage(page.port)
    seen = {"row": False, "sweep": False}
    for msg in newcomer.messages(60.0):
        seen["row"] = seen["row"] or "step test: trial 1 done" in str(msg)
        seen["sweep"] = seen["sweep"] or "sweep: done, 2 of 2 points" in str(msg)
        if all(seen.values()):
            break
    assert seen == {"row": True, "sweep": True}
    newcomer.close()


def test_tuning_messages_of_no_known_shape_are_refused_and_start_nothing(service: Service) -> None:
    """docs/safety.md: the loop's side builds a test or a sweep only from plain values of the
    documented shape, checked as the panel's buttons are; anything else is answered and refused."""
    answers: list[tuple[Any, ...]] = []
    tuning = service.page_tuning
    tuning.post = answers.append
    test = {"kind": "offset", "follower": 0, "size": 0.1, "formation": "line abreast", "window_s": 3.0}
    ask = {"gain1": "k_w2", "range1": "1:4:2", "gain2": "none", "range2": "", "feedback": "truth"}
    hostile: list[tuple[Any, ...]] = [
        ("tuning", 1, "test", {**test, "size": 5.0}),  # beyond the panel's 50 cm
        ("tuning", 2, "test", {**test, "window_s": 1e9}),
        ("tuning", 3, "test", {**test, "follower": 7}),
        ("tuning", 4, "test", {**test, "kind": "shutdown"}),
        ("tuning", 5, "test", {**test, "extra": 1}),
        ("tuning", 6, "test", {**test, "size": "0.1"}),
        ("tuning", 7, "sweep", {"ask": {**ask, "gain1": "leader_speed_mps"}, "test": test}),
        ("tuning", 8, "sweep", {"ask": {**ask, "range1": "1:4:100000"}, "test": test}),
        ("tuning", 9, "sweep", {"ask": {**ask, "feedback": "vision"}, "test": test}),  # no synthetic rig here
        ("tuning", 10, "apply", {"k_w2": 99.0}),
        ("tuning", 11, "test"),
        ("tuning", 12),
    ]
    for msg in hostile:
        tuning.receive(msg)
    replies = [a for a in answers if a[1] == "reply"]
    assert [r[2] for r in replies] == list(range(1, 13))  # each answered, in order
    assert all(isinstance(r[3], str) and r[3] for r in replies), replies  # each refused, saying why
    assert not service.tests.trials and service.tests.status == "idle" and not service.sweeps.busy
    assert service.store.get().gains.k_w2 != 99.0
