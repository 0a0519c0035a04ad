"""Joining a fleet's Zenoh bus for a command (a leader, the arena, the fleet page): one line
(UserError) for an endpoint refused or a bus that cannot be joined."""

from __future__ import annotations

from typing import TYPE_CHECKING

from app.files import UserError

if TYPE_CHECKING:
    import zenoh

    from app.fleet.security import FleetKeys


def open_bus(listen: list[str], connect: list[str], who: str, keys: FleetKeys | None = None) -> zenoh.Session:
    from app.fleet.bridge import open_session

    try:
        return open_session(listen, connect, keys)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    except Exception as exc:  # noqa: BLE001 - zenoh says why it cannot open (an endpoint taken, ...)
        raise UserError(f"{who}: cannot join the bus: {str(exc).splitlines()[0][:200]}") from None
