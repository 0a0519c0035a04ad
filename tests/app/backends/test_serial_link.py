"""The follower link over a real pseudo-terminal: emulated followers, the serial link, the safety rules."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import serial

from app.backends.serial_link import SerialLink
from app.backends.emulator import PtyEndpoint
from core.link import protocol as p
from core.types import Commands

from tests.helpers import ROOT, EmulatorThread, plain, sealed, wait_for


def test_commands_reach_the_robots_and_odometry_comes_back(emulated):
    link = SerialLink(emulated.path, 3, v_max=0.3, w_max=2.0)
    try:
        wait_for(lambda: link.connects == 1, 5, "the port to open")
        for _ in range(30):  # 1 s at 30 Hz
            link.send(Commands(np.array([0.1, 5.0, math.nan]), np.array([0.5, 0.0, 0.0])))
            time.sleep(1 / 30)
        wait_for(lambda: link.stats[0].answered >= 29, 10, "the replies on their way")  # read on the link's thread
        robots = emulated.emulator.snapshot()
        v1, w1 = robots[1].measured(emulated.emulator.hw)
        assert v1 == pytest.approx(0.1, abs=0.01) and w1 == pytest.approx(0.5, abs=0.05)
        assert robots[2].target_l_mps == pytest.approx(0.3)  # 5 m/s was clamped to v_max on the way out
        assert robots[3].target_l_mps == 0.0  # NaN became zero
        v, w = link.measured()
        assert v[0] == pytest.approx(0.1, abs=0.01) and w[0] == pytest.approx(0.5, abs=0.05)
        s1 = link.stats[0]
        assert s1.answered >= 29 and s1.lost == 0 and s1.crc_errors == 0 and 0 < s1.rtt_mean_ms < 100
        assert s1.battery_mv == 7400  # from a STATUS answering a PING
        assert link.link_state.endswith(": ok")
    finally:
        link.close()

    def all_stopped() -> bool:  # the emulator's thread reads the STOP frames after close() returns
        robots = emulated.emulator.snapshot()
        return all(r.flags & p.FLAG_STOPPED and r.target_l_mps == 0 == r.target_r_mps for r in robots.values())

    wait_for(all_stopped, 5, "every robot to be stopped after close")


def test_lost_replies_and_crc_errors_are_counted_per_follower():
    em = EmulatorThread(drop=0.2, corrupt=0.1)
    link = SerialLink(em.path, 3)
    try:
        wait_for(lambda: link.connects == 1, 5, "the port to open")
        for _ in range(90):
            link.send(Commands(np.full(3, 0.05), np.zeros(3)))
            time.sleep(1 / 30)
        time.sleep(0.4)
        link.send(Commands.zeros(3))  # expires what is older than the reply timeout
        sent = sum(s.sent for s in link.stats)
        lost = sum(s.lost for s in link.stats)
        crc = sum(s.crc_errors for s in link.stats)
        assert em.emulator.stats.dropped > 0 and em.emulator.stats.corrupted > 0
        # a dropped or corrupted reply is a lost one; corrupted ones are also CRC errors
        assert 0.15 * sent < lost < 0.45 * sent
        assert crc >= 0.5 * em.emulator.stats.corrupted
        assert link.parser.rejected_total >= crc
        assert "lost" in link.detail()

        # every command written is answered, late, lost or still pending: the counts add up
        sent_now, settled, pending = link.tally()
        assert sent_now == sent == settled + pending

        def answered() -> bool:  # the loop keeps sending at 30 Hz; replies come back after the pause
            link.send(Commands.zeros(3))
            time.sleep(1 / 30)
            return link.connected

        wait_for(answered, 2, "the link to be answered again after the 0.4 s pause")

        def degraded() -> bool:  # about 28 % of replies dropped or corrupted: answered, but not "ok"
            link.send(Commands.zeros(3))
            time.sleep(1 / 30)
            state = link.link_state
            losses = [why for why in link.quality() if why]
            assert state.endswith(": ok") == (not losses), state  # "ok" exactly when no follower loses > 20 %
            return "degraded" in state and "% lost" in state

        wait_for(degraded, 10, "the link to say degraded with about 28 % of replies lost")
    finally:
        link.close()
        em.close()


def test_a_port_that_takes_no_bytes_is_reopened_after_three_stalled_writes():
    """Nobody reads the robots' end of this pty, so its buffer fills and writes time out.
    One timed-out write does not close the port (pyserial also times out a write that went
    out whole when the thread was held off the CPU); three in a row do, and it is reopened."""
    end = PtyEndpoint()
    link = SerialLink(end.path, 3)
    try:
        wait_for(lambda: link.connects == 1, 5, "the port to open")
        # The kernel moves bytes on from a full pty for a while after its first refusal, so a write
        # after a stall may go through (and the count starts again): send until the port closes.
        t0 = time.monotonic()
        stalls_seen: set[int] = set()
        before = 0
        while link.connects == 1 and link._port is not None:
            assert time.monotonic() - t0 < 30, "the pty's buffer never stayed full"
            before = link._stalled_writes
            link.send(Commands(np.full(3, 0.05), np.zeros(3)))
            if link._port is not None:
                stalls_seen.add(link._stalled_writes)
        assert {1, 2} <= stalls_seen  # one stall, then two in a row: still open
        assert before == 2  # closed by the third stall in a row, not before ...
        wait_for(lambda: link.connects == 2, 5, "the port to be reopened")  # ... and opened again
    finally:
        link.close()
        end.close()


def test_a_follower_stops_by_itself_when_commands_stop_coming(emulated):
    """The watchdog, through the real pty: one command, then silence (a hung service)."""
    port = serial.Serial(emulated.path, 115200, timeout=0.1)
    try:
        port.write(sealed(p.set_velocity(1, 1, 0.2, 0.0), counter=1))  # docs: the open key, no key given
        t_cmd = time.monotonic()
        hw = emulated.emulator.hw
        wait_for(lambda: emulated.emulator.snapshot()[1].measured(hw)[0] > 0.1, 1, "the follower to move")
        wait_for(lambda: emulated.emulator.snapshot()[1].flags & p.FLAG_WATCHDOG, 2, "the watchdog")
        assert 0.45 < time.monotonic() - t_cmd < 1.0  # 0.5 s after the last command, not before
        wait_for(lambda: not emulated.emulator.snapshot()[1].moving, 2, "the wheels to stop")
    finally:
        port.close()


def test_a_missing_port_never_blocks_the_loop():
    link = SerialLink("/nonexistent/ttyFOLLOWERS", 2)
    try:
        t0 = time.perf_counter()
        for _ in range(10):
            link.send(Commands(np.full(2, 0.1), np.zeros(2)))
        assert time.perf_counter() - t0 < 0.05
        wait_for(lambda: "cannot open" in link.link_state, 2, "the reason")
        assert link.link_state.startswith("link lost (cannot open /nonexistent/ttyFOLLOWERS")
        assert np.all(link.measured()[0] == 0)
    finally:
        link.close()


_SECOND_PROGRAM = """
import json, sys, time
import numpy as np
from app.backends.serial_link import SerialLink
from core.types import Commands
link = SerialLink(sys.argv[1], 3)
try:
    for _ in range(45):  # 1.5 s at 30 Hz, every robot at 0.2 m/s if it could
        link.send(Commands(np.full(3, 0.2), np.zeros(3)))
        time.sleep(1 / 30)
    print(json.dumps({"connects": link.connects, "state": link.link_state}))
