"""The fleet's radio key on disk: one file per leader, one record for the robots, and what the
firmware is flashed with (docs/follower-protocol.md, "Keys and provisioning").

`omniformation fleet-keys DIR ...` writes DIR/radio/ (mode 0700, the operator's, like the CA):
``robots.json`` (the fleet's radio secret, the leaders' radio ids, the STOP policy) and
``<leader>.radio`` per leader (its radio id, its place among the leaders, and its own key,
derived from the secret and its radio id: a leader's key signs as its own id alone), each mode
0600. A leader's machine gets only its own ``.radio`` file; the robots get each leader's key
(never the secret) from ``robots.json`` as a C header or a binary record by `omniformation
radio-provision`. A key file that others may read, or that is not what it should be, is one
line naming it. A rotation (`radio-rotate`) and the frame counter's file (`run --radio-counter`)
fail closed: see :func:`rotate` and :func:`check_counter_file`.
"""

from __future__ import annotations

import hashlib
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
RECORD_MAGIC = b"OFR3"  # one key for the fleet (an older robots.json)
RECORD_MAGIC_PER_LEADER = b"OFR4"  # a key per leader
DERIVE_LABEL = b"omniformation radio leader key "


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
    """A fresh radio secret (32 random bytes) for the fleet: ``directory``/robots.json (the
    secret: the operator's) and one ``<leader>.radio`` per leader (radio id = its place among the
    leaders, 1..; its own key, :func:`leader_key`). Refuses (FileExistsError naming the file) to
    write over a key unless ``overwrite``."""
    files = check_radio_keys_writable(directory, leaders, overwrite=overwrite)
    _private_dir(directory)
    stale = directory / NEXT  # a rotation of the key replaced now: its next files mean nothing any more
    if stale.is_dir():
        for old in stale.glob(f"*{SUFFIX}"):
            old.unlink()
        if not any(stale.iterdir()):
            stale.rmdir()
    secret = secrets.token_bytes(p.RADIO_KEY_LEN)
    ids = {name: k + 1 for k, name in enumerate(leaders)}
    _write_secret(files[0], json.dumps({"keys": [secret.hex()], "leaders": ids, "stop": stop, "per_leader": True},
                                       indent=1) + "\n")
    for name in leaders:
        _write_secret(directory / f"{name}{SUFFIX}", _leader_text(ids[name], leader_key(secret, ids[name])))
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
    if len(set(leaders.values())) != len(leaders):
        raise UserError(f"{path}: leaders must have distinct radio ids")
    stop = data.get("stop", STOP_ANYONE)
    if stop not in STOP_POLICIES:
        raise UserError(f"{path}: stop must be one of {', '.join(STOP_POLICIES)}, not {stop!r}")
    per_leader = data.get("per_leader", False)
    if not isinstance(per_leader, bool):
        raise UserError(f"{path}: per_leader must be true or false")
    secrets_ = tuple(_key(path, k) for k in keys)
    ids = tuple(sorted(leaders.values()))
    if not per_leader:  # an older fleet: one key every leader signs with
        return RadioAuth(secrets_, ids, str(stop))
    # the robots hold each leader's keys, never the fleet's secret
    return RadioAuth((), ids, str(stop), tuple(tuple(leader_key(k, rid) for k in secrets_) for rid in ids))


def set_stop_policy(path: Path, stop: str) -> None:
    data = _read_private(path, "the robots' radio keys")
    data["stop"] = stop
    _write_secret(path, json.dumps(data, indent=1) + "\n")


def leader_key(secret: bytes, radio_id: int, per_leader: bool = True) -> bytes:
    """The key leader ``radio_id`` signs with under the fleet's radio secret: its own, derived
    with keyed BLAKE2b (the secret as the key, the leader's radio id in the message), so that no
    leader's key gives another's; ``per_leader`` False (an older fleet's robots.json): the secret
    itself, one key for every leader."""
    if not per_leader:
        return secret
    return hashlib.blake2b(DERIVE_LABEL + bytes((radio_id,)), key=secret, digest_size=p.RADIO_KEY_LEN).digest()


