"""A key per leader (docs/follower-protocol.md, "Keys and provisioning"): a leader whose machine is
taken can sign only as its own radio id. The reference firmware and the Python follower agree on
every frame of one script (L2's key signing as L1 refused and counted as bad MAC), and on real
files: fleet-keys, radio-provision, the firmware flashed with the record and the emulated robots
read from robots.json obey L1's key as L1 and refuse L2's key as L1."""

from __future__ import annotations

import subprocess
import threading
import time

import numpy as np
import pytest

from app.backends.radio import Radio
from app.backends.radio_keys import leader_key, load_leader_key, load_robot_auth
from app.backends.serial_link import SerialLink
from core.link import protocol as p
from core.link.follower import FollowerHardware, FollowerState, RadioAuth, handle_frame, step_follower
from core.types import Commands
from tests.app.backends.test_firmware import Firmware, conformance_bin, firmware_bin  # noqa: F401 - fixtures
from tests.helpers import main_cli, wait_for

SECRET = bytes(range(32))  # the fleet's radio secret (robots.json's): never on a robot
NEXT = bytes(range(100, 132))  # the next one, during a rotation
K1, K2 = leader_key(SECRET, 1), leader_key(SECRET, 2)
K1N, K2N = leader_key(NEXT, 1), leader_key(NEXT, 2)


def leader_script() -> list[tuple[int, p.Frame, str]]:
    """Robot 4, provisioned with L1's and L2's keys (current and next): each frame and what the
    document asks the robot to do with it."""
    a = 4

    def sig(frame: p.Frame, sender: int, counter: int, key: bytes) -> p.Frame:
        return p.seal(frame, key, sender, counter)

    return [
        (0, sig(p.ping(a, 1), 1, 10, K1), "STATUS"),                          # L1 as L1
        (10, sig(p.claim(a, 2, 1, 500), 1, 11, K1), "OWNER"),                # granted to L1
        (20, sig(p.drive(a, 3, 1, 10, 0.10, 0.0), 1, 12, K1), "DRIVEN"),     # obeyed
        (30, sig(p.drive(a, 4, 1, 10, -0.2, 0.0), 1, 13, K2), "bad_mac"),    # L2's key signing as L1
        (40, sig(p.handover(a, 5, 1, 2, 10_000), 1, 14, K2), "bad_mac"),     # L2's key handing L1's robot to L2
        (50, sig(p.claim(a, 6, 1, 500), 1, 15, K2), "bad_mac"),              # L2's key claiming as L1
        (60, sig(p.stop(a, 7), 1, 16, K2), "bad_mac"),                        # L2's key: STOP as L1 (policy)
        (70, sig(p.drive(a, 8, 1, 10, 0.10, 0.0), 1, 17, K1), "DRIVEN"),     # L1 again: moving
        (80, sig(p.drive(a, 9, 1, 10, -0.2, 0.0), 1, 18, SECRET), "bad_mac"),  # the fleet's secret itself
        (90, sig(p.drive(a, 10, 1, 10, -0.2, 0.0), 1, 19, K1N), "DRIVEN"),   # L1's next key (rotation)
        (100, sig(p.claim(a, 11, 2, 500), 2, 50, K2), "NACK"),               # L2 as L2: refused as owned
        (110, sig(p.drive(a, 12, 9, 10, -0.2, 0.0), 9, 20, K1), "bad_mac"),  # an id with no key: none verifies
        (115, sig(p.drive(a, 13, 2, 10, -0.2, 0.0), 1, 21, K1), "unknown_sender"),  # L1 naming leader 2
        (120, sig(p.ping(a, 14), 2, 51, K2N), "STATUS"),                     # L2 as L2, next key: the counts
    ]


def _c_run(binary, script, stop: str) -> list[tuple[list[p.Frame], list[int]]]:
    args = ["4", "--leader-key", "1", K1.hex(), "--leader-key", "1", K1N.hex(), "--leader-key", "2", K2.hex(),
            "--leader-key", "2", K2N.hex()] + (["--stop-authenticated"] if stop == "authenticated" else [])
    text = "".join(f"{t} {p.encode_frame(f).hex(' ')}\n" for t, f, _ in script)
    run = subprocess.run([str(binary), *args], input=text, capture_output=True, text=True, timeout=30)
    assert run.returncode == 0, run.stderr
    steps, replies = [], []
    for line in run.stdout.splitlines():
        if line.startswith(">"):
            replies += p.FrameParser().feed(bytes.fromhex(line[1:]))
        else:
            steps.append((replies, [int(x) for x in line[1:].split()]))
            replies = []
    return steps


