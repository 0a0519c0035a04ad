"""The fleet's radio key on disk and in the robots (docs/follower-protocol.md, "Keys and
provisioning", "Rotating the key", "What the host does"): fleet-keys writes private files, the
firmware is provisioned from them (a C header that builds, a record the firmware reads), a leader
with the key drives the firmware and one with another key drives nothing, a rotation keeps the
fleet driving, and an older robot is named and not driven unless the operator allows it."""

from __future__ import annotations

import shutil
import stat
import subprocess
import time

import numpy as np
import pytest

from app.backends.radio import Radio
from app.backends.radio_keys import load_leader_key, load_robot_auth
from app.backends.serial_link import ALLOWED_NOTE, UNAUTHENTICATED, SerialLink
from core.link import protocol as p
from core.link.follower import RadioAuth
from core.types import Commands
from tests.app.backends.test_firmware import FIRMWARE, Firmware, firmware_bin  # noqa: F401 - the fixture
from tests.helpers import main_cli, wait_for


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet") / "keys"
    made = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", "L1,L2")
    assert made.returncode == 0, made.stderr
    assert "radio ids: L1 1, L2 2" in made.stdout
    return d / "radio"


def _drive(link: SerialLink, seconds: float, v: float = 0.1) -> None:
    for _ in range(int(seconds * 30)):
        link.send(Commands(np.full(link.n, v), np.zeros(link.n), observed_at=time.monotonic()))
        time.sleep(1 / 30)


def test_fleet_keys_writes_private_radio_keys_and_refuses_to_write_over_them(keys, tmp_path):
    assert stat.S_IMODE(keys.stat().st_mode) == 0o700
    for name in ("robots.json", "L1.radio", "L2.radio"):
        assert stat.S_IMODE((keys / name).stat().st_mode) == 0o600, name
    l1, l2 = load_leader_key(keys / "L1.radio"), load_leader_key(keys / "L2.radio")
    auth = load_robot_auth(keys / "robots.json")
    assert (l1.radio_id, l2.radio_id) == (1, 2) and len(l1.key) == len(l2.key) == 32
    # a key per leader: the robots hold each leader's own, never the fleet's secret (robots.json's)
    assert l1.key != l2.key and auth.leader_keys == ((l1.key,), (l2.key,)) and auth.keys == ()
    assert auth.leaders == (1, 2) and auth.stop == "anyone"
    for name in ("L1", "L2"):  # each leader's own file also in its bundle (the folder copied to its machine)
        bundled = keys.parent / name / f"{name}.radio"
        assert stat.S_IMODE(bundled.stat().st_mode) == 0o600 and load_leader_key(bundled) == load_leader_key(
            keys / f"{name}.radio")
    assert not (keys.parent / "arena" / "arena.radio").exists() and not (keys.parent / "L1" / "L2.radio").exists()
    again = main_cli("fleet-keys", str(keys.parent), "--fleet", "lab", "--leaders", "L1,L2")
    assert again.returncode == 2 and "exists" in again.stderr
    copy = tmp_path / "L1.radio"
    shutil.copy(keys / "L1.radio", copy)
    copy.chmod(0o644)  # readable by others: refused, one line naming it
    run = main_cli("run", "--port", "0", "--no-record", "--link", "serial:/dev/null", "--radio-key", str(copy))
    assert run.returncode == 2 and f"{copy}: a leader's radio key is readable" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def sim_bin(firmware_bin):  # noqa: F811 - the fixture imported above
    """The reference firmware's host build, made as the conformance tests make it (-Werror -pedantic)."""
    return firmware_bin


