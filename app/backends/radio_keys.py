"""The fleet's radio key on disk: one file per leader, one record for the robots, and what the
firmware is flashed with (docs/follower-protocol.md, "Keys and provisioning").

`omniformation fleet-keys DIR ...` writes DIR/radio/ (mode 0700, the operator's, like the CA):
``robots.json`` (the keys the robots accept, the leaders' radio ids, the STOP policy) and
``<leader>.radio`` per leader (its radio id, its place among the leaders, and the key it signs
with), each mode 0600. A leader's machine gets only its own ``.radio`` file; the robots get
``robots.json`` turned into a C header or a binary record by `omniformation radio-provision`.
A key file that others may read, or that is not what it should be, is one line naming it.
"""

from __future__ import annotations

import json
import os
import secrets
import stat
import struct
from dataclasses import dataclass
from pathlib import Path

from core.link import protocol as p
from core.link.follower import MAX_SENDERS, STOP_ANYONE, STOP_POLICIES, RadioAuth

from app.files import UserError, parse_json, read_regular

ROBOTS = "robots.json"
SUFFIX = ".radio"
NEXT = "next"  # during a rotation: the leaders' files with the next key, to deploy once the robots hold both
RECORD_MAGIC = b"OFR3"


@dataclass(frozen=True)
class LeaderRadioKey:
    """What a leader signs its frames with."""

    radio_id: int
    key: bytes


def _write_secret(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.new")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(tmp, 0o600)
    tmp.replace(path)


def _private_dir(directory: Path) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)


def _leader_text(radio_id: int, key: bytes) -> str:
    return json.dumps({"radio_id": radio_id, "key": key.hex()}, indent=1) + "\n"


def check_radio_keys_writable(directory: Path, leaders: tuple[str, ...], *, overwrite: bool = False) -> list[Path]:
    """The files :func:`write_radio_keys` would write, checked before anything is written: at most
    16 leaders, and (without ``overwrite``) no key there already (FileExistsError naming it)."""
    if len(leaders) > MAX_SENDERS:
        raise ValueError(f"--leaders: {len(leaders)} leaders; a robot keeps counters for at most {MAX_SENDERS}")
    files = [directory / ROBOTS] + [directory / f"{name}{SUFFIX}" for name in leaders]
    if not overwrite:
        for f in (*files, directory / NEXT):
            if f.exists() or f.is_symlink():
                raise FileExistsError(f"{f}: exists; fleet-keys writes over keys only with --overwrite")
    return files


def write_radio_keys(directory: Path, leaders: tuple[str, ...], *, overwrite: bool = False,
                     stop: str = STOP_ANYONE) -> list[Path]:
    """A fresh radio key (32 random bytes) for the fleet: ``directory``/robots.json and one
    ``<leader>.radio`` per leader (radio id = its place among the leaders, 1..). Refuses
    (FileExistsError naming the file) to write over a key unless ``overwrite``."""
    files = check_radio_keys_writable(directory, leaders, overwrite=overwrite)
    _private_dir(directory)
    key = secrets.token_bytes(p.RADIO_KEY_LEN)
    ids = {name: k + 1 for k, name in enumerate(leaders)}
    _write_secret(files[0], json.dumps({"keys": [key.hex()], "leaders": ids, "stop": stop}, indent=1) + "\n")
    for name in leaders:
        _write_secret(directory / f"{name}{SUFFIX}", _leader_text(ids[name], key))
    return files


def _read_private(path: Path, what: str) -> dict[str, object]:
    """A key file: a regular file of at most 64 KiB (app.files.read_regular), private, JSON."""
    try:
        raw = read_regular(path, what)
        st = path.stat()
    except FileNotFoundError:
        raise UserError(f"{path}: cannot read {what} (no such file; `omniformation fleet-keys` writes it)") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise UserError(f"{path}: {what} is readable or writable by others (mode {stat.S_IMODE(st.st_mode):o});"
                        f" chmod 600 {path}")
    data = parse_json(raw, path, what)
    if not isinstance(data, dict):
        raise UserError(f"{path}: not {what} (a JSON object expected)")
    return data


def _key(path: Path, value: object) -> bytes:
    if not isinstance(value, str) or len(value) != 2 * p.RADIO_KEY_LEN:
        raise UserError(f"{path}: a radio key is {p.RADIO_KEY_LEN} bytes in hex ({2 * p.RADIO_KEY_LEN} digits)")
    try:
        return bytes.fromhex(value)
    except ValueError:
        raise UserError(f"{path}: a radio key is {p.RADIO_KEY_LEN} bytes in hex") from None