def _robots_data(directory: Path) -> tuple[Path, dict[str, object], tuple[bytes, ...], dict[str, int], bool]:
    """robots.json checked: its path, its data, the fleet's secrets (current, next), the leaders'
    radio ids, and whether each leader has a key of its own."""
    robots = directory / ROBOTS
    load_robot_auth(robots)  # checked: one line if it cannot serve
    data = _read_private(robots, "the robots' radio keys")
    leaders = {str(k): int(v) for k, v in data["leaders"].items()}  # type: ignore[attr-defined]
    secrets_ = tuple(_key(robots, k) for k in data["keys"])  # type: ignore[attr-defined]
    return robots, data, secrets_, leaders, data.get("per_leader") is True


UNREADABLE = b"?"  # a leader's file that cannot serve (Rotation.problems says why)


def _key_in(path: Path, problems: dict[Path, str]) -> bytes | None:
    """The key a leader's file holds (None: no file; UNREADABLE, with the reason in ``problems``)."""
    if not path.exists() and not path.is_symlink():
        return None
    try:
        return load_leader_key(path).key
    except UserError as exc:
        problems[path] = str(exc)
        return UNREADABLE


@dataclass(frozen=True)
class Rotation:
    """Where a rotation stands, read from the files themselves (nothing else is kept): the robots'
    keys (robots.json), and for each leader the key of its file in ``next/``, in the radio folder
    and in its bundle (None: no such file; bundles only where the bundle's folder exists)."""

    directory: Path
    keys: tuple[bytes, ...]
    leaders: dict[str, int]
    nexts: dict[str, bytes | None]
    files: dict[str, bytes | None]
    bundles: dict[str, bytes | None]
    problems: dict[Path, str]  # files that cannot serve: a step writes them afresh
    per_leader: bool = True  # each leader a key of its own (False: an older fleet's one key)

    def key_of(self, secret: bytes, name: str) -> bytes:
        """Leader ``name``'s key under the fleet's radio secret ``secret``."""
        return leader_key(secret, self.leaders[name], self.per_leader)

    def _holds(self, keys: dict[str, bytes | None], secret: bytes) -> list[str]:
        return [n for n in self.leaders if keys.get(n) == self.key_of(secret, n)]

    @property
    def next_dir(self) -> Path:
        return self.directory / NEXT

    def begin_interrupted(self) -> bool:
        """next/ holds a key the robots do not list: a --begin stopped before its last rename."""
        return len(self.keys) == 1 and any(k not in (None, UNREADABLE, self.key_of(self.keys[0], n))
                                           for n, k in self.nexts.items())

    def finish_pending(self) -> list[str]:
        """With one key: what still disagrees with it (a --finish stopped half way, or a copy left
        behind); empty when the folder agrees."""
        cur = self.keys[0]
        out = [f"next/{n}{SUFFIX}" for n, k in self.nexts.items() if k is not None]
        out += [f"{n}{SUFFIX}" for n in self.leaders if self.files[n] != self.key_of(cur, n)]
        out += [f"../{n}/{n}{SUFFIX}" for n, k in self.bundles.items() if k != self.key_of(cur, n)]
        return out

    def describe(self) -> str:
        """One paragraph for --status: the step the rotation is at, and what to run next."""
        text = self._describe()
        if self.problems:
            text += "; files that cannot serve: " + "; ".join(self.problems.values())
        return text

    def _describe(self) -> str:
        n_all = len(self.leaders)
        if len(self.keys) == 2:
            old, new = self.keys
            ready = self._holds(self.nexts, new)
            on_new = self._holds(self.files, new) + [f"{n}'s bundle" for n in self._holds(self.bundles, new)]
            missing = [n for n in self.leaders if n not in ready and self.files[n] != self.key_of(new, n)]
            text = (f"begun: the robots' record lists the current key and the next one; next/ holds {len(ready)} of"
                    f" {n_all} leaders' files")
            if missing:
                text += f" (missing or wrong: {', '.join(missing)}: run --begin again to write them)"
            if on_new:
                text += (f"; a --finish was interrupted: {', '.join(on_new)} already on the next key, the others"
                         " on the current one (the robots accept both): run --finish again")
            else:
                text += ("; next: provision the robots (they accept both keys), give each leader its file from next/"
                         " and restart it, then --finish")
            return text
        if self.begin_interrupted():
            return ("a --begin was interrupted: next/ holds a key the robots' record does not list (nothing was"
                    " deployed): run --begin again, it starts afresh")
        pending = self.finish_pending()
        if pending:
            return (f"a --finish was interrupted: the robots' record lists only the new key, and {', '.join(pending)}"
                    " still disagree: run --finish again")
        return (f"no rotation under way: the robots' record, the {n_all} leaders' files and their bundles' copies"
                " hold one key (--begin starts a rotation)")


