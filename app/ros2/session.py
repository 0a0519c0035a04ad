"""The Zenoh session a ROS 2 node of ours runs on: a client of the ROS 2 machines' router
(``rmw_zenohd`` or ``zenohd``), under the fleet's endpoint rules (loopback without keys,
mutual TLS ``tls/`` with them: app.fleet.bridge.check_endpoint)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import zenoh

    from app.fleet.security import FleetKeys


def ros2_keys(directory: Path) -> FleetKeys:
    """``--keys DIR`` with ``--ros2``: one identity's bundle from ``fleet-keys`` (a leader's, the
    page's, or ``ros2``: the one ``<id>.key`` in it names the identity, its fleet.json the fleet),
    checked as the fleet checks it (app.fleet.security.load_fleet_keys: no CA key, no other
    identity's key beside it); else ValueError in one line."""
    from app.fleet.security import CA_DIR, CA_KEY, ROS2, ROSTER, KeyFileError, load_fleet_keys

    if not directory.is_dir():
        raise KeyFileError(f"--keys {directory}: not a directory (`omniformation fleet-keys DIR --ros2 ...` makes"
                           " DIR/ros2/ and one bundle per identity)")
    keys = sorted(p.stem for p in directory.glob("*.key") if p.name != CA_KEY)
    if not keys and not (directory / CA_DIR).is_dir() and not (directory / CA_KEY).exists():
        raise KeyFileError(f"--keys {directory}: no identity's key (<id>.key) in it: give one identity's bundle,"
                           " fleet-keys' DIR/<id>/")
    from app.files import UserError, read_regular

    try:  # a regular file of at most 64 KiB, as load_fleet_keys reads it
        fleet = json.loads(read_regular(directory / ROSTER, "the fleet's roster"))["fleet"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError, UserError):
        fleet = ""  # load_fleet_keys names what is wrong with the roster
    # a whole fleet-keys folder, a CA key or a second key beside: load_fleet_keys' bundle checks refuse it
    return load_fleet_keys(directory, keys[0] if keys else ROS2, fleet if isinstance(fleet, str) else "", ros2=True)


def session_config(connect: list[str], keys: FleetKeys | None = None) -> Any:
    """A client of the router at ``connect`` (each checked; ValueError names a bad one): it listens
    on nothing and scouts for nothing, so it reaches ROS nodes only through the router."""
    import zenoh

    from app.fleet.bridge import check_endpoint

    if not connect:
        raise ValueError("--ros2 needs --zenoh-connect ENDPOINT: the ROS 2 machines' Zenoh router")
    config: dict[str, Any] = {"mode": "client", "connect": {"endpoints": [check_endpoint(e, keys) for e in connect]},
                              "scouting": {"multicast": {"enabled": False}}}
    if keys is not None:
        from app.fleet.security import tls_config

        # mutual TLS only: who may publish what on ROS keys is the ROS router's access control (docs/ros2.md)
        config["transport"] = {"link": {"tls": tls_config(keys)}}
    return zenoh.Config.from_json5(json.dumps(config))


def open_ros2_session(connect: list[str], keys: FleetKeys | None = None) -> zenoh.Session:
    """The session, else ValueError in one line (a bad endpoint, or no router answers there)."""
    import zenoh

    config = session_config(connect, keys)
    try:
        return zenoh.open(config)
    except Exception as exc:  # noqa: BLE001 - zenoh says why (no router at the endpoint, ...)
        why = str(exc).splitlines()[0].split(" at /")[0][:160] if str(exc) else type(exc).__name__
        raise ValueError(f"--zenoh-connect {', '.join(connect)}: no ROS 2 Zenoh router answers ({why})") from None