@pytest.mark.parametrize("stop", ["anyone", "authenticated"])
def test_the_firmware_and_the_python_follower_let_a_leaders_key_sign_only_as_its_own_id(
        conformance_bin, stop):  # noqa: F811 - the fixture imported above
    auth = RadioAuth((), (1, 2), stop, ((K1, K1N), (K2, K2N)))
    script = leader_script()
    c_steps = _c_run(conformance_bin, script, stop)
    assert len(c_steps) == len(script)
    hw, s, now = FollowerHardware(motor_tau_s=0.0), FollowerState(address=4), 0
    obeyed_as_l1_by_l2 = 0
    for (t, frame, want), (c_replies, c_state) in zip(script, c_steps, strict=True):
        s = step_follower(s, hw, (t - now) / 1000)
        now = t
        before = s.refusals
        s, reply = handle_frame(s, hw, frame, auth)
        mine = [reply] if reply is not None else []
        what = f"at {t} ms ({want})"
        assert [r.msg_type for r in mine] == [r.msg_type for r in c_replies], what
        ident = p.trailer(frame)[0]
        for a, b in zip(mine, c_replies):  # both sealed with the key of the id that asked, bound to the request
            oa, ob = (p.open_sealed(x, auth.keys_of(ident), p.tag_of(frame)) for x in (a, b))
            assert oa is not None and ob is not None and (oa.ident, oa.counter, oa.key_index) == (
                ob.ident, ob.counter, ob.key_index), what
            assert p.MESSAGE_NAMES[oa.frame.msg_type] == want, what
        if want in ("bad_mac", "unknown_sender"):
            assert not mine and getattr(s.refusals, want) == getattr(before, want) + 1, what
        owner, _, left_mm, right_mm, flags, nacks, two, *refused = c_state
        assert (s.owner, s.flags, s.nacks, s.two_owners) == (owner, flags, nacks, two), (what, s, c_state)
        assert tuple(vars(s.refusals).values()) == tuple(refused), (what, s.refusals, refused)
        assert (round(s.target_l_mps * 1000), round(s.target_r_mps * 1000)) == (left_mm, right_mm), what
        obeyed_as_l1_by_l2 += bool(mine) and p.open_sealed(frame, (K2,)) is not None and ident == 1
    assert obeyed_as_l1_by_l2 == 0
    assert s.refusals == p.RadioCounts(bad_mac=6, unknown_sender=1, replayed=0, unauthenticated=0)
    assert s.owner == 1  # L2's key never took L1's robot


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet") / "keys"
    assert main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", "L1,L2").returncode == 0
    return d


def _drive(link: SerialLink, seconds: float) -> None:
    for _ in range(int(seconds * 30)):
        link.send(Commands(np.full(link.n, 0.1), np.zeros(link.n), observed_at=time.monotonic()))
        time.sleep(1 / 30)


def test_fleet_keys_give_each_leader_its_own_key_and_the_robots_refuse_l2s_as_l1(fleet):
    """robots.json read by the emulated robots (as `radio --radio-key` reads it): L2's key file
    with sender id 1 drives nothing (every frame a bad MAC), L1's drives."""
    l1, l2 = load_leader_key(fleet / "radio" / "L1.radio"), load_leader_key(fleet / "radio" / "L2.radio")
    assert l1.key != l2.key and (l1.radio_id, l2.radio_id) == (1, 2)
    radio = Radio(1, 2, auth=load_robot_auth(fleet / "radio" / "robots.json"))
    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    carrier.start()
    try:
        forger = SerialLink(radio.paths[0], 2, radio_key=l2.key, sender_id=1)  # L2's machine taken, posing as L1
        try:
            _drive(forger, 1.5)
            wait_for(lambda: sum(s.refusals.bad_mac for s in radio.robots.snapshot().values()) > 40, 10,
                     "the robots counting L2's frames as bad MACs")
            assert sum(s.answered for s in forger.stats) == 0 and not forger.answering().any()
            assert not any(s.moving for s in radio.robots.snapshot().values())
        finally:
            forger.close()
        own = SerialLink(radio.paths[0], 2, radio_key=l1.key, sender_id=1)
        try:
            wait_for(lambda: (_drive(own, 0.2), own.answering().all())[1], 10, "L1 answered as L1")
        finally:
            own.close()
    finally:
        stop.set()
        carrier.join(5)
        radio.close()


def test_the_firmware_flashed_from_fleet_keys_refuses_l2s_key_as_l1(fleet, firmware_bin, tmp_path):  # noqa: F811
    record = tmp_path / "radio_auth.bin"
    r = main_cli("radio-provision", str(fleet / "radio" / "robots.json"), "--record", str(record))
    assert r.returncode == 0 and "a key per leader" in r.stdout, r.stderr
    assert record.read_bytes()[:4] == b"OFR4" and _holds_leader_keys_only(record.read_bytes(), fleet)
    l2 = load_leader_key(fleet / "radio" / "L2.radio")
    fw = Firmware(firmware_bin, tmp_path / "followers", "--radio-record", str(record))
    try:
        forger = SerialLink(str(fw.link), 3, radio_key=l2.key, sender_id=1)
        try:
            _drive(forger, 1.5)
            assert sum(s.answered for s in forger.stats) == 0 and not forger.answering().any()
            assert all("moving" not in fw.events(a) for a in (1, 2, 3))
        finally:
            forger.close()
        own = SerialLink(str(fw.link), 3, radio_key=l2.key, sender_id=2)  # L2 as itself: obeyed
        try:
            wait_for(lambda: (_drive(own, 0.2), own.answering().all())[1], 10, "L2 answered as L2")
        finally:
            own.close()
    finally:
        fw.close()


def _holds_leader_keys_only(record: bytes, fleet) -> bool:
    """The robots' record holds each leader's key, never the fleet's secret."""
    import json

    secret = bytes.fromhex(json.loads((fleet / "radio" / "robots.json").read_text())["keys"][0])
    return secret not in record and leader_key(secret, 1) in record and leader_key(secret, 2) in record
