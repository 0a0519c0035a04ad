"""The fleet's keys: who may say what on the bus (docs/fleet-protocol.md, "Security").

`omniformation fleet-keys DIR --fleet NAME --leaders L1,L2` makes a fleet certificate authority
and one certificate per identity (``arena``, ``page`` and every leader id; the certificate's
common name is the identity). A process started with ``--keys DIR`` then speaks only mutual TLS
(Zenoh's own ``tls/`` transport: both ends show a certificate of the fleet's CA) and runs
Zenoh's access control (the ``access_control`` section of its session config): a message that
comes in from an identity is let through only if that identity owns the key it writes.

The certificates and keys are made with the ``cryptography`` package (no home-made crypto);
the checks here run before anything joins the bus, so a wrong, missing, foreign or expired
file is one line naming the file and the reason.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.keys import root

ARENA = "arena"
PAGE = "page"
HUBS = (ARENA, PAGE)  # the identities that may listen; of them only the arena writes what it forwards
ROS2 = "ros2"  # fleet-keys --ros2: the ROS 2 machines' identity (their router, a ROS base); nothing on the fleet's bus
ROSTER = "fleet.json"
ROS2_ROUTER = "router.json5"  # fleet-keys --ros2: the ROS 2 machines' router config, in DIR/ros2/ (docs/ros2.md)
ROS2_CONTROL_KEYS = ("*/omniformation/stop/**", "*/omniformation/goal/**")  # every domain, every type
CA_CERT = "ca.pem"
CA_KEY = "ca.key"  # only fleet-keys needs it (a new identity): keep it off the robots
CA_DIR = "ca"  # DIR/ca/: the CA's key and certificate, for the operator's machine only
# files fleet-keys may add to an identity's bundle beside its own key (e.g. a key the radio
# shares): the only other secrets `--keys` lets lie in a bundle
BUNDLE_EXTRAS: tuple[str, ...] = ()
DEFAULT_DAYS = 365
MAX_DAYS = 3650

# what a leader may write (its token and its claims apart); everyone may read the fleet's keys
LEADER_WRITES = ("leader/{id}/state", "leader/{id}/events", "arena/drive/{id}")
# what the page may write: the operator's commands and its own token; its handovers are queries
PAGE_WRITES = ("leader/*/cmd", "all/cmd")
PAGE_TOKEN = "page/alive"
READS = ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_query")
EVERY_MESSAGE = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                 "declare_liveliness_subscriber", "liveliness_query")


def organization(fleet: str) -> str:
    return f"omniformation fleet {fleet}"


@dataclass(frozen=True)
class Roster:
    """Who is in the fleet (DIR/fleet.json, written by fleet-keys with the certificates)."""

    fleet: str
    leaders: tuple[str, ...]
    ros2: bool = False  # fleet-keys --ros2 made a bundle for the ROS 2 machines too (docs/ros2.md)

    @property
    def identities(self) -> tuple[str, ...]:
        return (*HUBS, *self.leaders)

    @property
    def bundles(self) -> tuple[str, ...]:
        """Every identity with a bundle: the fleet's, and ``ros2`` (no member of the fleet's bus:
        its access control lets it write nothing there) when made."""
        return (*self.identities, *((ROS2,) if self.ros2 else ()))


@dataclass(frozen=True)
class FleetKeys:
    """One identity's files, checked: the fleet's CA, its certificate and key, the roster."""

    identity: str
    ca: Path
    cert: Path
    key: Path
    roster: Roster

    @property
    def is_hub(self) -> bool:
        return self.identity in HUBS


def _identity_ok(name: str) -> bool:
    """An identity's name: a letter, then up to 31 letters, digits, _ or - (a folder, a file stem
    and a certificate's common name on every system)."""
    import re

    return re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,31}", name) is not None


# names the key folder's layout uses itself (DIR/ca/, DIR/radio/, DIR/radio/next/, the CA's
# ca.pem and ca.key, fleet.json, robots.json): a leader so named would write over them or be
# read as them. Compared without case: on a case-blind file system "CA" is "ca".
LAYOUT_NAMES = ("ca", "radio", "next", "fleet", "robots")


