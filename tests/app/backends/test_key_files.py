"""The key folder against hostile input, on real files (docs/safety.md, "Key files and counters";
docs/follower-protocol.md, "Keys and provisioning", "Counters that only grow", "Rotating the
key"): names that would collide with the folder's own layout, key and counter files that are not
regular files or are too big or too deep, counters that are corrupt or cannot go up, and a
rotation interrupted half way. Each is one line on stderr, exit 2, and nothing written."""

from __future__ import annotations

import pytest

from tests.helpers import main_cli


def _files(d) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*")) if d.exists() else []


def _one_line(r) -> str:
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (r.returncode, r.stderr)
    return lines[0]


@pytest.mark.parametrize("leaders, words", [
    ("ca,L1", "a name the key folder uses itself"),  # would write over the CA's ca.key and ca.pem
    ("L1,radio", "a name the key folder uses itself"),  # would get the radio folder as its bundle
    ("L1,next", "a name the key folder uses itself"),
    ("CA,L1", "a name the key folder uses itself"),  # "CA" is "ca" on a case-blind file system
    ("L1,Robots", "a name the key folder uses itself"),
    ("L1,l1", "twice"),
    ("1L", "a letter first"),
    ("L1,-L2", "a letter first"),
    ("_x", "a letter first"),
    ("L1,../L2", "a letter first"),
    ("L 1", "1 to 32 characters"),
    ("L1,L2." , "a letter first"),
    ("L" * 33, "1 to 32 characters"),
    ("L\u00e9", "a letter first"),
])
def test_identity_names_that_collide_or_are_not_names_are_refused_and_nothing_is_written(tmp_path, leaders, words):
    d = tmp_path / "keys"
    r = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", leaders)
    line = _one_line(r)
    assert words in line and "--leaders" in line, line
    assert _files(d) == []


def test_too_many_leaders_for_the_radio_are_refused_before_any_file_is_written(tmp_path):
    d = tmp_path / "keys"
    r = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", ",".join(f"L{k}" for k in range(1, 18)))
    assert "at most 16" in _one_line(r) and _files(d) == []


def test_good_names_still_make_keys(tmp_path):
    d = tmp_path / "keys"
    r = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", "L1,leader_2,Rover-3,x" + "y" * 31)
    assert r.returncode == 0, r.stderr
    assert (d / "ca" / "ca.key").is_file() and (d / "leader_2" / "leader_2.radio").is_file()


# -- key files that are not small regular files ---------------------------------------------------
@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet") / "keys"
    made = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", "L1,L2")
    assert made.returncode == 0, made.stderr
    return d


def _hostile_files(tmp_path) -> dict[str, str]:
    """What a user may name by mistake (or a stranger may leave) where a key is expected."""
    import os

    fifo = tmp_path / "key.fifo"
    os.mkfifo(fifo, 0o600)  # no writer: opening it for reading waits for one, unless told not to
    big = tmp_path / "big.radio"
    big.write_bytes(b" " * (2 << 20))
    big.chmod(0o600)
    nested = tmp_path / "nested.json"
    nested.write_text("[" * 5000 + "]" * 5000)
    nested.chmod(0o600)
    deep = tmp_path / "deep.json"
    deep.write_text('{"keys": ' + "[" * 5000 + "]" * 5000 + "}")
    deep.chmod(0o600)
    return {"a FIFO": str(fifo), "a device": "/dev/zero", "a folder": str(tmp_path), "bytes; ": str(big),
            "nested too deep": str(nested), "nested too deep ": str(deep)}