def load_leader_key(path: Path) -> LeaderRadioKey:
    """A leader's ``.radio`` file, checked (one-line UserError)."""
    data = _read_private(path, "a leader's radio key")
    rid = data.get("radio_id")
    if type(rid) is not int or not 1 <= rid <= p.MAX_LEADER:
        raise UserError(f"{path}: radio_id must be 1..{p.MAX_LEADER}")
    return LeaderRadioKey(rid, _key(path, data.get("key")))


def load_robot_auth(path: Path) -> RadioAuth:
    """The robots' record (``robots.json``), checked (one-line UserError)."""
    data = _read_private(path, "the robots' radio keys")
    keys = data.get("keys")
    if not isinstance(keys, list) or not 1 <= len(keys) <= 2:
        raise UserError(f"{path}: keys must list the current key and, during a rotation, the next one")
    leaders = data.get("leaders")
    if not isinstance(leaders, dict) or not leaders or len(leaders) > MAX_SENDERS or any(
            type(v) is not int or not 1 <= v <= p.MAX_LEADER for v in leaders.values()):
        raise UserError(f"{path}: leaders must map 1..{MAX_SENDERS} leader names to radio ids 1..{p.MAX_LEADER}")
    stop = data.get("stop", STOP_ANYONE)
    if stop not in STOP_POLICIES:
        raise UserError(f"{path}: stop must be one of {', '.join(STOP_POLICIES)}, not {stop!r}")
    return RadioAuth(tuple(_key(path, k) for k in keys), tuple(sorted(leaders.values())), str(stop))


def set_stop_policy(path: Path, stop: str) -> None:
    data = _read_private(path, "the robots' radio keys")
    data["stop"] = stop
    _write_secret(path, json.dumps(data, indent=1) + "\n")


def rotate(directory: Path, finish: bool) -> list[Path]:
    """Begin a rotation (a new key: the robots accept both, the leaders' next files are written to
    ``NEXT``/) or finish it (the robots accept only the new key; the next files replace the
    leaders' files). docs/follower-protocol.md, "Rotating the key", step by step."""
    robots = directory / ROBOTS
    load_robot_auth(robots)  # checked
    data = _read_private(robots, "the robots' radio keys")
    keys = list(data["keys"])  # type: ignore[call-overload]
    leaders: dict[str, int] = dict(data["leaders"])  # type: ignore[call-overload]
    nxt = directory / NEXT
    if not finish:
        if len(keys) == 2:
            raise UserError(f"{robots}: a rotation is already under way; finish it first (--finish)")
        new = secrets.token_bytes(p.RADIO_KEY_LEN)
        data["keys"] = [keys[0], new.hex()]
        _private_dir(nxt)
        written = [robots] + [nxt / f"{n}{SUFFIX}" for n in leaders]
        for n, rid in leaders.items():
            _write_secret(nxt / f"{n}{SUFFIX}", _leader_text(rid, new))
        _write_secret(robots, json.dumps(data, indent=1) + "\n")
        return written
    if len(keys) != 2:
        raise UserError(f"{robots}: no rotation under way (--begin starts one)")
    data["keys"] = [keys[1]]
    written = [robots]
    for n in leaders:
        src = nxt / f"{n}{SUFFIX}"
        if src.exists():
            src.replace(directory / f"{n}{SUFFIX}")
            written.append(directory / f"{n}{SUFFIX}")
    _write_secret(robots, json.dumps(data, indent=1) + "\n")
    if nxt.is_dir() and not any(nxt.iterdir()):
        nxt.rmdir()
    return written


# -- the frame counter's high-water mark (run --radio-counter FILE) --------------------------------
COUNTER_HEADROOM = 1 << 36  # a counter file this close to 2^48 cannot go up for long: refused at start
COUNTER_PER_DAY = 256 * 86_400_000  # the clock's counter runs 256 a millisecond
COUNTER_CLOCK_SLACK = COUNTER_PER_DAY  # a clock this far behind the file is wrong: refused at start


def _counter_help(clock_counter: int) -> str:
    return (f"the counter this machine's clock gives now is {clock_counter};"
            " docs/follower-protocol.md, \"Counters that only grow\", says what to do")


def read_counter_mark(path: Path, clock_counter: int | None = None) -> int | None:
    """The high-water mark in a counter file (None: no file yet). One whole number 0..2^48-1 and a
    newline is the only content: anything else (empty, -5, 1.5, text) is one UserError line, and
    the file is left as it is (a guess could bring back a used counter)."""
    try:
        raw = read_regular(path, "a frame counter file", limit=64)
    except FileNotFoundError:
        if path.is_symlink():
            raise UserError(f"{path}: cannot read a frame counter file (a link to nothing)") from None
        return None
    except OSError as exc:
        raise UserError(f"{path}: cannot read a frame counter file ({exc.strerror or exc})") from None
    text = raw.decode("ascii", "replace").strip()
    if not text.isascii() or not text.isdigit() or int(text) > p.COUNTER_MAX:
        shown = repr(text[:24]) if text else "nothing"
        raise UserError(f"{path}: not a frame counter (one whole number 0..{p.COUNTER_MAX} expected, found {shown});"
                        " left as it is: write in it a number above the last counter this leader used"
                        + (f" ({_counter_help(clock_counter)})" if clock_counter is not None else ""))
    return int(text)