def parse_leaders(text: str) -> tuple[str, ...]:
    """``L1,L2,...``: distinct leader ids (``[A-Za-z][A-Za-z0-9_-]{0,31}``), none of them a hub's
    name nor one of the key folder's own names (ValueError says which)."""
    ids = tuple(s.strip() for s in text.split(",") if s.strip())
    if not ids:
        raise ValueError("--leaders: give at least one leader id, e.g. L1,L2,L3")
    for i in ids:
        if not _identity_ok(i):
            raise ValueError(f"--leaders: {i!r}: 1 to 32 characters, a letter first, then letters, digits, _ or -"
                             " (e.g. L1)")
        if i in (*HUBS, ROS2):
            raise ValueError(f"--leaders: {i!r} is taken by the {i} itself (a leader needs another id)")
        if i.lower() in (*LAYOUT_NAMES, *HUBS, ROS2):
            raise ValueError(f"--leaders: {i!r} is a name the key folder uses itself ({', '.join(LAYOUT_NAMES)},"
                             f" {', '.join(HUBS)}, {ROS2}): give the leader another id")
    folded = [i.lower() for i in ids]
    if len(set(folded)) != len(ids):
        dup = next(i for i in ids if folded.count(i.lower()) > 1)
        raise ValueError(f"--leaders: {dup!r} twice (every leader has its own certificate; case does not tell"
                         " two apart on every file system)")
    return ids


# -- making keys ---------------------------------------------------------------------------------
def bundle_files(identity: str) -> tuple[str, ...]:
    """What DIR/<identity>/ holds: all that identity's process needs, nothing of another's (the
    ROS 2 machines' bundle also their router's config)."""
    return (CA_CERT, ROSTER, f"{identity}.pem", f"{identity}.key", *((ROS2_ROUTER,) if identity == ROS2 else ()))


