"""One radio, two leaders (docs/follower-protocol.md, "Ownership"): the robots themselves hold
their owner, over real pseudo-terminals with a lossy, delayed medium and a cut link."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import serial

from app.backends.radio import Radio
from core.link import protocol as p

from tests.helpers import main_cli, wait_for

ROBOTS = (1, 2, 3)


class Leader:
    """A leader's end of the radio, written from the protocol document: frames out, every
    reply that reaches it kept (replies to the other leader included: it is one medium)."""

    def __init__(self, path: str, number: int) -> None:
        self.number = number
        self.port = serial.Serial(path, 115200, timeout=0.01)
        self.parser = p.FrameParser()
        self.lock = threading.Lock()
        self.replies: list[p.Frame] = []
        self.seq = 0
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            data = self.port.read(256)
            if data:
                with self.lock:
                    self.replies += self.parser.feed(data)

    def send(self, make) -> tuple[int, int]:
        """Write ``make(seq)``; (the sequence used, how many replies had come before it)."""
        with self.lock:
            self.seq = (self.seq + 1) % 256
            seq, before = self.seq, len(self.replies)
        self.port.write(p.encode_frame(make(seq)))
        return seq, before

    def answer(self, robot: int, sent: tuple[int, int]) -> p.Frame | None:
        """Its own answer to a frame sent: after it, the robot, the sequence and the asker (one
        medium: the other leader's replies come here too, and sequences of two leaders meet;
        its own wrap at 256)."""
        seq, before = sent
        with self.lock:
            return next((f for f in self.replies[before:] if f.address == robot and f.seq == seq
                         and p.answers(f) == self.number), None)

    def ask(self, robot: int, make, timeout: float = 10.0) -> p.Frame:
        """Send until the robot's answer comes (the medium loses frames)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            sent = self.send(make)
            t = time.monotonic()
            while time.monotonic() - t < 0.15:
                got = self.answer(robot, sent)
                if got is not None:
                    return got
                time.sleep(0.005)
        raise AssertionError(f"robot {robot} never answered leader {self.number}")

    def close(self) -> None:
        self._stop.set()
        self._reader.join(2)
        self.port.close()