finally:
    link.close()
"""


def test_a_port_one_link_holds_is_refused_to_a_second_program_until_the_first_lets_it_go(emulated):
    """Two programs never drive through one port: while a link holds it, a second program's link
    on the same path never opens it, writes nothing and says why; once the first closes, a link
    opens it at its next try."""
    import json
    import subprocess
    import sys

    from app.backends.serial_link import HELD_ELSEWHERE

    first = SerialLink(emulated.path, 3)
    try:
        wait_for(lambda: first.connects == 1, 5, "the port to open")
        second = subprocess.Popen([sys.executable, "-c", _SECOND_PROGRAM, emulated.path], stdout=subprocess.PIPE,
                                  text=True, cwd=ROOT)
        while second.poll() is None:
            first.send(Commands(np.full(3, 0.1), np.zeros(3)))
            time.sleep(1 / 30)
        out = json.loads(second.communicate(timeout=10)[0])
        assert out["connects"] == 0 and HELD_ELSEWHERE in out["state"], out
        for _ in range(5):  # the robots heard the first link only, to the last frame
            first.send(Commands(np.full(3, 0.1), np.zeros(3)))
            time.sleep(1 / 30)
        robots = emulated.emulator.snapshot()
        assert all(robots[a].target_l_mps == pytest.approx(0.1) for a in (1, 2, 3))
        assert first.answering().all() and first.connects == 1
    finally:
        first.close()
    after = SerialLink(emulated.path, 3)
    try:
        wait_for(lambda: after.connects == 1, 5, "the port to open once the first link let it go")
    finally:
        after.close()


def test_run_on_sigterm_stops_the_followers_on_the_wire(emulated, tmp_path):
    """SIGTERM stops every robot on the wire, an older one (protocol 2, driven as the operator
    allowed) too; every recorded tick's link state says the radio was unauthenticated by choice."""
    from app.backends.serial_link import ALLOWED_NOTE
    from app.recording.reader import read_recording
    from tests.helpers import serve_then_signal

    emulated.emulator.older = frozenset({2})  # R2 speaks protocol 2 only
    hw = emulated.emulator.hw
    moving = lambda: all(r.moving for r in emulated.emulator.snapshot().values())
    record = tmp_path / "s.mcap"
    run = serve_then_signal("--port", "0", "--feedback", "truth", "--record", str(record), "--link",
                            f"serial:{emulated.path}", "--allow-unauthenticated-radio", until=moving)
    assert run.returncode == 0, run.stderr
    assert "all followers commanded to zero" in run.stdout
    states = [t["link_state"] for t in read_recording(record).ticks]
    assert states and all(st.endswith(ALLOWED_NOTE) for st in states), states[:3]
    # the service wrote STOP before it ended; the emulator (a thread here) takes it when it gets the CPU
    wait_for(lambda: all(r.flags & p.FLAG_STOPPED and r.target_l_mps == 0 == r.target_r_mps
                         for r in emulated.emulator.snapshot().values()), 30, "every robot to take the STOP")
    wait_for(lambda: not any(r.moving for r in emulated.emulator.snapshot().values()), 2, "the wheels to stop")
    assert all(abs(r.measured(hw)[0]) < 1e-3 for r in emulated.emulator.snapshot().values())


