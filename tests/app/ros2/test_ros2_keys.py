"""ROS 2 under the fleet's rules with keys (docs/ros2.md, "Security"): `fleet-keys --ros2` makes a
bundle for the ROS 2 machines; their router listens on tls/ with it; `run --ros2 --keys` and
`emulate-base --ros2 --keys` join it by mutual TLS with one identity's bundle. Written from the
docs: a Python Zenoh router in router mode stands for `rmw_zenohd` with a TLS config."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import main_cli, serve_then_signal


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("keys")
    out = main_cli("fleet-keys", str(d), "--fleet", "f", "--leaders", "L1", "--ros2")
    assert out.returncode == 0, out.stderr
    return d


def _open(config: dict[str, Any]) -> Any:
    import zenoh

    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


def _tls(bundle: Path, identity: str) -> dict[str, Any]:
    """The router's TLS section as docs/ros2.md gives it (transport/link/tls, mutual TLS)."""
    return {"root_ca_certificate": str(bundle / "ca.pem"), "enable_mtls": True,
            "listen_private_key": str(bundle / f"{identity}.key"), "listen_certificate": str(bundle / f"{identity}.pem"),
            "connect_private_key": str(bundle / f"{identity}.key"),
            "connect_certificate": str(bundle / f"{identity}.pem"), "verify_name_on_connect": False}


def test_fleet_keys_ros2_makes_a_bundle_for_the_ros_machines(keys):
    bundle = keys / "ros2"
    assert sorted(p.name for p in bundle.iterdir()) == ["ca.pem", "fleet.json", "ros2.key", "ros2.pem",
                                                          "router.json5"]
    assert (bundle / "ca.pem").read_bytes() == (keys / "L1" / "ca.pem").read_bytes()
    assert json.loads((bundle / "fleet.json").read_text())["ros2"] is True