def check_counter_file(path: Path, clock_counter: int) -> int:
    """``run --radio-counter FILE`` at start: the mark to start above (-1: a new file), checked so
    that the counter can go up from it, and the file shown to be writable (it is written back as it
    is, or made with the clock's counter), all before anything is sent. ``clock_counter``: where
    the clock alone would start. Every problem is one UserError line saying what to do."""
    mark = read_counter_mark(path, clock_counter)
    if mark is not None and mark >= p.COUNTER_MAX - COUNTER_HEADROOM:
        raise UserError(f"{path}: the frame counter is at {mark}, within {COUNTER_HEADROOM} of its 48-bit end"
                        f" ({p.COUNTER_MAX}): this leader's counter cannot go up; give it a new radio id (fleet-keys"
                        " --overwrite, then provision the robots) and a new counter file")
    if clock_counter >= p.COUNTER_MAX - COUNTER_HEADROOM:
        raise UserError(f"--radio-counter {path}: this machine's clock gives counter {clock_counter}, within"
                        f" {COUNTER_HEADROOM} of its 48-bit end: is the clock right? Set it and start again")
    if mark is not None and mark - clock_counter > COUNTER_CLOCK_SLACK:
        days = (mark - clock_counter) / COUNTER_PER_DAY
        raise UserError(f"{path}: this machine's clock is {days:.1f} days behind the frame counter this leader"
                        " reached before: set the clock right (the robots refuse a counter below one they took;"
                        f" {_counter_help(clock_counter)})")
    try:
        write_counter_mark(path, mark if mark is not None else clock_counter)
    except OSError as exc:
        raise UserError(f"{path}: cannot write the frame counter file ({exc.strerror or exc}); the counter is kept"
                        " there before it is used, so run needs to write it") from None
    return mark if mark is not None else -1


def write_counter_mark(path: Path, mark: int) -> None:
    """Reserve counters up to ``mark`` before they are used: written to a temporary name, synced
    and renamed, so the file always holds a whole mark."""
    tmp = path.with_name(f".{path.name}.new")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"{mark}\n")
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)


def copy_into_bundles(files: list[Path], fleet_dir: Path) -> list[Path]:
    """Each leader's ``ID.radio`` also into its identity bundle ``fleet_dir/ID/`` (fleet-keys'
    folder copied whole to that leader's machine), where that bundle exists; mode 0600."""
    copies: list[Path] = []
    for f in files:
        if f.suffix != SUFFIX:
            continue
        bundle = fleet_dir / f.stem
        if bundle.is_dir():
            copy = bundle / f.name
            _write_secret(copy, f.read_text())
            copies.append(copy)
    return copies


def binary_record(auth: RadioAuth) -> bytes:
    """What a robot's flash holds (firmware/host_sim.c reads it): "OFR3", n keys, the keys, n
    leaders, their ids, the STOP policy (0 anyone, 1 authenticated), CRC-16 of all before it."""
    body = RECORD_MAGIC + bytes((len(auth.keys),)) + b"".join(auth.keys) + bytes((len(auth.leaders),)) \
        + bytes(auth.leaders) + bytes((STOP_POLICIES.index(auth.stop),))
    return body + struct.pack("<H", p.crc16(body))


def c_header(auth: RadioAuth) -> str:
    """A C header defining ``OF_RADIO_AUTH`` (an of_radio_auth) for firmware/omni_follower.h."""
    def arr(b: bytes) -> str:
        return "{" + ", ".join(f"0x{x:02x}" for x in b) + "}"

    keys = ",\n     ".join(arr(k) for k in auth.keys)
    return ("/* The fleet's radio key for the robots: SECRET, keep out of version control. */\n"
            "#include \"omni_follower.h\"\n"
            f"static const of_radio_auth OF_RADIO_AUTH = {{\n    {{{keys}}},\n    {len(auth.keys)}u,\n"
            f"    {arr(bytes(auth.leaders))},\n    {len(auth.leaders)}u,\n"
            f"    {'OF_STOP_ANYONE' if auth.stop == STOP_ANYONE else 'OF_STOP_AUTHENTICATED'}\n}};\n")


def write_provision(auth: RadioAuth, header: Path | None, record: Path | None) -> list[Path]:
    out = []
    if header is not None:
        _write_secret(header, c_header(auth))
        out.append(header)
    if record is not None:
        tmp = record.with_name(f".{record.name}.new")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(binary_record(auth))
        tmp.replace(record)
        out.append(record)
    return out