def test_bad_link_arguments_exit_2(tmp_path):
    from tests.helpers import main_cli

    out = main_cli("run", "--port", "0", "--link", "tcp:9", "--no-record")
    assert out.returncode == 2 and "--link 'tcp:9': must be 'sim', 'none' or 'serial:PATH'" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = main_cli("run", "--port", "0", "--camera", "frames", "--link", "serial:/dev/ttyUSB0,/dev/ttyUSB1",
                   "--leader", "serial:/dev/ttyUSB1", "--no-record")
    assert out.returncode == 2 and "the followers' link (--link) has that port" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = main_cli("run", "--port", "0", "--camera", "frames", "--link", "serial:/dev/ttyUSB0",
                   "--leader", "serial:/dev/../dev/ttyUSB0", "--no-record")  # the same device by another name
    assert out.returncode == 2 and "the followers' link (--link) has that port" in out.stderr
    out = main_cli("run", "--port", "0", "--camera", str(tmp_path), "--followers", "2", "--link",
                   "serial:/dev/ttyUSB0, /dev/ttyUSB0", "--no-record")
    assert out.returncode == 2 and "/dev/ttyUSB0 is named twice" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = main_cli("emulate-follower", "--port", "/nonexistent/tty")
    assert out.returncode == 2 and "cannot open serial port /nonexistent/tty" in out.stderr
    out = main_cli("emulate-follower", "--protocol", "2", "--radio-key", "/nonexistent/robots.json")
    assert out.returncode == 2 and "--protocol 2 robots know no key" in out.stderr
    out = main_cli("radio", "--older-robots", "0,2")
    assert out.returncode == 2 and "robot addresses 1..250" in out.stderr
    out = main_cli("radio-provision", "/nonexistent/robots.json")
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    out = main_cli("emulate-follower", "--drop", "1.5")
    assert out.returncode == 2 and "--drop" in out.stderr