def make_fleet_keys(directory: Path, fleet: str, leaders: tuple[str, ...], *, overwrite: bool = False,
                    days: int = DEFAULT_DAYS, now: dt.datetime | None = None, ros2: bool = False,
                    ros2_control_by: tuple[str, ...] = (ROS2,)) -> list[Path]:
    """Writes DIR/ca/ (ca.key and ca.pem: the operator's, never given to a process) and one
    bundle per identity, DIR/<identity>/ (ca.pem, fleet.json, <identity>.pem and .key: what
    ``--keys DIR/<identity>`` reads) for ``arena``, ``page`` and every leader; folders mode
    0700, keys 0600. Refuses (FileExistsError naming the first file) to write over any of them
    unless ``overwrite``. ``ros2``: a bundle DIR/ros2/ for the ROS 2 machines too, with their
    router's config (:func:`ros2_router_config`; ``ros2_control_by`` may STOP and set goals).
    Returns the files written."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    roster = Roster(fleet, leaders, ros2)
    names = [f"{CA_DIR}/{CA_KEY}", f"{CA_DIR}/{CA_CERT}"] + [f"{i}/{n}" for i in roster.bundles
                                                             for n in bundle_files(i)]
    if not overwrite:
        for n in names:
            if (directory / n).exists():
                raise FileExistsError(f"{directory / n}: exists; fleet-keys writes over keys only with --overwrite")
    for sub_dir in (CA_DIR, *roster.bundles):
        (directory / sub_dir).mkdir(parents=True, exist_ok=True)
        os.chmod(directory / sub_dir, 0o700)  # a bundle nobody else may read or change
    now = now or dt.datetime.now(dt.UTC)
    start, end = now - dt.timedelta(minutes=5), now + dt.timedelta(days=days)
    org = x509.NameAttribute(NameOID.ORGANIZATION_NAME, organization(fleet))
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([org, x509.NameAttribute(NameOID.COMMON_NAME, f"{fleet} fleet CA")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                       data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                       crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
          .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
          .sign(ca_key, hashes.SHA256()))
    written: list[Path] = []

    def write(name: str, data: bytes, secret: bool = False) -> None:
        path = directory / name
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if secret else 0o644)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(path, 0o600 if secret else 0o644)  # also when it existed with another mode
        written.append(path)

    def pem_key(key: Any) -> bytes:
        return bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))

    ca_pem = ca.public_bytes(serialization.Encoding.PEM)
    roster_json = (json.dumps({"fleet": fleet, "leaders": list(leaders), **({"ros2": True} if ros2 else {})}, indent=1)
                   + "\n").encode()
    write(f"{CA_DIR}/{CA_KEY}", pem_key(ca_key), secret=True)
    write(f"{CA_DIR}/{CA_CERT}", ca_pem)
    for identity in roster.bundles:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([org, x509.NameAttribute(NameOID.COMMON_NAME, identity)]))
                .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
                .not_valid_before(start).not_valid_after(end)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost"),
                                                            x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                               critical=False)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                               critical=False)
                .sign(ca_key, hashes.SHA256()))
        write(f"{identity}/{CA_CERT}", ca_pem)
        write(f"{identity}/{ROSTER}", roster_json)
        write(f"{identity}/{identity}.pem", cert.public_bytes(serialization.Encoding.PEM))
        write(f"{identity}/{identity}.key", pem_key(key), secret=True)
    if ros2:
        config = ros2_router_config(roster, ros2_control_by)
        write(f"{ROS2}/{ROS2_ROUTER}", (json.dumps(config, indent=1) + "\n").encode())
    return written


# -- checking keys -------------------------------------------------------------------------------
class KeyFileError(ValueError):
    """A key file that cannot serve: one line naming the file and the reason."""


def _read(path: Path, what: str) -> bytes:
    """A regular file of at most 64 KiB (app.files.read_regular: no FIFO, device or folder)."""
    from app.files import UserError, read_regular

    try:
        return read_regular(path, what)
    except FileNotFoundError:
        raise KeyFileError(f"{path}: missing ({what}; `omniformation fleet-keys` writes it)") from None
    except UserError as exc:
        raise KeyFileError(str(exc)) from None


def _parse(path: Path, data: bytes, loader: Any, what: str) -> Any:
    try:
        return loader(data)
    except (ValueError, TypeError, KeyError, UnicodeDecodeError, RecursionError):  # RecursionError: nested JSON
        raise KeyFileError(f"{path}: {what}") from None


def _roster(directory: Path) -> Roster:
    path = directory / ROSTER

    def parse(data: bytes) -> Roster:
        d = json.loads(data)
        fleet, leaders = d["fleet"], d["leaders"]  # KeyError / TypeError: not a roster
        ros2 = d.get("ros2", False)
        if not isinstance(fleet, str) or not isinstance(leaders, list) or not all(isinstance(x, str) for x in leaders) \
                or not isinstance(ros2, bool):
            raise TypeError
        return Roster(fleet, parse_leaders(",".join(leaders)), ros2)

    roster: Roster = _parse(path, _read(path, "the fleet's roster"), parse,
                            'not a fleet roster ({"fleet": NAME, "leaders": [ID, ...]})')
    return roster


def _not_writable_by_others(path: Path) -> None:
    if not path.exists():
        return  # missing: said when it is read
    mode = path.stat().st_mode
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise KeyFileError(f"{path}: others may write it (mode {stat.S_IMODE(mode):04o}): anyone on this machine could"
                           f" swap the fleet's keys; `chmod go-w {path}`")


def _check_bundle(directory: Path, identity: str) -> None:
    """``--keys DIR`` is one identity's bundle (fleet-keys' DIR/<identity>/), nothing more: no
    one else may write the folder, and it holds neither the CA's private key nor another
    identity's (whoever can read such a folder can be anyone)."""
    _not_writable_by_others(directory)
    own = f"{identity}.key"
    for entry in sorted(directory.iterdir()):
        if entry.is_dir() and (entry.name == CA_DIR or (entry / f"{entry.name}.key").exists()):
            raise KeyFileError(f"--keys {directory}: fleet-keys' whole folder (the CA's key and every identity's"
                               f" bundle): give this process its own bundle only, --keys {directory / identity}")
        if entry.name == CA_KEY:
            raise KeyFileError(f"{entry}: the fleet CA's private key beside {identity}'s: whoever reads this folder can"
                               " make any identity; keep it on the operator's machine, apart")
        if entry.name == own or entry.name in BUNDLE_EXTRAS or not entry.is_file():
            continue
        try:
            with entry.open("rb") as f:
                head = f.read(64 * 1024)
        except OSError:
            continue
        if entry.suffix == ".key" or b"PRIVATE KEY-----" in head:
            raise KeyFileError(f"{entry}: another private key beside {identity}'s ({own}): each machine holds its"
                               " own identity's key only; move it away")