def rotation_state(directory: Path) -> Rotation:
    """Where a rotation of ``directory`` (DIR/radio) stands (one UserError line if a file cannot
    serve)."""
    if not directory.is_dir():
        raise UserError(f"{directory}: not a folder (fleet-keys writes DIR/radio/)")
    _, _, keys, leaders, per_leader = _robots_data(directory)
    fleet_dir = directory.parent
    problems: dict[Path, str] = {}
    nexts = {n: _key_in(directory / NEXT / f"{n}{SUFFIX}", problems) for n in leaders}
    files = {n: _key_in(directory / f"{n}{SUFFIX}", problems) for n in leaders}
    bundles = {n: _key_in(fleet_dir / n / f"{n}{SUFFIX}", problems) for n in leaders if (fleet_dir / n).is_dir()}
    return Rotation(directory, keys, leaders, nexts, files, bundles, problems, per_leader)


class _Step:
    """One step's files: each written to a temporary name beside it first (synced, mode 0600),
    then all renamed in the order given. If any write fails, every temporary is removed and
    nothing has changed; the renames come last, robots.json's after the leaders' files, so a
    step stopped among them is finished by running it again (docs/follower-protocol.md)."""

    def __init__(self) -> None:
        self.files: list[tuple[Path, bytes]] = []

    def add(self, path: Path, text: str) -> None:
        self.files.append((path, text.encode()))

    def run(self, what: str) -> list[Path]:
        tmps: list[tuple[Path, Path]] = []
        path = Path("?")
        try:
            for path, data in self.files:
                if path.is_dir() and not path.is_symlink():
                    raise IsADirectoryError(21, "a folder is in its place")
                tmp = path.with_name(f".{path.name}.new")
                tmps.append((tmp, path))
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                with os.fdopen(fd, "wb") as fh:
                    fh.write(data)
                    fh.flush()
                    os.fsync(fh.fileno())
                os.chmod(tmp, 0o600)
        except OSError as exc:
            for tmp, _ in tmps:
                try:
                    tmp.unlink()
                except OSError:
                    pass
            raise UserError(f"{path}: cannot write ({exc.strerror or exc}); {what}: nothing changed, fix it and"
                            " run the same step again") from None
        try:
            for tmp, path in tmps:
                tmp.replace(path)
        except OSError as exc:
            raise UserError(f"{path}: cannot rename ({exc.strerror or exc}); {what} stopped half way: fix it and run"
                            " the same step again (it finishes what is left)") from None
        return [path for _, path in tmps]