def test_the_firmware_provisioned_from_fleet_keys_obeys_the_fleet_and_refuses_another_key(keys, sim_bin, tmp_path):
    header, record = tmp_path / "radio_auth.h", tmp_path / "radio_auth.bin"
    r = main_cli("radio-provision", str(keys / "robots.json"), "--header", str(header), "--record", str(record))
    assert r.returncode == 0, r.stderr
    assert stat.S_IMODE(header.stat().st_mode) == 0o600 and stat.S_IMODE(record.stat().st_mode) == 0o600
    # the header builds with the firmware, pedantic, and holds the key
    probe = tmp_path / "probe.c"
    probe.write_text('#include "radio_auth.h"\n#include <stdio.h>\nint main(void) { printf("%u %u %u %u %u %u\\n",'
                     ' OF_RADIO_AUTH.n_keys, OF_RADIO_AUTH.n_leaders, OF_RADIO_AUTH.per_leader,'
                     ' OF_RADIO_AUTH.leader_keys[0][0][0], OF_RADIO_AUTH.leader_keys[1][0][0],'
                     ' OF_RADIO_AUTH.stop_policy); return 0; }\n')
    cc = shutil.which("cc") or shutil.which("gcc")
    build = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", f"-I{FIRMWARE}",
                            f"-I{tmp_path}", str(probe), "-o", str(tmp_path / "probe")],
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    key, key2 = load_leader_key(keys / "L1.radio").key, load_leader_key(keys / "L2.radio").key
    out = subprocess.run([str(tmp_path / "probe")], capture_output=True, text=True).stdout.split()
    assert out == ["1", "2", "1", str(key[0]), str(key2[0]), "0"]
    # the firmware flashed with the record: the fleet's leader drives it, the open key drives nothing
    fw = Firmware(sim_bin, tmp_path / "followers", "--radio-record", str(record))
    good = SerialLink(str(fw.link), 3, radio_key=key, sender_id=1)
    try:
        _drive(good, 2.0)  # then looked at as the drives go on: a reply on its way is not a silent robot
        wait_for(lambda: (_drive(good, 0.2), good.answering().all() and all("moving" in fw.events(r) for r in (1, 2, 3)))[1],
                 10, "every robot answering and moving")
    finally:
        good.close()
    stranger = SerialLink(str(fw.link), 3)  # no key: the open key
    try:
        _drive(stranger, 1.5)
        assert not stranger.answering().any() and stranger.link_state.startswith("link lost")
        assert sum(s.answered for s in stranger.stats) == 0
    finally:
        stranger.close()
        fw.close()


def test_a_rotation_keeps_the_fleet_driving_and_retires_the_old_key(keys, tmp_path):
    work = tmp_path / "radio"
    shutil.copytree(keys, work)
    (tmp_path / "L1").mkdir(mode=0o700)  # L1's bundle beside it, as fleet-keys lays them out
    shutil.copy(keys / "L1.radio", tmp_path / "L1" / "L1.radio")
    old = load_leader_key(work / "L1.radio").key
    assert main_cli("radio-rotate", str(work), "--begin").returncode == 0
    both = load_robot_auth(work / "robots.json")
    new = load_leader_key(work / "next" / "L1.radio").key
    assert both.leader_keys[0] == (old, new) and load_leader_key(work / "L1.radio").key == old
    assert main_cli("radio-rotate", str(work), "--begin").returncode == 2  # one at a time
    radio = Radio(1, 2, auth=both)  # the robots provisioned with both (step 2)
    import threading

    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    carrier.start()
    try:
        for key in (old, new):  # a leader on the old key, then restarted on the new one (step 3)
            link = SerialLink(radio.paths[0], 2, radio_key=key, sender_id=1)
            try:
                _drive(link, 1.5)
                wait_for(lambda link=link: (_drive(link, 0.2), link.answering().all())[1], 10, f"both answering on {key!r}")
            finally:
                link.close()
        assert main_cli("radio-rotate", str(work), "--finish").returncode == 0
        after = load_robot_auth(work / "robots.json")
        assert after.leader_keys[0] == (new,) and load_leader_key(work / "L1.radio").key == new
        assert load_leader_key(tmp_path / "L1" / "L1.radio").key == new  # the bundle's copy too
        radio.robots.auth = after  # provisioned again (step 4): the old key is refused
        link = SerialLink(radio.paths[0], 2, radio_key=old, sender_id=1)
        try:
            _drive(link, 1.0)
            assert not link.answering().any()
        finally:
            link.close()
        assert sum(s.refusals.bad_mac for s in radio.robots.snapshot().values()) > 10
    finally:
        stop.set()
        carrier.join(5)
        radio.close()