def test_one_port_per_follower():
    from app.backends.serial_link import PortPerFollowerLink, make_link

    robots = [EmulatorThread(addresses=[i + 1]) for i in range(2)]  # follower i alone on its own pty
    link = make_link(f"{robots[0].path},{robots[1].path}", 2)
    assert isinstance(link, PortPerFollowerLink)
    try:
        wait_for(lambda: link.connects == 1, 5, "both ports to open")
        for _ in range(20):
            link.send(Commands(np.array([0.1, -0.05]), np.array([0.0, 0.3])))
            time.sleep(1 / 30)
        hw = robots[0].emulator.hw
        assert robots[0].emulator.snapshot()[1].measured(hw)[0] == pytest.approx(0.1, abs=0.01)
        assert robots[1].emulator.snapshot()[2].measured(hw)[1] == pytest.approx(0.3, abs=0.03)
        # the replies come back on each port's own reader thread
        wait_for(lambda: link.link_state == "serial 2 ports: ok" and link.detail().count("rtt") == 2, 10, "both ports ok")
        v, w = link.measured()
        assert v == pytest.approx([0.1, -0.05], abs=0.01) and w[1] == pytest.approx(0.3, abs=0.03)
        robots[1].close()
        wait_for(lambda: link.link_state.startswith("F2 link lost"), 3, "F2's port to be reported lost")
    finally:
        link.close()
        robots[0].close()
    with pytest.raises(ValueError, match="3 ports for 2 followers"):
        make_link("a,b,c", 2)
    with pytest.raises(ValueError, match="/dev/../dev/ttyUSB0 is named twice"):  # one device under two names
        make_link("/dev/ttyUSB0,/dev/../dev/ttyUSB0", 2)


def test_the_host_numbers_frames_per_line_and_tick_and_broadcasts_only_stop():
    """docs/follower-protocol.md: one sequence counter per line; all of one tick's frames
    share it; it goes up by one per tick; the only broadcast the host sends is STOP."""
    end = PtyEndpoint()
    link = SerialLink(end.path, 3)
    parser = p.FrameParser()
    frames: list[p.Frame] = []
    try:
        wait_for(lambda: link.connects == 1, 5, "the port to open")
        for _ in range(4):
            link.send(Commands(np.full(3, 0.05), np.zeros(3)))
            time.sleep(1 / 30)
        def four_ticks() -> bool:
            frames.extend(parser.feed(end.read(0.05)))
            return len([f for f in plain(frames) if f.msg_type == p.MSG_SET_VELOCITY]) >= 12

        wait_for(four_ticks, 5, "4 ticks of frames")
    finally:
        link.close()
    frames += parser.feed(end.read(0.3))
    end.close()
    frames = plain(frames)  # every frame authenticated (the open key): what a robot reads inside
    velocity = [f for f in frames if f.msg_type == p.MSG_SET_VELOCITY]
    ticks: dict[int, list[int]] = {}
    for f in velocity:
        ticks.setdefault(f.seq, []).append(f.address)
    assert all(sorted(a) == [1, 2, 3] for a in ticks.values())  # one sequence for the whole tick
    seqs = sorted(ticks)
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # one more per tick
    broadcast = {f.msg_type for f in frames if f.address == p.BROADCAST}
    assert broadcast == {p.MSG_STOP}  # on close: STOP to each robot, then once more to all
