"""A fleet no one can hijack (docs/fleet-protocol.md, "Security"): `fleet-keys`, then an arena
and two leaders with `--keys`, attacked by a plain Zenoh session and by one holding another
leader's certificate, each written from the document as a third party would write it."""

from __future__ import annotations

import datetime as dt
import json
import os
import subprocess
import threading
import time
from pathlib import Path

import pytest

from app.fleet.bridge import loopback_endpoint
from app.fleet.security import load_fleet_keys

from tests.helpers import LEADER_PROCESS, fleet_session, interrupt, main_cli, spawn_cli, wait_for

zenoh = pytest.importorskip("zenoh")

FLEET = "three_teams"
BASE = f"omniformation/{FLEET}"


def tls_endpoint() -> str:
    return "tls/" + loopback_endpoint().split("/", 1)[1]


def make_keys(directory: Path) -> Path:
    r = main_cli("fleet-keys", str(directory), "--fleet", FLEET, "--leaders", "L1,L2,L3")
    assert r.returncode == 0, r.stderr
    return directory


def test_fleet_keys_makes_a_ca_and_one_certificate_per_identity(tmp_path):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    keys = make_keys(tmp_path / "keys")
    idents = ("arena", "page", "L1", "L2", "L3")
    assert sorted(p.name for p in keys.iterdir()) == sorted(["ca", "radio", *idents])  # radio/: test_radio_keys
    assert sorted(p.name for p in (keys / "ca").iterdir()) == ["ca.key", "ca.pem"]
    for ident in idents:  # one bundle per identity, to copy whole: nothing of another's in it
        radio = [f"{ident}.radio"] if ident.startswith("L") else []  # a leader's own radio key and id
        assert sorted(p.name for p in (keys / ident).iterdir()) == sorted(["ca.pem", "fleet.json", f"{ident}.pem",
                                                                           f"{ident}.key", *radio])
    for p in keys.rglob("*.key"):
        assert (p.stat().st_mode & 0o777) == 0o600, p
    for d in keys.iterdir():
        assert (d.stat().st_mode & 0o777) == 0o700, d
    for ident in idents:
        cert = x509.load_pem_x509_certificate((keys / ident / f"{ident}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == ident
        assert load_fleet_keys(keys / ident, ident, FLEET).identity == ident
    before = (keys / "L1" / "L1.pem").read_bytes()
    again = main_cli("fleet-keys", str(keys), "--fleet", FLEET, "--leaders", "L1,L2,L3")
    assert again.returncode == 2 and "exists; fleet-keys writes over keys only with --overwrite" in again.stderr
    assert len(again.stderr.strip().splitlines()) == 1 and (keys / "L1" / "L1.pem").read_bytes() == before
    assert main_cli("fleet-keys", str(keys), "--fleet", FLEET, "--leaders", "L1,L2", "--overwrite").returncode == 0
    assert (keys / "L1" / "L1.pem").read_bytes() != before
    for args, words in ((["--leaders", "L1,L1"], "'L1' twice"), (["--leaders", "arena"], "taken by the arena"),
                        (["--leaders", "L 1"], "1 to 32 characters"), (["--leaders", "L1", "--days", "0"], "--days")):
        r = main_cli("fleet-keys", str(tmp_path / "other"), "--fleet", FLEET, *args)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)


def _expired_certificate(keys: Path, identity: str, ca_dir: Path) -> None:
    """Re-issue ``identity``'s certificate (in its bundle ``keys``) from the fleet's CA (the
    operator's ``ca_dir``), valid until yesterday."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.x509.oid import NameOID

    ca = x509.load_pem_x509_certificate((ca_dir / "ca.pem").read_bytes())
    ca_key = serialization.load_pem_private_key((ca_dir / "ca.key").read_bytes(), password=None)
    key = serialization.load_pem_private_key((keys / f"{identity}.key").read_bytes(), password=None)
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(x509.Name([
        x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"omniformation fleet {FLEET}"),
        x509.NameAttribute(NameOID.COMMON_NAME, identity)])).issuer_name(ca.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(days=30))
        .not_valid_after(now - dt.timedelta(days=1)).sign(ca_key, hashes.SHA256()))
    (keys / f"{identity}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def test_bad_keys_and_open_endpoints_are_refused_in_one_line(tmp_path):
    keys = make_keys(tmp_path / "keys")
    other = tmp_path / "other"
    assert main_cli("fleet-keys", str(other), "--fleet", "elsewhere", "--leaders", "L1").returncode == 0
    ep = tls_endpoint()

    def arena(keys_dir: Path, *more: str) -> tuple[int, str]:
        r = main_cli("arena", FLEET, "--keys", str(keys_dir), "--zenoh-listen", ep, "--minutes", "0.01", *more)
        return r.returncode, r.stderr

    def broken(name: str, change) -> Path:
        d = tmp_path / name
        d.mkdir(mode=0o700)
        for p in (keys / "arena").iterdir():
            (d / p.name).write_bytes(p.read_bytes())
            os.chmod(d / p.name, p.stat().st_mode & 0o777)
        change(d)
        return d

    cases = [
        (broken("missing", lambda d: (d / "arena.key").unlink()), "arena.key: missing"),
        (broken("readable", lambda d: os.chmod(d / "arena.key", 0o644)), "arena.key: readable by others (mode 0644)"),
        (broken("garbled", lambda d: (d / "arena.pem").write_text("not a certificate")), "arena.pem: not a PEM certificate"),
        (broken("foreign", lambda d: (d / "arena.pem").write_bytes((other / "page" / "page.pem").read_bytes())),
         "arena.pem: not signed by this fleet's CA"),
        (broken("swapped", lambda d: (d / "arena.pem").write_bytes((keys / "page" / "page.pem").read_bytes())),
         "arena.pem: made for 'page', not for 'arena'"),
        (broken("wrongkey", lambda d: (d / "arena.key").write_bytes((keys / "page" / "page.key").read_bytes())),
         "arena.key: not the key of"),
        (broken("expired", lambda d: _expired_certificate(d, "arena", keys / "ca")), "arena.pem: expired on"),
        (other / "arena", "fleet.json: keys of fleet 'elsewhere', not of 'three_teams'"),
        (tmp_path / "nowhere", "not a directory"),
    ]
    for d, words in cases:
        rc, err = arena(d)
        assert rc == 2 and words in err and len(err.strip().splitlines()) == 1, (d.name, err)
    # endpoints: with keys tls/ only; without keys loopback only; with keys a leader does not listen
    for args, words in ((["arena", FLEET, "--keys", str(keys / "arena"), "--zenoh-listen", "tcp/127.0.0.1:7447"],
                         "with --keys every endpoint is tls/HOST:PORT"),
                        (["arena", FLEET, "--zenoh-listen", "tcp/192.168.1.5:7447"], "without --keys the bus stays on"),
                        (["fleet", "--fleet", FLEET, "--zenoh-connect", "tcp/10.0.0.2:7447"], "without --keys"),
                        (["arena", FLEET, "--zenoh-listen", ep], "tls/ needs the fleet's keys"),
                        (["run", "--arena", FLEET, "--leader-id", "L1", "--keys", str(keys / "L1"), "--zenoh-listen", ep,
                          "--no-record", "--port", "0"], "with --keys only the fleet's hubs"),
                        (["run", "--arena", FLEET, "--leader-id", "L1", "--keys", str(other / "L1"), "--zenoh-connect", ep,
                          "--no-record", "--port", "0"], "keys of fleet 'elsewhere'")):
        r = main_cli(*args)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)


def listening_ports(pid: int) -> set[int]:
    """The TCP ports process ``pid`` and its children (the page's process) listen on (their sockets
    matched in /proc/net/tcp{,6})."""
    inodes = set()
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    for proc in (pid, *map(int, children)):
        for fd in Path(f"/proc/{proc}/fd").iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                ports.add(int(f[1].rsplit(":", 1)[1], 16))
    return ports


class Heard:
    """Everything a session hears of the fleet, and the newest truth."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.samples: list[tuple[str, bytes]] = []
        self.truth: dict | None = None
        self.truths: list[dict] = []
        self.states: dict[str, dict] = {}
        self.events: list[dict] = []
        self.sub = session.declare_subscriber(f"{BASE}/**", self._on)

    def _on(self, s) -> None:
        key, data = str(s.key_expr), s.payload.to_bytes()
        with self.lock:
            self.samples.append((key, data))
            if key.endswith("/arena/truth"):
                self.truth = json.loads(data)
                self.truths.append(self.truth)
            elif key.endswith("/state"):
                msg = json.loads(data)
                if isinstance(msg, dict) and "leader_id" in msg:
                    self.states[key.split("/")[-2]] = msg
            elif key.endswith("/events"):
                self.events.append(json.loads(data))


def test_with_keys_no_one_without_a_certificate_or_with_another_leaders_can_take_over(tmp_path):
    keys = make_keys(tmp_path / "keys")
    ep = tls_endpoint()
    summary = tmp_path / "arena.json"
    arena = spawn_cli("arena", FLEET, "--keys", str(keys / "arena"), "--zenoh-listen", ep, "--status-every", "0",
                   "--summary", str(summary))
    procs: dict[str, subprocess.Popen] = {}
    sessions: list[zenoh.Session] = []
    try:
        assert arena.stdout is not None and "arena three_teams" in arena.stdout.readline()
        page = fleet_session(keys / "page", "page", ep)  # the operator's side: hears everything, may STOP
        sessions.append(page)
        heard = Heard(page)
        for leader in ("L1", "L2"):
            procs[leader] = spawn_cli("run", LEADER_PROCESS, "--arena", FLEET, "--leader-id", leader, "--keys", str(keys / leader),
                                   "--zenoh-connect", ep, "--port", "0", "--no-record", "--feedback", "truth")
        wait_for(lambda: heard.truth is not None and heard.truth["alive"] == ["L1", "L2"]
                 and {"L1", "L2"} <= set(heard.states), 60, "L1 and L2 alive, their states heard")
        owners = list(heard.truth["owners"])
        # a leader told only where to connect listens on nothing but its own page (no implicit Zenoh
        # listener): the page's gate, and the viser server behind it on a loopback port of its own
        # (both in the page's process, the leader's child)
        out = procs["L2"].stdout
        assert out is not None
        page_port = next(int(line.split("http://127.0.0.1:")[1].split("/")[0]) for line in iter(out.readline, "")
                         if "dashboard at http://127.0.0.1:" in line)
        ports = listening_ports(procs["L2"].pid)
        assert page_port in ports and len(ports) == 2, (ports, page_port)

        # 1. no certificate: a plain TCP session to the same port hears nothing and changes nothing
        plain = fleet_session(None, None, "tcp/" + ep.split("/", 1)[1])
        sessions.append(plain)
        plain_heard = Heard(plain)
        for _ in range(30):
            plain.put(f"{BASE}/all/cmd", json.dumps({"set": {"stop": True}}))
            plain.put(f"{BASE}/leader/L1/state", b"{}")
            time.sleep(0.03)
        time.sleep(1.0)
        # (it hears its own puts, locally: nothing else)
        assert plain_heard.truth is None and plain_heard.states == {} and plain_heard.events == []
        assert {k for k, _ in plain_heard.samples} == {f"{BASE}/all/cmd", f"{BASE}/leader/L1/state"}
        assert not heard.states["L1"]["stopped"]

        # ... nor with a certificate of another fleet, or an expired one of this fleet: the handshake fails
        other = tmp_path / "other"
        assert main_cli("fleet-keys", str(other), "--fleet", FLEET, "--leaders", "L1,L2,L3").returncode == 0
        stale = tmp_path / "stale"
        stale.mkdir()
        for f in (keys / "L1").iterdir():
            (stale / f.name).write_bytes(f.read_bytes())
        _expired_certificate(stale, "L1", keys / "ca")
        for d in (other / "L1", stale):
            with pytest.raises(zenoh.ZError):
                sessions.append(fleet_session(d, "L1", ep))

        # 2. with L2's certificate, a third party written from the document
        mallory = fleet_session(keys / "L2", "L2", ep)
        sessions.append(mallory)
        mallory_heard = Heard(mallory)  # a member hears the fleet (reading is every member's)
        wait_for(lambda: mallory_heard.truth is not None, 20, "the truth reaching a member")
        # (a) drive L1's robot R1 at 0.25 m/s for 3 s, each drive naming the newest truth
        r1 = owners.index("L1")
        with heard.lock:
            first = len(heard.truths)
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            tick = mallory_heard.truth["tick"]
            for key, twist in (("drive/L1", 0.25), ("drive/L2", 0.0)):  # as L1; as itself, for L1's robot
                mallory.put(f"{BASE}/arena/{key}", json.dumps({"tick": tick, "truth_tick": tick, "twist": [twist, 0.0],
                                                                 "commands": {f"R{r1 + 1}": [0.25, 0.0]}}))
            time.sleep(1 / 30)
        with heard.lock:
            window = heard.truths[first:]
        spoofed = sum(abs(t["velocities"][r1][0] - 0.25) < 0.03 for t in window)
        assert window and spoofed / len(window) < 0.10, (spoofed, len(window))
        assert spoofed == 0
        # (b) a forged state under L1's id, with and without the twin fields: L1 carries on
        for fake in ({}, {"leader_id": "L1", "instance": "00000000", "started": 0.0}):
            mallory.put(f"{BASE}/leader/L1/state", json.dumps(fake))
        # (c) a STOP or a gain for L1 and for the whole fleet: the commands are the page's
        mallory.put(f"{BASE}/leader/L1/cmd", json.dumps({"set": {"stop": True}, "from": "mallory"}))
        mallory.put(f"{BASE}/all/cmd", json.dumps({"set": {"stop": True}, "from": "mallory"}))
        # (d) L1's token, and L3's (a leader that is not running)
        tokens = [mallory.liveliness().declare_token(f"{BASE}/alive/{x}") for x in ("L1", "L3")]
        # (e) a claim for L1, and one under its own name for L1; a handover (the page's)
        claim_l1 = list(mallory.get(f"{BASE}/arena/claim/L1", payload=json.dumps({"robot": "R7"}), timeout=3.0))
        claim_as = [json.loads(r.ok.payload.to_bytes()) for r in mallory.get(
            f"{BASE}/arena/claim/L2", payload=json.dumps({"leader": "L1", "robot": "R7"}), timeout=3.0) if r.ok]
        handover = list(mallory.get(f"{BASE}/arena/handover", payload=json.dumps({"robot": "R1", "to": "L2",
                                                                                 "from": "mallory"}), timeout=3.0))
        assert claim_l1 == [] and handover == [], (claim_l1, handover)
        assert claim_as and not claim_as[0]["granted"] and "is L2's, not 'L1'" in claim_as[0]["why"], claim_as
        t_after = heard.truth["t"]
        wait_for(lambda: heard.truth["t"] >= t_after + 2.0, 30, "2 s more of the arena")
        assert procs["L1"].poll() is None, procs["L1"].stderr.read() if procs["L1"].stderr else ""
        assert not heard.states["L1"]["stopped"] and not heard.states["L2"]["stopped"]
        assert heard.truth["alive"] == ["L1", "L2"] and heard.truth["owners"] == owners
        assert not any(e.get("kind") == "twin" for e in heard.events), heard.events
        # what reached the arena was refused and counted (shown on the fleet page): the drives under its
        # own name for L1's robot (conflicts) and the claim under its own name for L1
        assert heard.truth["refused"]["claims"] == 1 and heard.truth["refused"]["conflicts"] > 0, heard.truth["refused"]

        # the operator's identity may: a STOP from the fleet page (its own process, the page's certificate)
        # stops L1, and the page hears and records every leader
        fleet_page = spawn_cli("fleet", "--fleet", FLEET, "--keys", str(keys / "page"), "--zenoh-connect", ep, "--port", "0",
                            "--record", str(tmp_path / "fleet.mcap"))
        procs["page"] = fleet_page
        assert fleet_page.stdout is not None and "fleet three_teams at http" in fleet_page.stdout.readline()
        # its token says its subscribers are declared: the second below is one it records
        wait_for(lambda: any(r.ok is not None for r in page.liveliness().get(f"{BASE}/page/alive", timeout=1.0)),
                 30, "the fleet page's token")
        page.put(f"{BASE}/leader/L1/cmd", json.dumps({"set": {"stop": True}, "from": "test"}))
        wait_for(lambda: heard.states["L1"]["stopped"], 20, "L1 stopped by the page")
        time.sleep(1.0)  # the page records a second of the fleet
        # L1 dies while the third party still holds a token under its name: the arena sees L1 lost at once
        procs["L1"].kill()
        wait_for(lambda: "L1" in heard.truth["lost"] and heard.truth["alive"] == ["L2"], 20, "L1 lost")
        for tok in tokens:
            tok.undeclare()
    finally:
        for s in sessions:
            s.close()
        interrupt(*procs.values())
        interrupt(arena)
    from mcap.reader import make_reader

    with open(tmp_path / "fleet.mcap", "rb") as f:
        topics = [channel.topic for _, channel, _ in make_reader(f).iter_messages()]
    assert topics.count("/fleet/L1/state") > 10 and topics.count("/fleet/L2/state") > 10, set(topics)
    counts = json.loads(summary.read_text())
    # no token under a name outside the fleet, no handover reached the arena (the page made none)
    assert counts["strangers"] == 0 and counts["handovers_refused"] == 0, counts