def test_a_fifo_as_the_radio_key_is_one_line_not_a_hang(tmp_path):
    """In a process of its own, as typed, with a deadline: a reader that waited for a writer
    would never come back."""
    import os
    import subprocess
    import sys

    from tests.helpers import ROOT

    fifo = tmp_path / "L1.radio"
    os.mkfifo(fifo, 0o600)
    r = subprocess.run([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--link",
                        "serial:/dev/null", "--radio-key", str(fifo)], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert f"{fifo}: is a FIFO; a leader's radio key must be a regular file" in _one_line(r)


def test_radio_keys_and_the_robots_record_are_read_only_from_small_regular_files(tmp_path):
    for words, path in _hostile_files(tmp_path).items():
        r = main_cli("run", "--port", "0", "--no-record", "--link", "serial:/dev/null", "--radio-key", path)
        assert words.strip() in _one_line(r) and path in r.stderr, (words, r.stderr)
        for cmd in (("radio-provision", path, "--record", str(tmp_path / "r.bin")),
                    ("emulate-follower", "--radio-key", path)):
            r = main_cli(*cmd)
            assert words.strip() in _one_line(r) and path in r.stderr, (cmd, r.stderr)
        assert not (tmp_path / "r.bin").exists()


def test_foxglove_tls_files_are_read_only_from_small_regular_files(tmp_path, fleet):
    cert = str(fleet / "ca" / "ca.pem")
    for words, path in _hostile_files(tmp_path).items():
        if "nested" in words:
            continue  # not JSON: a PEM file
        r = main_cli("run", "--port", "0", "--no-record", "--foxglove", "127.0.0.1:0", "--foxglove-tls-cert", cert,
                     "--foxglove-tls-key", path)
        assert words.strip() in _one_line(r) and "--foxglove-tls-key" in r.stderr, (words, r.stderr)


def test_certificates_keys_and_rosters_of_a_bundle_are_read_only_from_small_regular_files(tmp_path, fleet):
    import os
    import shutil

    from app.fleet.security import KeyFileError
    from app.ros2.session import ros2_keys

    (tmp_path / "hostile").mkdir()
    hostile = _hostile_files(tmp_path / "hostile")
    for name in ("page.key", "page.pem", "ca.pem", "fleet.json"):
        for words, path in hostile.items():
            if "nested" in words and name != "fleet.json":
                continue
            bundle = tmp_path / f"page-{name}"
            shutil.rmtree(bundle, ignore_errors=True)
            shutil.copytree(fleet / "page", bundle)
            (bundle / name).unlink()
            if words == "a FIFO":
                os.mkfifo(bundle / name, 0o600)
            elif words in ("a device", "a folder"):
                (bundle / name).symlink_to(path)  # the bundle's file names one
            else:
                shutil.copy(path, bundle / name)
            r = main_cli("fleet", "--fleet", "lab", "--port", "0", "--keys", str(bundle))
            line = _one_line(r)
            assert str(bundle / name) in line, (name, words, line)
            if name == "fleet.json":
                with pytest.raises(KeyFileError, match="fleet.json"):
                    ros2_keys(bundle)


# -- the frame counter file (run --radio-counter FILE) --------------------------------------------
def _run_with_counter(fleet, counter) -> object:
    return main_cli("run", "--port", "0", "--no-record", "--link", "serial:/dev/null", "--radio-key",
                    str(fleet / "radio" / "L1.radio"), "--radio-counter", str(counter))


@pytest.mark.parametrize("content", ["garbage\n", "", "\n", "-5\n", "1.5\n", "1e9\n", "+5\n", "0x10\n", "12 13\n",
                                     "\u0663\n", "281474976710656\n", "99999999999999999999999\n", "\x00" * 8])
def test_a_corrupt_counter_file_is_refused_at_start_and_never_rewritten(tmp_path, fleet, content):
    counter = tmp_path / "counter"
    counter.write_text(content)
    before = counter.read_bytes(), counter.stat().st_mtime_ns
    line = _one_line(_run_with_counter(fleet, counter))
    assert f"{counter}: not a frame counter" in line and "write in it a number above" in line, line
    assert (counter.read_bytes(), counter.stat().st_mtime_ns) == before
    assert [p.name for p in tmp_path.iterdir()] == ["counter"]  # no temporary left either


def test_a_counter_file_that_is_not_a_readable_regular_file_is_refused_at_start(tmp_path, fleet):
    import os

    loop = tmp_path / "loop"
    loop.symlink_to(loop)  # a link to itself: cannot be opened
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "nowhere")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    under_a_file = tmp_path / "L1.txt"
    under_a_file.write_text("a file, not a folder\n")
    for path, words in ((loop, "cannot read"), (dangling, "a link to nothing"), (fifo, "is a FIFO"),
                        (tmp_path, "is a folder"), ("/dev/null", "is a device"), ("/dev/zero", "is a device"),
                        (under_a_file / "counter", "cannot read")):
        line = _one_line(_run_with_counter(fleet, path))
        assert f"{path}: " in line and words in line, (path, line)
    assert not (tmp_path / "nowhere").exists()