def load_fleet_keys(directory: Path, identity: str, fleet: str, *, now: dt.datetime | None = None,
                    ros2: bool = False) -> FleetKeys:
    """The files ``identity`` joins ``fleet`` with, checked: present and readable, the key not
    readable by others, the certificate this fleet CA's, named ``identity``, in date and made
    for this key. KeyFileError (a ValueError) names the file and the reason. ``ros2``: for a ROS 2
    session, where the ``ros2`` bundle serves too (on the fleet's bus it is nobody)."""
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives import serialization
    from cryptography.x509.oid import NameOID

    if not directory.is_dir():
        raise KeyFileError(f"--keys {directory}: not a directory (`omniformation fleet-keys {directory} ...` makes one)")
    _check_bundle(directory, identity)
    roster = _roster(directory)
    if roster.fleet != fleet:
        raise KeyFileError(f"{directory / ROSTER}: keys of fleet {roster.fleet!r}, not of {fleet!r}")
    members = roster.bundles if ros2 else roster.identities
    if identity not in members:
        raise KeyFileError(f"{directory / ROSTER}: {identity!r} is not in fleet {fleet} (its identities:"
                        f" {', '.join(members)}; fleet-keys makes the keys of a new one)")
    now = now or dt.datetime.now(dt.UTC)
    ca_path, cert_path, key_path = directory / CA_CERT, directory / f"{identity}.pem", directory / f"{identity}.key"
    ca = _parse(ca_path, _read(ca_path, "the fleet's CA certificate"), x509.load_pem_x509_certificate,
                "not a PEM certificate")
    cert = _parse(cert_path, _read(cert_path, f"{identity}'s certificate"), x509.load_pem_x509_certificate,
                  "not a PEM certificate")
    for path in (ca_path, cert_path, directory / ROSTER):
        _not_writable_by_others(path)
    mode = key_path.stat().st_mode if key_path.exists() else 0
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise KeyFileError(f"{key_path}: readable by others (mode {stat.S_IMODE(mode):04o}); `chmod 600 {key_path}`")
    key = _parse(key_path, _read(key_path, f"{identity}'s private key"),
                 lambda data: serialization.load_pem_private_key(data, password=None),
                 "not an unencrypted PEM private key")

    def org(c: Any) -> str:
        attrs = c.subject.get_attributes_for_oid(NameOID.ORGANIZATION_NAME)
        return str(attrs[0].value) if attrs else "?"

    if org(ca) != organization(fleet):
        raise KeyFileError(f"{ca_path}: the CA of {org(ca)!r}, not of {organization(fleet)!r}")
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        raise KeyFileError(f"{cert_path}: not signed by this fleet's CA ({ca_path}): a certificate of another"
                        " fleet or of an older CA") from None
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    cn = str(cns[0].value) if cns else ""
    if cn != identity:
        raise KeyFileError(f"{cert_path}: made for {cn!r}, not for {identity!r}")
    for c, path in ((ca, ca_path), (cert, cert_path)):
        if c.not_valid_after_utc < now:
            raise KeyFileError(f"{path}: expired on {c.not_valid_after_utc:%Y-%m-%d %H:%M} UTC (make new keys with"
                            " fleet-keys --overwrite)")
        if c.not_valid_before_utc > now:
            raise KeyFileError(f"{path}: not valid before {c.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (is this"
                            " machine's clock right?)")
    pub = serialization.PublicFormat.SubjectPublicKeyInfo
    if key.public_key().public_bytes(serialization.Encoding.DER, pub) != \
            cert.public_key().public_bytes(serialization.Encoding.DER, pub):
        raise KeyFileError(f"{key_path}: not the key of {cert_path}")
    return FleetKeys(identity, ca_path.resolve(), cert_path.resolve(), key_path.resolve(), roster)


# -- the session's config ------------------------------------------------------------------------
def tls_config(keys: FleetKeys) -> dict[str, Any]:
    """Mutual TLS: both ends show a certificate of the fleet's CA. Names are not checked against
    addresses (robots move between networks): who is at the other end is its certificate's
    common name, and the access control below judges by that."""
    return {"root_ca_certificate": str(keys.ca), "enable_mtls": True,
            "listen_private_key": str(keys.key), "listen_certificate": str(keys.cert),
            "connect_private_key": str(keys.key), "connect_certificate": str(keys.cert),
            "verify_name_on_connect": False}