def test_an_older_robot_is_named_and_not_driven_unless_the_operator_allows_it():
    import threading

    radio = Radio(1, 3, auth=RadioAuth(), older=(2,))  # R2 speaks protocol 2 only
    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    carrier.start()
    try:
        link = SerialLink(radio.paths[0], 3)
        try:
            wait_for(lambda: (_drive(link, 0.2), UNAUTHENTICATED in link.link_state)[1], 10, "R2 named")
            _drive(link, 1.0)
            wait_for(lambda: (_drive(link, 0.2), link.answering().tolist() == [True, False, True]
                              and radio.robots.snapshot()[1].moving and radio.robots.snapshot()[3].moving)[1],
                     10, "R1 and R3 answering and moving")
            assert f"F2 {UNAUTHENTICATED}" in link.link_state and not link.answering()[1]
            assert not radio.robots.snapshot()[2].moving  # never driven
        finally:
            link.close()
        link = SerialLink(radio.paths[0], 3, allow_unauthenticated=True)
        try:
            # R2 answers and moves (read as the drives go on: on a loaded machine a later look may find
            # its watchdog already holding it after a late drive)
            wait_for(lambda: (_drive(link, 0.2), link.answering().all() and radio.robots.snapshot()[2].target_l_mps > 0)[1],
                     10, "R2 driven, as allowed")
            assert link.link_state.endswith(ALLOWED_NOTE)
        finally:
            link.close()
    finally:
        stop.set()
        carrier.join(5)
        radio.close()


def test_a_leader_never_believes_a_strangers_reply(keys):
    """On the fleet's radio a stranger answers for the robots: plain NACKs and OWNERs naming
    leader 1, and authenticated ones with the open key and leader 1's id. Leader 1 keeps owning
    and driving its robots; the forgeries are counted, never taken."""
    import threading

    auth = load_robot_auth(keys / "robots.json")
    radio = Radio(2, 2, auth=auth)
    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    carrier.start()
    link = SerialLink(radio.paths[0], 2, radio_id=1, radio_key=load_leader_key(keys / "L1.radio").key)
    import serial

    stranger = serial.Serial(radio.paths[1], 115200, timeout=0.01)
    try:
        wait_for(lambda: (_drive(link, 0.1), link.owns(1) and link.owns(2))[1], 10, "leader 1 owning R1, R2")
        counter = int((time.time() - 1_704_067_200) * 1000) * 256  # where the document says counters start
        for k in range(60):
            for a in (1, 2):
                no = p.Ownership(9, 5000, p.NACK_OWNED, 1)
                for seq in range(0, 256, 32):
                    stranger.write(p.encode_frame(p.nack(a, seq, no)))
                    stranger.write(p.encode_frame(p.seal(p.nack(a, seq, no), p.OPEN_KEY, 1, counter + k * 64 + seq)))
            _drive(link, 1 / 30)
        assert link.owns(1) and link.owns(2)
        wait_for(lambda: (_drive(link, 0.2), link.answering().all() and radio.robots.snapshot()[1].moving
                          and radio.robots.snapshot()[2].moving)[1], 10, "both answering and moving")
        robots = radio.robots.snapshot()
        assert robots[1].owner == robots[2].owner == 1
        assert sum(s.unmatched for s in link.stats) > 100  # counted, never taken
    finally:
        stranger.close()
        link.close()
        stop.set()
        carrier.join(5)
        radio.close()



def test_a_leaders_counter_only_grows_across_restarts_even_with_its_clock_set_back(tmp_path):
    """docs/follower-protocol.md, "Counters that only grow": from the wall clock (256 per ms and a
    random start), and with --radio-counter above the high-water mark written before it is used."""
    from app.backends.serial_link import FrameCounter

    now = [1_800_000_000.0]
    first = FrameCounter(lambda: now[0])
    a = [first.next() for _ in range(1000)]
    assert a == sorted(set(a)) and a[0] >= int((now[0] - FrameCounter.EPOCH_S) * 1000) * 256
    now[0] += 0.5  # a restart half a second later starts above every counter used
    assert FrameCounter(lambda: now[0]).next() > a[-1]
    mark = tmp_path / "counter"
    kept = FrameCounter(lambda: now[0], mark)
    used = [kept.next() for _ in range(10)]
    assert int(mark.read_text()) > used[-1]  # reserved before it was used
    now[0] -= 3600.0  # the clock set back an hour: the file keeps the counter above
    assert FrameCounter(lambda: now[0], mark).next() > used[-1]