def test_an_unwritable_counter_file_is_refused_at_start_and_kept(tmp_path, fleet):
    """The counter is reserved in the file before it is used: a file run cannot write is refused
    before the first frame. Made unwritable for real: the temporary it is written through is a
    folder (root writes through any mode bits)."""
    counter = tmp_path / "counter"
    counter.write_text("12345\n")
    (tmp_path / ".counter.new").mkdir()
    (tmp_path / ".counter.new" / "x").write_text("")
    line = _one_line(_run_with_counter(fleet, counter))
    assert f"{counter}: cannot write the frame counter file" in line, line
    assert counter.read_text() == "12345\n"


def test_a_counter_that_cannot_go_up_is_refused_at_start_with_what_to_do(tmp_path, fleet):
    import time

    from app.backends.link_auth import FrameCounter
    from core.link import protocol as p

    counter = tmp_path / "counter"
    for mark in (p.COUNTER_MAX, p.COUNTER_MAX - 1, p.COUNTER_MAX - 1000):  # at or near 2^48: stuck there before
        counter.write_text(f"{mark}\n")
        line = _one_line(_run_with_counter(fleet, counter))
        assert "cannot go up" in line and "new radio id" in line, line
        assert counter.read_text() == f"{mark}\n"
    ahead = FrameCounter.clock_counter(time.time() + 2 * 86400)  # the clock two days behind the file
    counter.write_text(f"{ahead}\n")
    line = _one_line(_run_with_counter(fleet, counter))
    assert "days behind the frame counter" in line and "set the clock right" in line, line
    assert counter.read_text() == f"{ahead}\n"


def test_a_good_counter_file_and_a_new_one_are_used_and_only_grow(tmp_path):
    """The file is made on the first start (the clock's counter), reserved ahead before use, and
    a clock set back less than a day starts above it."""
    from app.backends.link_auth import FrameCounter
    from app.files import UserError

    now = [1_800_000_000.0]
    counter = tmp_path / "counter"
    first = FrameCounter(lambda: now[0], counter)
    assert int(counter.read_text()) == FrameCounter.clock_counter(now[0])  # made at start
    used = [first.next() for _ in range(5)]
    assert int(counter.read_text()) == used[0] + FrameCounter.BLOCK  # reserved before the first was used
    now[0] -= 12 * 3600.0  # set back half a day: the file keeps the counter above
    assert FrameCounter(lambda: now[0], counter).next() > used[-1]
    now[0] -= 2 * 86400.0  # two days: refused, the file as it was
    kept = counter.read_text()
    with pytest.raises(UserError, match="days behind"):
        FrameCounter(lambda: now[0], counter)
    assert counter.read_text() == kept


# -- a rotation stopped half way (radio-rotate DIR/radio --begin / --finish / --status) ------------
def _secrets(radio) -> tuple[bytes, ...]:
    """The fleet's radio secrets in robots.json (the current one, and the next during a rotation)."""
    import json

    return tuple(bytes.fromhex(k) for k in json.loads((radio / "robots.json").read_text())["keys"])