def rotate(directory: Path, finish: bool) -> list[Path]:
    """Begin a rotation (a new key: the robots accept both, the leaders' next files are written to
    ``NEXT``/) or finish it (the robots accept only the new key; the next files replace the
    leaders' files and their bundles' copies). Every file of a step is written to a temporary name
    first and committed by renames, robots.json last: a step that stopped half way (an unwritable
    bundle, a full disk, a crash) is finished by running it again, or, for a --begin that never
    reached robots.json, started afresh. docs/follower-protocol.md, "Rotating the key"."""
    state = rotation_state(directory)
    robots, data, keys, leaders, per_leader = _robots_data(directory)
    nxt = directory / NEXT
    step = _Step()
    if not finish:
        if len(keys) == 2:
            new = keys[1]
            missing = [n for n in leaders if state.nexts[n] != leader_key(new, leaders[n], per_leader)
                       and state.files[n] != leader_key(new, leaders[n], per_leader)]
            if not missing:
                raise UserError(f"{robots}: a rotation is already under way; finish it first (--finish)")
            for n in missing:  # a begin whose next/ files went missing: written again, same key
                step.add(nxt / f"{n}{SUFFIX}", _leader_text(leaders[n], leader_key(new, leaders[n], per_leader)))
            _private_dir(nxt)
            return step.run("radio-rotate --begin")
        if state.finish_pending() and not state.begin_interrupted():
            raise UserError(f"{directory}: {state.describe()}")
        new = secrets.token_bytes(p.RADIO_KEY_LEN)
        _private_dir(nxt)
        for n, rid in leaders.items():
            step.add(nxt / f"{n}{SUFFIX}", _leader_text(rid, leader_key(new, rid, per_leader)))
        step.add(robots, json.dumps({**data, "keys": [keys[0].hex(), new.hex()]}, indent=1) + "\n")
        return step.run("radio-rotate --begin")
    if len(keys) == 2:
        cur = keys[1]  # every file is made from the robots' record: next/ is not read, only removed at the end
    else:
        cur = keys[0]
        if state.begin_interrupted():
            raise UserError(f"{directory}: {state.describe()}")
        if not state.finish_pending():
            raise UserError(f"{robots}: no rotation under way (--begin starts one; --status says where it stands)")
    for n, rid in leaders.items():
        if n in state.bundles:
            step.add(directory.parent / n / f"{n}{SUFFIX}", _leader_text(rid, leader_key(cur, rid, per_leader)))
    for n, rid in leaders.items():
        step.add(directory / f"{n}{SUFFIX}", _leader_text(rid, leader_key(cur, rid, per_leader)))
    step.add(robots, json.dumps({**data, "keys": [cur.hex()]}, indent=1) + "\n")
    written = step.run("radio-rotate --finish")
    try:  # the robots' record is the new one now: next/ is only a leftover
        for n in leaders:
            (nxt / f"{n}{SUFFIX}").unlink(missing_ok=True)
        if nxt.is_dir() and not any(nxt.iterdir()):
            nxt.rmdir()
    except OSError as exc:
        raise UserError(f"{nxt}: cannot remove ({exc.strerror or exc}); the rotation is finished otherwise: run"
                        " --finish again to clear it") from None
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
    """What a robot's flash holds (firmware/host_sim.c reads it): with a key per leader "OFR4", n
    keys, n leaders, then each leader's id and its n keys (current, next), the STOP policy (0
    anyone, 1 authenticated), CRC-16 of all before it; one key for the fleet (an older
    robots.json): "OFR3", n keys, the keys, n leaders, their ids, the STOP policy, CRC-16."""
    if auth.leader_keys:
        body = RECORD_MAGIC_PER_LEADER + bytes((len(auth.leader_keys[0]), len(auth.leaders))) + b"".join(
            bytes((rid,)) + b"".join(keys) for rid, keys in zip(auth.leaders, auth.leader_keys)) \
            + bytes((STOP_POLICIES.index(auth.stop),))
        return body + struct.pack("<H", p.crc16(body))
    body = RECORD_MAGIC + bytes((len(auth.keys),)) + b"".join(auth.keys) + bytes((len(auth.leaders),)) \
        + bytes(auth.leaders) + bytes((STOP_POLICIES.index(auth.stop),))
    return body + struct.pack("<H", p.crc16(body))


def c_header(auth: RadioAuth) -> str:
    """A C header defining ``OF_RADIO_AUTH`` (an of_radio_auth) for firmware/omni_follower.h: each
    leader's keys (``per_leader``), or one key for the fleet from an older robots.json."""
    def arr(b: bytes) -> str:
        return "{" + ", ".join(f"0x{x:02x}" for x in b) + "}"

    stop = "OF_STOP_ANYONE" if auth.stop == STOP_ANYONE else "OF_STOP_AUTHENTICATED"
    head = ("/* The fleet's radio keys for the robots: SECRET, keep out of version control. */\n"
            "#include \"omni_follower.h\"\n")
    if auth.leader_keys:
        per = ",\n     ".join("{" + ", ".join(arr(k) for k in keys) + "}" for keys in auth.leader_keys)
        return (head + "static const of_radio_auth OF_RADIO_AUTH = {\n"
                f"    .n_keys = {len(auth.leader_keys[0])}u,\n    .leaders = {arr(bytes(auth.leaders))},\n"
                f"    .n_leaders = {len(auth.leaders)}u,\n    .stop_policy = {stop},\n    .per_leader = 1u,\n"
                f"    .leader_keys = {{{per}}}\n}};\n")
    keys = ",\n     ".join(arr(k) for k in auth.keys)
    return (head + f"static const of_radio_auth OF_RADIO_AUTH = {{\n    .keys = {{{keys}}},\n"
            f"    .n_keys = {len(auth.keys)}u,\n    .leaders = {arr(bytes(auth.leaders))},\n"
            f"    .n_leaders = {len(auth.leaders)}u,\n    .stop_policy = {stop}\n}};\n")


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