def test_a_ros_base_and_the_service_join_a_tls_router_and_a_plain_client_hears_nothing(keys):
    """The router listens on tls/ with the ros2 bundle; `emulate-base --ros2 --keys DIR/ros2` and
    `run --ros2 --keys DIR/L1 --leader ros2:/cmd_vel` join it by mutual TLS: the base is driven.
    A plain tcp/ peer pointed at the router's port gets nothing of it."""
    import subprocess
    import sys

    from tests.helpers import ROOT

    port = _port()
    endpoint = f"tls/127.0.0.1:{port}"
    router = _open({"mode": "router", "listen": {"endpoints": [endpoint]},
                    "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                    "transport": {"link": {"tls": _tls(keys / "ros2", "ros2")}}})
    heard: list[bytes] = []
    plain = _open({"mode": "peer", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}, "listen": {"endpoints": []},
                   "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}})
    sub = plain.declare_subscriber("0/**", lambda s: heard.append(s.payload.to_bytes()))
    seen: list[bytes] = []  # the router's own view: what the service sends on /cmd_vel
    router_sub = router.declare_subscriber("0/cmd_vel/**", lambda s: seen.append(s.payload.to_bytes()))
    base = subprocess.Popen([sys.executable, "-m", "app.cli", "emulate-base", "--ros2", "--zenoh-connect", endpoint,
                             "--keys", str(keys / "ros2"), "--seconds", "60"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert base.stdout is not None
        assert "ROS 2 base on domain 0" in base.stdout.readline()
        run = serve_then_signal("--feedback", "truth", "--followers", "2", "--port", "0", "--no-record", "--ros2",
                                "--zenoh-connect", endpoint, "--keys", str(keys / "L1"), "--leader", "ros2:/cmd_vel",
                                until=lambda: len(seen) >= 20)
        assert run.returncode == 0, run.stderr
        assert "ROS 2 node /omniformation on domain 0" in run.startup + run.stdout
    finally:
        base.terminate()
        out, _ = base.communicate(30)
    commands = int(out.split("base stopped after ")[1].split()[0])
    print(f"mutual TLS: the base took {commands} commands; the plain tcp/ peer heard {len(heard)} messages")
    assert commands >= 20 and not heard
    sub.undeclare()
    router_sub.undeclare()
    plain.close()
    router.close()


@pytest.mark.parametrize("args, words", [
    (["emulate-base", "--ros2", "--zenoh-connect", "tls/127.0.0.1:7447", "--keys", "{keys}"], "whole folder"),
    (["emulate-base", "--ros2", "--zenoh-connect", "tcp/127.0.0.1:7447", "--keys", "{keys}/ros2"],
     "with --keys every endpoint is tls/"),
    (["emulate-base", "--ros2", "--keys", "{keys}/ros2"], "--keys needs --zenoh-connect tls/"),
    (["run", "--ros2", "--zenoh-connect", "tls/127.0.0.1:7447", "--keys", "{keys}"], "whole folder"),
    (["run", "--ros2", "--zenoh-connect", "tls/127.0.0.1:7447"], "tls/ needs the fleet's keys"),
    (["run", "--ros2", "--zenoh-connect", "tls/127.0.0.1:7447", "--keys", "{keys}/ca"], "CA's private key"),
])
def test_bad_keys_for_ros2_are_one_line_and_exit_2(keys, args, words):
    out = main_cli(*[a.format(keys=keys) for a in args])
    assert out.returncode == 2, out
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], out.stderr


def test_the_ros2_bundle_is_nobody_on_the_fleets_bus(keys):
    from app.fleet.security import KeyFileError, load_fleet_keys

    with pytest.raises(KeyFileError, match="'ros2' is not in fleet f"):
        load_fleet_keys(keys / "ros2", "ros2", "f")
    assert load_fleet_keys(keys / "ros2", "ros2", "f", ros2=True).identity == "ros2"


def _router_from_bundle(bundle: Path, endpoint: str) -> dict[str, Any]:
    """DIR/ros2/router.json5 as docs/ros2.md says to use it: its file names are the bundle's."""
    config = json.loads((bundle / "router.json5").read_text())
    tls = config["transport"]["link"]["tls"]
    for k, v in tls.items():
        if isinstance(v, str):
            tls[k] = str(bundle / v)
    config["listen"]["endpoints"] = [endpoint]
    return config


def _client(bundle: Path, identity: str, endpoint: str) -> Any:
    return _open({"mode": "client", "connect": {"endpoints": [endpoint]},
                  "scouting": {"multicast": {"enabled": False}}, "transport": {"link": {"tls": _tls(bundle, identity)}}})


def test_only_the_ros2_identity_may_stop_or_set_goals_through_the_routers_access_rules(tmp_path):
    """fleet-keys --ros2 writes the ROS router's config: on it a leader's certificate (L2's) can
    publish ROS traffic but not /omniformation/stop or /goal; the ros2 identity can. The listener
    holds L1's certificate, as `run --ros2 --ros2-control --keys KEYS/L1` would."""
    import threading
    import time

    from rosbags.typesys import Stores, get_typestore

    out = main_cli("fleet-keys", str(tmp_path), "--fleet", "f", "--leaders", "L1,L2", "--ros2")
    assert out.returncode == 0, out.stderr
    port = _port()
    endpoint = f"tls/127.0.0.1:{port}"
    router = _open(_router_from_bundle(tmp_path / "ros2", endpoint))
    heard: list[tuple[str, bool]] = []
    lock = threading.Lock()
    service = _client(tmp_path / "L1", "L1", endpoint)

    def on(sample: Any) -> None:
        with lock:
            heard.append((str(sample.key_expr).split("/")[2], sample.payload.to_bytes()[4] == 1))

    sub = service.declare_subscriber("0/omniformation/*/**", on)
    ts = get_typestore(Stores.ROS2_JAZZY)
    true, false = (bytes(ts.serialize_cdr(ts.types["std_msgs/msg/Bool"](data=b), "std_msgs/msg/Bool"))
                   for b in (True, False))
    attachment = bytes(33)
    l2 = _client(tmp_path / "L2", "L2", endpoint)
    operator = _client(tmp_path / "ros2", "ros2", endpoint)

    def key(kind: str) -> str:
        return f"0/omniformation/{kind}/std_msgs::msg::dds_::Bool_/RIHS01_x"

    def until(what: tuple[str, bool], put: Any = None) -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and what not in heard:
            if put is not None:
                put()
            time.sleep(0.05)

    try:
        until(("status", True), lambda: l2.put(key("status"), true, attachment=attachment))  # L2 reaches the service
        for kind in ("stop", "goal"):
            l2.put(key(kind), true, attachment=attachment)
        l2.put(key("status"), false, attachment=attachment)  # after its stop and goal on the same link
        until(("status", False))
        until(("stop", True), lambda: operator.put(key("stop"), true, attachment=attachment))
        with lock:
            got = list(heard)
        print(f"the service heard {got}: L2's stop and goal denied by the router, the operator's stop let through")
        marker = got.index(("status", False))  # L2's stop and goal, had they passed, came before it
        assert all(k == "status" for k, _ in got[:marker]) and ("stop", True) in got[marker:]
        assert all(k != "goal" for k, _ in got)
    finally:
        sub.undeclare()
        for s in (l2, operator, service, router):
            s.close()


def test_ros2_control_by_names_identities_of_the_fleet(tmp_path):
    from app.fleet.security import Roster, ros2_access_control

    roster = Roster("f", ("L1", "L2"), True)
    acl = ros2_access_control(roster, ("ros2", "L1"))
    assert acl["policies"][0]["subjects"] == ["arena", "page", "L2"]
    out = main_cli("fleet-keys", str(tmp_path / "k"), "--fleet", "f", "--leaders", "L1", "--ros2",
                   "--ros2-control-by", "ros2,L9")
    assert out.returncode == 2 and "L9 is no identity of this fleet" in out.stderr, out
    assert not (tmp_path / "k").exists()