def _agree(d) -> bytes:
    """Every file of the radio folder and every bundle's copy holds its leader's key under the
    robots' one secret, and the robots hold those keys; that secret."""
    from app.backends.radio_keys import leader_key, load_leader_key, load_robot_auth

    (secret,) = _secrets(d / "radio")
    auth = load_robot_auth(d / "radio" / "robots.json")
    for rid, n in enumerate(("L1", "L2", "L3"), start=1):
        key = leader_key(secret, rid)
        assert auth.keys_of(rid) == (key,), n
        assert load_leader_key(d / "radio" / f"{n}.radio").key == key, n
        assert load_leader_key(d / n / f"{n}.radio").key == key, f"{n}'s bundle"
    assert not (d / "radio" / "next").exists()
    assert not [p for p in d.rglob(".*.new")]  # no temporary left behind
    return secret


def _status(radio) -> str:
    r = main_cli("radio-rotate", str(radio), "--status")
    assert r.returncode == 0, r.stderr
    return r.stdout


def _snapshot(d) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture
def three(tmp_path):
    d = tmp_path / "keys"
    assert main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", "L1,L2,L3").returncode == 0
    return d


def test_a_finish_stopped_by_an_unwritable_bundle_changes_nothing_and_is_finished_by_running_it_again(three):
    """The issue's case: one leader's bundle cannot be written. Before, --finish left robots.json
    on the new key and L2, L3 on the old, and a second --finish said no rotation was under way."""
    radio, bundle = three / "radio", three / "L2" / "L2.radio"
    old = _agree(three)
    assert "no rotation under way" in _status(radio)
    assert main_cli("radio-rotate", str(radio), "--begin").returncode == 0
    assert "begun" in _status(radio) and "next/ holds 3 of 3" in _status(radio)
    bundle.unlink()
    bundle.mkdir()  # a folder in the copy's place: the write fails for real
    (bundle / "keep").write_text("")
    before = _snapshot(three)
    line = _one_line(main_cli("radio-rotate", str(radio), "--finish"))
    assert f"{bundle}: cannot write" in line and "nothing changed" in line and "run the same step again" in line, line
    assert _snapshot(three) == before  # robots.json still lists both keys, every leader file as it was
    assert "begun" in _status(radio) and "is a folder" in _status(radio)
    (bundle / "keep").unlink()
    bundle.rmdir()  # fixed
    r = main_cli("radio-rotate", str(radio), "--finish")
    assert r.returncode == 0, r.stderr
    assert _agree(three) != old
    assert "no rotation under way" in _status(radio)
    again = main_cli("radio-rotate", str(radio), "--finish")
    assert "no rotation under way" in _one_line(again)
    _l2_drives(three)


def _l2_drives(d) -> None:
    """Robots provisioned from robots.json answer L2 driving with its bundle's key (before, L2 drove
    0 of 309 ticks after the interrupted finish)."""
    import threading
    import time

    import numpy as np

    from app.backends.radio import Radio
    from app.backends.radio_keys import load_leader_key, load_robot_auth
    from app.backends.serial_link import SerialLink
    from core.types import Commands
    from tests.helpers import wait_for

    radio = Radio(1, 2, auth=load_robot_auth(d / "radio" / "robots.json"))
    stop = threading.Event()
    carrier = threading.Thread(target=radio.run, args=(stop,), daemon=True)
    carrier.start()
    l2 = load_leader_key(d / "L2" / "L2.radio")
    link = SerialLink(radio.paths[0], 2, radio_key=l2.key, sender_id=l2.radio_id)

    def drive() -> bool:
        for _ in range(6):
            link.send(Commands(np.full(2, 0.1), np.zeros(2), observed_at=time.monotonic()))
            time.sleep(1 / 30)
        return bool(link.answering().all())

    try:
        wait_for(drive, 10, "L2 driving its robots on the rotated key")
    finally:
        link.close()
        stop.set()
        carrier.join(5)
        radio.close()