def test_on_one_radio_a_robot_obeys_one_leader_and_passes_to_another_only_when_its_lease_lapses():
    radio = Radio(2, len(ROBOTS), drop=0.1, delay_s=0.01, seed=3)
    stop = threading.Event()
    medium = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    medium.start()
    a, b = Leader(radio.paths[0], 1), Leader(radio.paths[1], 2)
    driving = threading.Event()
    obs_age = {"ms": 20}

    def drive_all(leader: Leader) -> None:  # 30 Hz, as a leader's loop does, while ``driving``
        while driving.is_set():
            for r in ROBOTS:
                leader.send(lambda seq, r=r: p.drive(r, seq, leader.number, obs_age["ms"], 0.05, 0.0))
            time.sleep(1 / 30)

    try:
        # A claims its three robots (a 2 s lease, renewed by each DRIVE) and drives them
        for r in ROBOTS:
            got = a.ask(r, lambda seq, r=r: p.claim(r, seq, 1, 2000))
            assert got.msg_type == p.MSG_OWNER and p.decode_ownership(got).owner == 1
        driving.set()
        pump = threading.Thread(target=drive_all, args=(a,), daemon=True)
        pump.start()
        wait_for(lambda: all(s.moving for s in radio.robots.snapshot().values()), 10, "A's robots moving")
        # B can neither take nor drive them while A's lease lives: each refusal names the owner
        for r in ROBOTS:
            got = b.ask(r, lambda seq, r=r: p.claim(r, seq, 2, 2000))
            assert got.msg_type == p.MSG_NACK and p.decode_ownership(got).owner == 1
            assert p.decode_ownership(got).reason == p.NACK_OWNED
            got = b.ask(r, lambda seq, r=r: p.drive(r, seq, 2, 10, 0.3, 0.0))
            assert got.msg_type == p.MSG_NACK and p.decode_ownership(got).reason == p.NACK_NOT_OWNER
        # a short cut of A's link (less than its lease): its first command after, computed from an
        # observation taken before the cut, moves nothing; fresh ones drive again
        radio.cut(0, 0.5)
        obs_age["ms"] = 600
        time.sleep(0.6)
        got = a.ask(1, lambda seq: p.drive(1, seq, 1, 600, 0.05, 0.0))
        assert got.msg_type == p.MSG_NACK and p.decode_ownership(got).reason == p.NACK_STALE
        wait_for(lambda: radio.robots.snapshot()[1].target_l_mps == 0.0, 5, "robot 1 standing still")
        obs_age["ms"] = 20
        wait_for(lambda: radio.robots.snapshot()[1].target_l_mps > 0.0, 5, "robot 1 driven again")
        # A cut for longer than its lease: the robots stop by their watchdog, their lease lapses, and
        # B's claims are granted; A, back, is refused at once (it no longer owns them)
        radio.cut(0, 4.0)
        cut_at = time.monotonic()
        wait_for(lambda: not any(s.moving for s in radio.robots.snapshot().values()), 10, "the watchdog stops")
        refused = 0
        for r in ROBOTS:  # B keeps asking, as an adopter does: refused while A's lease lives, then granted
            while (got := b.ask(r, lambda seq, r=r: p.claim(r, seq, 2, 2000))).msg_type == p.MSG_NACK:
                assert p.decode_ownership(got).owner == 1
                refused += 1
                time.sleep(0.05)
                assert time.monotonic() - cut_at < 10, "never granted"
            if r == ROBOTS[0]:
                assert time.monotonic() - cut_at >= 2.0 - 0.1  # not before A's lease lapsed
        assert refused > 0
        driving.clear()
        pump.join(5)
        driving.set()
        pump = threading.Thread(target=drive_all, args=(b,), daemon=True)
        pump.start()
        wait_for(lambda: all(s.moving for s in radio.robots.snapshot().values()), 10, "B's robots moving")
        wait_for(lambda: time.monotonic() - cut_at > 4.1, 10, "A's link back")
        for r in ROBOTS:
            got = a.ask(r, lambda seq, r=r: p.drive(r, seq, 1, 20, 0.2, 0.0))
            assert got.msg_type == p.MSG_NACK and p.decode_ownership(got).owner == 2, got
        driving.clear()
        pump.join(5)
    finally:
        driving.clear()
        stop.set()
        medium.join(5)
        a.close()
        b.close()
        radio.close()
    s = radio.summary()
    assert s["two_owners"] == 0 and all(r["owner"] == 2 for r in s["robots"].values()), s
    assert s["dropped"] > 0 and s["cut"] > 0, s  # the medium did lose and cut


def test_the_radio_command_prints_a_link_per_leader_and_its_summary(tmp_path):
    summary = tmp_path / "radio.json"
    r = main_cli("radio", "--leaders", "3", "--followers", "2", "--minutes", "0.01", "--summary", str(summary))
    assert r.returncode == 0, r.stderr
    assert [ln.split(":")[0] for ln in r.stdout.splitlines()[1:]] == ["leader 1", "leader 2", "leader 3"]
    assert json.loads(summary.read_text())["robots"].keys() == {"R1", "R2"}
    bad = main_cli("radio", "--drop", "1.5")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
    for args, words in ((["--radio-id", "0"], "--radio-id"), (["--radio-id", "251"], "--radio-id"),
                        (["--radio-id", "3"], "--radio-id goes with --link serial:PATH"),
                        (["--radio-id", "3", "--link", "serial:/dev/a,/dev/b", "--followers", "2",
                          "--allow-unauthenticated-radio"], "a radio is one port"),
                        (["--radio-id", "3", "--link", "serial:/dev/a"], "a shared radio needs the fleet's radio key"),
                        (["--radio-key", "/nonexistent/L1.radio", "--link", "serial:/dev/a"], "cannot read"),
                        (["--radio-key", "/nonexistent/L1.radio"], "--radio-key goes with --link"),
                        (["--radio-counter", "/tmp/c", "--link", "serial:/dev/a"], "--radio-counter goes with")):
        r = main_cli("run", "--port", "0", "--no-record", *args)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)


