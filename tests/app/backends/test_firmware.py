"""The reference follower firmware (firmware/, portable C), built here with `cc` and run
behind a real pseudo-terminal: it answers as docs/follower-protocol.md says (each point a
firmware author had to guess is answered there and checked here), the service holds the
formation with it, and it stops on STOP, when the service is interrupted and, by its own
watchdog, when the service dies."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from app.backends.serial_link import SerialLink
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import Params, ParamsStore, default_slots
from core.link import protocol as p

from tests.helpers import ROOT, serve_then_signal, wait_for

FIRMWARE = ROOT / "firmware"


@pytest.fixture(scope="module")
def firmware_bin(tmp_path_factory) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "a C compiler (cc) is needed to build the reference firmware"
    out = tmp_path_factory.mktemp("fw") / "follower_sim"
    build = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2",
                            str(FIRMWARE / "omni_follower.c"), str(FIRMWARE / "host_sim.c"), "-o", str(out), "-lm"],
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    return out


class Firmware:
    """The built firmware serving robots 1..3 on a pty; its event lines are collected."""

    def __init__(self, binary: Path, link: Path, *extra: str) -> None:
        self.link = link
        self.proc = subprocess.Popen([str(binary), "--link-path", str(link), *extra], stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline()
        assert first.startswith("firmware followers 1,2,3 on"), first
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.strip())

    def events(self, robot: int) -> list[str]:
        return [ln.split(": ", 1)[1] for ln in list(self.lines) if f" robot {robot}: " in f" {ln}"
                and "ms robot" in ln]

    def still(self, robot: int) -> bool:
        """Its wheels stopped since they last moved."""
        motion = [e for e in self.events(robot) if e in ("moving", "still")]
        return motion[-1:] == ["still"]

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(10)
        self._reader.join(5)


@pytest.fixture
def firmware(firmware_bin, tmp_path):
    fw = Firmware(firmware_bin, tmp_path / "followers")
    yield fw
    fw.close()
    assert not fw.link.exists()  # its link is gone with it


def _ask(port: serial.Serial, frame: p.Frame, wait_s: float = 0.3) -> list[p.Frame]:
    port.reset_input_buffer()
    port.write(p.encode_frame(frame))
    parser = p.FrameParser()
    deadline = time.monotonic() + wait_s
    out: list[p.Frame] = []
    while time.monotonic() < deadline:
        out += parser.feed(port.read(64))
    return out


@pytest.fixture
def firmware_p2(firmware_bin, tmp_path):
    """The firmware as an older robot (protocol 2: no key), which answers protocol 1 as before."""
    fw = Firmware(firmware_bin, tmp_path / "followers", "--protocol", "2")
    yield fw
    fw.close()


def test_the_firmware_answers_as_the_protocol_document_says(firmware_p2):
    firmware = firmware_p2
    port = serial.Serial(str(firmware.link), 115200, timeout=0.02)
    try:
        # PING before anything was commanded: STATUS with WATCHDOG, command age "never" (doc example)
        (st,) = _ask(port, p.ping(2, 9))
        assert (st.address, st.seq, st.msg_type) == (2, 9, p.MSG_STATUS)
        status = p.decode_status(st)
        assert status.battery_mv == 7400 and status.flags == p.FLAG_WATCHDOG and status.command_age_ms == 0xFFFF
        # the document's SET_VELOCITY example, byte for byte: answered by an ACK with the same sequence
        (ack,) = _ask(port, p.Frame(1, 7, p.MSG_SET_VELOCITY, bytes.fromhex("6400 06ff")))
        assert (ack.address, ack.seq, ack.msg_type) == (1, 7, p.MSG_ACK)
        # broadcast: obeyed, never answered
        assert _ask(port, p.ping(p.BROADCAST, 10), 0.15) == []
        # STOP neither feeds nor resets the watchdog's clock: the command age runs on
        _ask(port, p.set_velocity(3, 11, 0.1, 0.0), 0.2)
        _ask(port, p.stop(3, 12), 0.1)
        (st3,) = _ask(port, p.ping(3, 13))
        s3 = p.decode_status(st3)
        assert s3.flags & p.FLAG_STOPPED and s3.command_age_ms >= 250
        # a frame cut off is forgotten after 20 ms of silence; the next one is answered
        port.write(p.encode_frame(p.ping(2, 14))[:5])
        time.sleep(0.06)
        assert [f.seq for f in _ask(port, p.ping(2, 15))] == [15]
        # a header with a length over 32 is refused at once (before any CRC), the next frame is answered
        assert [f.seq for f in _ask(port, p.Frame(2, 16, p.MSG_PING, b""), 0.2)] == [16]
        port.write(bytes([0xA5, 0x5A, 2, 17, 3, 200]))
        assert [f.seq for f in _ask(port, p.ping(2, 18))] == [18]
        # wheels are scaled together at their limit: the path keeps its curvature (w / v = 5)
        for k in range(30):
            _ask(port, p.set_velocity(1, 20 + k, 0.4, 2.0), 0.03)
        a = p.decode_ack(_ask(port, p.set_velocity(1, 60, 0.4, 2.0))[0])
        assert a.w_rps / a.v_mps == pytest.approx(5.0, rel=0.03) and a.v_mps < 0.36
        # the watchdog: 0.5 s without SET_VELOCITY and the robot stops by itself
        wait_for(lambda: "watchdog" in firmware.events(1), 3.0, "robot 1's watchdog")
    finally:
        port.close()


def test_the_service_holds_the_formation_with_the_firmware_and_stop_stops_it(firmware):
    store = ParamsStore(Params(n_followers=3, slots=default_slots(3), leader_mode="straight"), fixed_followers=3)
    link = SerialLink(str(firmware.link), 3)
    # each robot starts 25-30 cm from its slot (the formation's convergence from anywhere
    # is the simulator's tests'; this one is the firmware's: it drives them there and holds them)
    start = default_slots(3) + np.array([[0.25, -0.1], [-0.2, 0.15], [0.1, 0.28]])
    loop = ServiceLoop(store, Backends(seed=4, link=link, initial_poses=(start, np.full(3, np.pi / 2))), rate_hz=30.0)
    seen: list = []
    loop.subscribe(lambda s: seen.append(s))
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: seen and seen[-1].t > 10.0, 90.0, "10 s of the team on the firmware")
        err0 = np.linalg.norm(seen[0].p_d - seen[0].p_true, axis=1)
        assert err0.min() > 0.2, err0  # it had somewhere to drive them
        last = [s for s in list(seen) if s.t > 7.0]  # RMS 25.5 cm in the first second, 1.8 cm by 6-7 s
        err = np.array([np.linalg.norm(s.p_d - s.p_true, axis=1) for s in last])
        assert np.sqrt(np.mean(err**2)) < 0.02, np.sqrt(np.mean(err**2, axis=0))  # in formation, moving
        assert last[-1].link_state.endswith(": ok"), last[-1].link_state
        assert all("moving" in firmware.events(r) for r in (1, 2, 3))
        store.update("browser:1", stop=True)
        wait_for(lambda: all(firmware.still(r) for r in (1, 2, 3)), 10.0, "every robot still")
    finally:
        loop.stop()
        thread.join(10)
    # the loop's end sends STOP to every robot
    wait_for(lambda: all("STOP" in firmware.events(r) for r in (1, 2, 3)), 5.0, "STOP for every robot")


def test_interrupting_the_service_stops_the_robots_and_killing_it_leaves_them_to_their_watchdog(firmware):
    moving = lambda: all("moving" in firmware.events(r) for r in (1, 2, 3))
    run = serve_then_signal("--port", "0", "--feedback", "truth", "--no-record", "--link", f"serial:{firmware.link}",
                            until=moving, sig=signal.SIGINT)
    assert run.returncode == 0, run.stderr
    wait_for(lambda: all("STOP" in firmware.events(r) for r in (1, 2, 3)), 5.0, "STOP for every robot")
    wait_for(lambda: all(firmware.still(r) for r in (1, 2, 3)), 5.0, "every robot still")
    before = {r: len(firmware.events(r)) for r in (1, 2, 3)}
    # now a service that dies without a word: only the robots' own watchdog can stop them
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--feedback", "truth",
                             "--no-record", "--link", f"serial:{firmware.link}"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: all("moving" in firmware.events(r)[before[r]:] for r in (1, 2, 3)), 90.0,
                 "the robots moving again")
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    for r in (1, 2, 3):
        wait_for(lambda r=r: "watchdog" in firmware.events(r)[before[r]:], 5.0, f"robot {r}'s watchdog")
        wait_for(lambda r=r: firmware.still(r), 5.0, f"robot {r} still")
        after = firmware.events(r)[before[r]:]
        since = after[len(after) - 1 - after[::-1].index("moving"):]  # from the last time it started moving
        assert "watchdog" in since and "STOP" not in since, after  # no STOP came: its own watchdog stopped it


def test_a_low_battery_is_flagged_by_the_robot_and_shown_by_the_host(firmware_bin, tmp_path):
    fw = Firmware(firmware_bin, tmp_path / "low", "--battery-mv", "6500")  # under the 6800 mV threshold
    link = SerialLink(str(fw.link), 3)
    try:
        from core.types import Commands

        def shown() -> bool:
            link.send(Commands(np.zeros(3), np.zeros(3)))
            time.sleep(1 / 30)
            return link.detail().count("LOW BATTERY") == 3

        wait_for(shown, 10.0, "LOW BATTERY for every robot on the host's status")
        assert "6.50 V" in link.detail()  # from STATUS, answering the host's PING
    finally:
        link.close()
        fw.close()


def ownership_script() -> list[tuple[int, p.Frame]]:
    """Protocol 2 (docs/follower-protocol.md, "Ownership"), robot 4, step by step; the comments
    say what the document asks for."""
    a = 4
    return [
        (0, p.ping(a, 1)),                                   # STATUS
        (10, p.set_velocity(a, 2, 0.10, 0.0)),               # nobody holds it: protocol 1 obeyed
        (20, p.claim(a, 3, 1, 500)),                         # granted to leader 1; from rest
        (30, p.set_velocity(a, 4, 0.10, 0.0)),               # owned: protocol 1 refused, owner named
        (40, p.drive(a, 5, 2, 10, 0.20, 0.0)),               # not the owner's: refused
        (50, p.drive(a, 6, 1, 50, 0.10, 0.5)),               # the owner's: obeyed, lease renewed
        (60, p.claim(a, 7, 2, 500)),                         # its lease lives: refused, owner and lease named
        (70, p.drive(a, 8, 1, 400, 0.10, 0.0)),              # from a stale observation: refused, standing still
        (80, p.drive(a, 9, 1, 10, 0.20, 0.0)),               # obeyed again
        (85, p.drive(p.BROADCAST, 10, 1, 10, 0.3, 0.0)),     # never by broadcast: ignored, unanswered
        (90, p.handover(a, 11, 2, 3, 500)),                  # not from the owner: refused
        (100, p.handover(a, 12, 1, 2, 300)),                 # the owner hands it to 2: granted, from rest
        (120, p.drive(a, 13, 2, 10, 0.10, 0.0)),             # 40 ms after 1's last: counted as two owners
        (130, p.stop(a, 14)),                                # STOP from anyone: obeyed
        (300, p.drive(a, 15, 2, 10, 0.10, 0.0)),             # the owner again: moving, lease renewed
        (1000, p.drive(a, 16, 2, 10, 0.10, 0.0)),            # its lease ran out (2 went quiet): refused
        (1010, p.claim(a, 17, 0, 500)),                      # leader 0 is nobody: refused
        (1020, p.claim(a, 18, 3, 5)),                        # a lapsed lease: granted to 3, held to 100 ms
        (1050, p.claim(a, 19, 2, 500)),                      # 3's lease lives: refused
        (1060, p.drive(a, 20, 3, 0, 0.1, -0.2)),             # the new owner drives
        (1500, p.claim(a, 21, 3, 20_000)),                   # the owner renews: held to 10 s
        (1510, p.set_velocity(a, 22, 0.1, 0.0)),             # owned: refused
        (12_000, p.set_velocity(a, 23, 0.1, 0.0)),           # every lease lapsed: protocol 1 again
    ]


@pytest.fixture(scope="module")
def conformance_bin(tmp_path_factory) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc
    binary = tmp_path_factory.mktemp("conf") / "conformance"
    build = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2",
                            str(FIRMWARE / "omni_follower.c"), str(FIRMWARE / "conformance.c"), "-o", str(binary)],
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    return binary


def run_both(binary: Path, script: list[tuple[int, p.Frame]], address: int, auth=None, c_args: tuple[str, ...] = ()):
    """The script through the firmware (``binary``) and the Python follower: every step's replies,
    owner, lease, wheel targets, flags and counts alike. Returns the Python follower's last state
    and the replies (Python's) per step."""
    from core.link.follower import FollowerHardware, FollowerState, handle_frame, step_follower

    text = "".join(f"{t} {p.encode_frame(f).hex(' ')}\n" for t, f in script)
    run = subprocess.run([str(binary), str(address), *c_args], input=text, capture_output=True, text=True, timeout=30)
    assert run.returncode == 0, run.stderr
    c_steps: list[tuple[list[p.Frame], list[int]]] = []
    replies: list[p.Frame] = []
    for line in run.stdout.splitlines():
        if line.startswith(">"):
            replies += p.FrameParser().feed(bytes.fromhex(line[1:]))
        else:
            c_steps.append((replies, [int(x) for x in line[1:].split()]))
            replies = []
    assert len(c_steps) == len(script)

    hw = FollowerHardware(motor_tau_s=0.0)
    s = FollowerState(address=address)
    now = 0
    answers: list[list[p.Frame]] = []
    keys = auth.keys if auth is not None else ()
    for (t, frame), (c_replies, c_state) in zip(script, c_steps, strict=True):
        s = step_follower(s, hw, (t - now) / 1000)
        now = t
        s, reply = handle_frame(s, hw, frame, auth)
        py_replies = [reply] if reply is not None else []
        answers.append(py_replies)
        what = f"at {t} ms, {p.MESSAGE_NAMES.get(frame.msg_type, hex(frame.msg_type))}"
        assert [r.msg_type for r in py_replies] == [r.msg_type for r in c_replies], what
        for mine, theirs in zip(py_replies, c_replies):
            if p.is_sealed(mine):  # both verify under the key the request used, bound to the request
                a, b = (p.open_sealed(x, keys, p.tag_of(frame)) for x in (mine, theirs))
                assert a is not None and b is not None, (what, mine, theirs)
                assert (a.ident, a.counter, a.key_index) == (b.ident, b.counter, b.key_index), what
                mine, theirs = a.frame, b.frame
            if mine.msg_type in (p.MSG_OWNER, p.MSG_NACK):
                a, b = p.decode_ownership(mine), p.decode_ownership(theirs)
                assert (a.owner, a.reason, a.asker) == (b.owner, b.reason, b.asker), (what, a, b)
                assert abs(a.lease_left_ms - b.lease_left_ms) <= 1, (what, a, b)
            elif mine.msg_type == p.MSG_DRIVEN:
                (ack_a, asker_a), (ack_b, asker_b) = p.decode_driven(mine), p.decode_driven(theirs)
                assert (ack_a.flags, asker_a) == (ack_b.flags, asker_b), what
            elif mine.msg_type == p.MSG_ACK:
                assert p.decode_ack(mine).flags == p.decode_ack(theirs).flags, what
            elif mine.msg_type == p.MSG_STATUS and len(mine.payload) > 9:
                assert p.decode_status_counts(mine)[1] == p.decode_status_counts(theirs)[1], what
        owner, lease_left, left_mm, right_mm, flags, nacks, two, *refused = c_state
        lease_py = int(round(s.lease_left_s * 1000)) if s.lease_lives else 0
        assert (s.owner, s.flags, s.nacks, s.two_owners) == (owner, flags, nacks, two), (what, s, c_state)
        assert tuple(vars(s.refusals).values()) == tuple(refused), (what, s.refusals, refused)
        assert abs(lease_py - lease_left) <= 1, (what, lease_py, lease_left)
        assert (round(s.target_l_mps * 1000), round(s.target_r_mps * 1000)) == (left_mm, right_mm), (what, s, c_state)
    return s, answers


def test_the_firmware_and_the_python_follower_keep_ownership_alike(conformance_bin):
    """The reference firmware (built with -Werror -pedantic, driven by a script) and the Python
    follower the emulator and the tests run answer every frame of the ownership script the
    same: the same replies, owners, reasons and leases, the same wheel targets after each."""
    s, _ = run_both(conformance_bin, ownership_script(), 4)
    # what the script was for: the robot ended with leader 3's lease lapsed, and counted one two-owner
    # overlap (the handover driven at once) and every refusal
    assert s.two_owners == 1 and s.nacks == 9 and s.owner == 3 and not s.lease_lives


K1 = bytes(range(32))  # the fleet's key
K2 = bytes(range(100, 132))  # the next key, during a rotation
WRONG = bytes(range(200, 232))  # another fleet's key


def authenticated_script() -> list[tuple[int, p.Frame]]:
    """Protocol 3 (docs/follower-protocol.md, "Authenticated frames"), robot 4 provisioned with
    K1 and, for a rotation, K2, obeying leaders 1 and 2: valid, forged, replayed, wrong-key and
    rotated-key frames; the comments say what the document asks for."""
    a = 4

    def sig(frame: p.Frame, sender: int, counter: int, key: bytes = K1) -> p.Frame:
        return p.seal(frame, key, sender, counter)

    drive = sig(p.drive(a, 3, 1, 10, 0.10, 0.0), 1, 12)
    tampered = p.Frame(drive.address, drive.seq, drive.msg_type, drive.payload[:3] + b"\x7f" + drive.payload[4:])
    return [
        (0, sig(p.ping(a, 1), 1, 10)),                             # STATUS+MAC, with the refusal counts (0)
        (10, sig(p.claim(a, 2, 1, 500), 1, 11)),                  # granted to leader 1
        (20, drive),                                              # obeyed, DRIVEN+MAC
        (30, drive),                                              # the same bytes again: a replay, refused
        (40, sig(p.drive(a, 4, 1, 10, -0.2, 0.0), 1, 12)),        # a new command with an old counter: refused
        (50, sig(p.drive(a, 5, 1, 10, -0.2, 0.0), 1, 13, WRONG)),  # another fleet's key: bad MAC
        (60, tampered),                                           # one byte changed in the air: bad MAC
        (70, p.drive(a, 6, 1, 10, -0.2, 0.0)),                    # plain protocol 2 DRIVE: unauthenticated
        (80, sig(p.handover(a, 7, 1, 9, 10_000), 1, 14, WRONG)),  # a forged HANDOVER "from 1": bad MAC
        (90, sig(p.drive(a, 8, 9, 10, -0.2, 0.0), 9, 15)),        # the key, but leader 9 is not the fleet's
        (100, sig(p.drive(a, 9, 1, 10, -0.2, 0.0), 2, 16)),       # sender 2 naming leader 1: refused
        (110, sig(p.claim(a, 10, 2, 500), 2, 100)),               # leader 2, its own counter: NACK OWNED
        (120, sig(p.claim(a, 11, 2, 500), 2, 50)),                # leader 2 going back: a replay
        (130, sig(p.drive(a, 12, 1, 10, 0.15, 0.0), 1, 17, K2)),  # the next key (rotation): obeyed, reply in K2
        (140, p.stop(a, 13)),                                     # plain STOP: the policy (fail-safe: obeyed)
        (150, sig(p.drive(a, 14, 1, 10, 0.15, 0.0), 1, 18)),      # moving again
        (160, sig(p.stop(a, 15), 1, 19, WRONG)),                  # a wrong-key STOP: counted, and the policy
        (170, sig(p.drive(a, 16, 1, 10, 0.15, 0.0), 1, 20)),      # moving again
        (180, sig(p.stop(p.BROADCAST, 17), 1, 21)),               # an authenticated broadcast STOP: unanswered
        (190, sig(p.drive(a, 18, 1, 10, 0.15, 0.0), 1, 22)),      # moving again
        (200, sig(p.stop(a, 19), 1, 23)),                         # an authenticated STOP: obeyed, ACK+MAC
        (210, sig(p.handover(a, 20, 1, 2, 500), 1, 24)),          # the owner hands over: OWNER+MAC to 1
        (220, sig(p.ping(a, 21), 2, 101)),                        # STATUS+MAC: the counts so far
    ]


@pytest.mark.parametrize("stop", ["anyone", "authenticated"])
def test_the_firmware_and_the_python_follower_refuse_the_same_frames(conformance_bin, stop):
    """One script of valid, forged, replayed, wrong-key and rotated-key frames: the firmware and
    the Python follower send the same replies (authenticated, bound to the request they answer),
    reach the same owners and wheel targets, and count the same refusals, under either STOP policy."""
    from core.link.follower import RadioAuth

    auth = RadioAuth((K1, K2), (1, 2), stop)
    c_args = ("--key", K1.hex(), "--key", K2.hex(), "--leaders", "1,2") + (
        ("--stop-authenticated",) if stop == "authenticated" else ())
    s, answers = run_both(conformance_bin, authenticated_script(), 4, auth, c_args)
    script = authenticated_script()
    moved = [i for i, (_, f) in enumerate(script) if answers[i] and answers[i][0].msg_type == p.MSG_DRIVEN | p.AUTH]
    assert [script[i][0] for i in moved] == [20, 130, 150, 170, 190]  # only the fleet's fresh DRIVEs
    assert p.open_sealed(answers[13][0], (K2,), p.tag_of(script[13][1])) is not None  # answered in the next key
    assert s.owner == 2  # handed over by its owner, never by the forged HANDOVER
    plain_stop, wrong_stop = 14, 16
    if stop == "anyone":  # fail-safe: every STOP heard stops the robot
        assert s.refusals == p.RadioCounts(bad_mac=4, unknown_sender=2, replayed=3, unauthenticated=1)
    else:  # only an authenticated one: the plain and the wrong-key STOP change nothing
        assert s.refusals == p.RadioCounts(bad_mac=4, unknown_sender=2, replayed=3, unauthenticated=2)
    assert all(not answers[i] for i in (plain_stop, wrong_stop))  # never answered either way
    status, counts = p.decode_status_counts(p.open_sealed(answers[-1][0], (K1,), p.tag_of(script[-1][1])).frame)
    assert counts == s.refusals  # the robot reports its refusals in its STATUS


def test_the_firmware_siphash_gives_the_published_test_vectors(conformance_bin):
    from core.link.siphash import siphash24
    from tests.core.link.siphash_vectors import KEY, VECTORS

    lines = "".join(f"{KEY.hex()} {bytes(range(n)).hex()}\n" for n in range(len(VECTORS)))
    run = subprocess.run([str(conformance_bin), "--siphash"], input=lines, capture_output=True, text=True, timeout=30)
    assert run.returncode == 0, run.stderr
    assert [int(x, 16) for x in run.stdout.split()] == VECTORS
    assert [siphash24(KEY, bytes(range(n))) for n in range(len(VECTORS))] == VECTORS