def test_a_finish_on_a_read_only_bundle_changes_nothing(three, tmp_path):
    """The same with a bundle on a read-only file system (a real mount; root only)."""
    import subprocess

    radio, bundle_dir = three / "radio", three / "L3"
    assert main_cli("radio-rotate", str(radio), "--begin").returncode == 0
    saved = _snapshot(bundle_dir)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m,mode=0700", "tmpfs", str(bundle_dir)],
                      capture_output=True).returncode != 0:
        pytest.skip("mounting a tmpfs needs root")
    try:
        for name, data in saved.items():
            (bundle_dir / name).write_bytes(data)
            (bundle_dir / name).chmod(0o600)
        assert subprocess.run(["mount", "-o", "remount,ro", str(bundle_dir)]).returncode == 0
        before = _snapshot(three)
        line = _one_line(main_cli("radio-rotate", str(radio), "--finish"))
        assert "L3.radio: cannot write (Read-only file system)" in line and "nothing changed" in line, line
        assert _snapshot(three) == before
    finally:
        subprocess.run(["umount", str(bundle_dir)], check=True)
    for name, data in saved.items():  # the folder under the mount, as it was
        assert (bundle_dir / name).read_bytes() == data
    assert main_cli("radio-rotate", str(radio), "--finish").returncode == 0
    _agree(three)


def test_a_finish_stopped_among_its_renames_is_finished_by_running_it_again(three):
    """What a finish killed between its renames leaves (the bundles and radio files renamed, not
    robots.json), and what one killed after robots.json leaves (next/ still there): --status says
    so, --finish completes it."""
    import shutil

    radio = three / "radio"
    assert main_cli("radio-rotate", str(radio), "--begin").returncode == 0
    new = _secrets(radio)[1]
    for n in ("L1", "L2"):  # renamed before the crash: L3 and robots.json not
        shutil.copy(radio / "next" / f"{n}.radio", three / n / f"{n}.radio")
        shutil.copy(radio / "next" / f"{n}.radio", radio / f"{n}.radio")
    status = _status(radio)
    assert "a --finish was interrupted" in status and "L1" in status and "run --finish again" in status, status
    assert main_cli("radio-rotate", str(radio), "--finish").returncode == 0
    assert _agree(three) == new
    # killed after robots.json, before next/ was removed; and L3's bundle copy not renamed
    assert main_cli("radio-rotate", str(radio), "--begin").returncode == 0
    keep = (three / "L3" / "L3.radio").read_bytes()
    newer = _secrets(radio)[1]
    shutil.copytree(radio / "next", three / "next-saved")
    assert main_cli("radio-rotate", str(radio), "--finish").returncode == 0
    shutil.copytree(three / "next-saved", radio / "next")
    shutil.rmtree(three / "next-saved")
    (three / "L3" / "L3.radio").write_bytes(keep)
    status = _status(radio)
    assert "a --finish was interrupted" in status and "../L3/L3.radio" in status, status
    assert main_cli("radio-rotate", str(radio), "--finish").returncode == 0
    assert _agree(three) == newer


def test_a_begin_stopped_before_robots_json_is_started_afresh_by_running_it_again(three):
    """next/ written, robots.json not: the robots know nothing of that key. --finish refuses it,
    --status says so, --begin starts afresh with a new key."""
    import json

    from app.backends.radio_keys import leader_key, load_leader_key

    radio = three / "radio"
    old = _agree(three)
    (radio / "next").mkdir(mode=0o700)
    stray = (radio / "next" / "L1.radio")
    stray.write_text(json.dumps({"radio_id": 1, "key": "ab" * 32}) + "\n")
    stray.chmod(0o600)
    assert "a --begin was interrupted" in _status(radio)
    assert "a --begin was interrupted" in _one_line(main_cli("radio-rotate", str(radio), "--finish"))
    assert _secrets(radio) == (old,)
    assert main_cli("radio-rotate", str(radio), "--begin").returncode == 0
    keys = _secrets(radio)
    assert keys[0] == old and keys[1] != bytes.fromhex("ab" * 32)
    assert all(load_leader_key(radio / "next" / f"L{r}.radio").key == leader_key(keys[1], r) for r in (1, 2, 3))
    assert main_cli("radio-rotate", str(radio), "--finish").returncode == 0
    assert _agree(three) == keys[1]