def access_control(roster: Roster) -> dict[str, Any]:
    """Zenoh's access control for every member of the fleet (the same on each; each judges what
    comes in from the identities it is connected to). Default deny; every member may read the
    fleet's keys and be sent them; each writes only what it owns:

    - a leader its ``leader/<id>/state|events``, ``arena/drive/<id>``, its ``alive/<id>`` token
      and claims on ``arena/claim/<id>`` -- nothing else: not another leader's keys, not the
      commands, not a handover, not the arena's truth;
    - the page the operator's commands (``leader/*/cmd``, ``all/cmd``), handovers (queries on
      ``arena/handover``) and its token ``page/alive`` -- nothing else: no truth, no leader's
      state, token, drive or claim. Its certificate drives nothing and speaks for no one;
    - the arena, the hub every other connects to, forwards the others' messages, which it
      checked as they came in (by this same control), so it may write every key of the fleet:
      the truth, the answers to claims and handovers, and what it forwards. A truth is
      therefore taken only from the arena, a leader's state only from that leader or through
      the arena, which took it only from that leader."""
    base = root(roster.fleet)
    rules: list[dict[str, Any]] = [
        {"id": "read", "permission": "allow", "flows": ["ingress"], "messages": list(READS),
         "key_exprs": [f"{base}/**"]},
        {"id": "hear", "permission": "allow", "flows": ["egress"], "messages": list(EVERY_MESSAGE),
         "key_exprs": [f"{base}/**"]},
        {"id": "relay", "permission": "allow", "flows": ["ingress"], "messages": list(EVERY_MESSAGE),
         "key_exprs": [f"{base}/**"]},
    ]
    subjects = [{"id": i, "cert_common_names": [i]} for i in roster.identities]
    rules += [
        {"id": "page-writes", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
         "key_exprs": [f"{base}/{k}" for k in PAGE_WRITES]},
        {"id": "page-alive", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
         "key_exprs": [f"{base}/{PAGE_TOKEN}"]},
        {"id": "page-handovers", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
         "key_exprs": [f"{base}/arena/handover"]},
    ]
    policies = [{"id": "arena", "rules": ["read", "hear", "relay"], "subjects": [ARENA]},
                {"id": "page", "rules": ["read", "hear", "page-writes", "page-alive", "page-handovers"],
                 "subjects": [PAGE]}]
    for lid in roster.leaders:
        rules += [
            {"id": f"{lid}-writes", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
             "key_exprs": [f"{base}/{k.format(id=lid)}" for k in LEADER_WRITES]},
            {"id": f"{lid}-alive", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
             "key_exprs": [f"{base}/alive/{lid}"]},
            {"id": f"{lid}-claims", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
             "key_exprs": [f"{base}/arena/claim/{lid}"]},
        ]
        policies.append({"id": f"leader-{lid}", "rules": ["read", "hear", f"{lid}-writes", f"{lid}-alive",
                                                          f"{lid}-claims"], "subjects": [lid]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def session_config(keys: FleetKeys) -> dict[str, Any]:
    """The parts of a Zenoh session's config that ``--keys`` adds."""
    return {"transport": {"link": {"tls": tls_config(keys)}}, "access_control": access_control(keys.roster)}


# -- the ROS 2 machines' router ------------------------------------------------------------------
def check_ros2_controllers(roster: Roster, controllers: tuple[str, ...]) -> tuple[str, ...]:
    """Who may publish /omniformation/stop and /goal on the ROS 2 router: identities with a
    bundle (``ros2`` and the fleet's); else ValueError in one line."""
    unknown = [c for c in controllers if c not in roster.bundles]
    if not controllers or unknown:
        raise ValueError(f"--ros2-control-by {','.join(controllers)}: {', '.join(unknown) or 'nobody'} is no identity"
                         f" of this fleet (one or more of {', '.join(roster.bundles)})")
    return controllers


def ros2_access_control(roster: Roster, controllers: tuple[str, ...] = (ROS2,)) -> dict[str, Any]:
    """Zenoh's access control for the ROS 2 machines' router: ROS traffic goes as it would (the
    default allows), but a put on ``/omniformation/stop`` or ``/omniformation/goal`` (any domain,
    any type) is let in only from ``controllers`` (default: ``ros2``, the operator's ROS tools):
    every other identity of the fleet, a leader's certificate among them, is denied it."""
    others = [i for i in roster.bundles if i not in check_ros2_controllers(roster, controllers)]
    acl: dict[str, Any] = {"enabled": True, "default_permission": "allow", "rules": [], "subjects": [],
                           "policies": []}
    if others:
        acl["rules"] = [{"id": "no-control", "permission": "deny", "flows": ["ingress"], "messages": ["put", "delete"],
                         "key_exprs": list(ROS2_CONTROL_KEYS)}]
        acl["subjects"] = [{"id": i, "cert_common_names": [i]} for i in others]
        acl["policies"] = [{"id": "not-controllers", "rules": ["no-control"], "subjects": others}]
    return acl


def ros2_router_config(roster: Roster, controllers: tuple[str, ...] = (ROS2,),
                       endpoint: str = "tls/[::]:7447") -> dict[str, Any]:
    """The ROS 2 router's config (``ZENOH_ROUTER_CONFIG_URI`` for ``rmw_zenohd``, started in the
    ``ros2`` bundle's folder: its file names are relative to it): mutual TLS with the ``ros2``
    identity, and :func:`ros2_access_control`."""
    tls = {"root_ca_certificate": CA_CERT, "enable_mtls": True,
           "listen_private_key": f"{ROS2}.key", "listen_certificate": f"{ROS2}.pem",
           "connect_private_key": f"{ROS2}.key", "connect_certificate": f"{ROS2}.pem", "verify_name_on_connect": False}
    return {"mode": "router", "listen": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            "transport": {"link": {"tls": tls}}, "access_control": ros2_access_control(roster, controllers)}