def test_a_leader_that_reads_nothing_never_holds_up_the_radio():
    """A leader killed with its port still open here reads nothing: its pty fills. The medium
    goes on for everyone else (frames to the full port are missed and counted), as a radio
    receiver that is off misses them."""
    radio = Radio(2, 1)
    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    try:
        deaf = radio.endpoints[1]
        filled, refused = 0, 0
        while refused < 20:  # nobody reads leader 2's end: full (the kernel moves bytes on for a while)
            if deaf.offer(b"\0" * 256):
                filled, refused = filled + 1, 0
            else:
                refused += 1  # refused at once: nothing waits
                time.sleep(0.01)
            assert filled < 100_000
        carrier.start()
        a = Leader(radio.paths[0], 1)
        try:
            def status(sent: tuple[int, int]) -> bool:
                seq, before = sent
                with a.lock:
                    return any(f.address == 1 and f.seq == seq and f.msg_type == p.MSG_STATUS
                               for f in a.replies[before:])

            for _ in range(20):  # leader 1's frames go to leader 2 too (one medium): each missed there
                sent = a.send(lambda seq: p.ping(1, seq))
                wait_for(lambda sent=sent: status(sent), 10, "the robot's STATUS")
        finally:
            a._stop.set()
            a._reader.join(2)
            a.port.close()
        assert radio.stats.unread[1] > 0 and radio.stats.unread[0] == 0, radio.stats
    finally:
        stop.set()
        if carrier.ident is not None:
            carrier.join(5)
        radio.close()


def test_a_radio_link_takes_in_and_lets_go_of_robots_and_commands_each_by_its_address():
    """A leader in a fleet on a radio (app.backends.arena): its link starts with its own robot,
    claims one more when told (granted: nobody holds it), sends each command to the robot it is
    for, and after letting one go sends it nothing more (its lease lapses)."""
    from app.backends.serial_link import SerialLink
    from core.types import Commands

    from core.link.follower import RadioAuth

    radio = Radio(1, 2, auth=RadioAuth())  # protocol 3 robots holding the open key, as the link without one
    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    carrier.start()
    link = SerialLink(radio.paths[0], 0, addresses=[1], radio_id=1)
    granted: list[int] = []
    link.on_owned = granted.append
    try:
        def tick(v2: float) -> None:  # the loop's team: robot 2 only, robot 1 held still
            link.send(Commands(np.array([v2]), np.array([0.0]), observed_at=time.monotonic()), [2])
            time.sleep(1 / 30)

        link.want(2)
        deadline = time.monotonic() + 10
        while not (link.owns(1) and link.owns(2)) and time.monotonic() < deadline:
            tick(0.0)
        assert link.owns(1) and link.owns(2) and sorted(granted) == [1, 2]
        for _ in range(30):
            tick(0.1)
        robots = radio.robots.snapshot()
        assert robots[2].target_l_mps == robots[2].target_r_mps == pytest.approx(0.1, abs=1e-3)
        assert robots[1].target_l_mps == robots[1].target_r_mps == 0.0 and robots[1].lease_lives  # held, still
        link.let_go(1)
        assert link.addresses == [2] and link.answering_at([1, 2]).tolist() == [False, True]
        for _ in range(45):  # 1.5 s: robot 1's lease (1 s) lapses, robot 2's lives
            tick(0.1)
        robots = radio.robots.snapshot()
        assert not robots[1].lease_lives and robots[2].lease_lives and robots[2].owner == 1
        assert radio.summary()["two_owners"] == 0
    finally:
        link.close()
        stop.set()
        carrier.join(5)
        radio.close()
