"""The one door to viser's private parts: the gate and the input filter need a few of viser's
internals (its message types, its table of controls, its live connections) that viser has no
public API for. Every such reach is here, and nowhere else (tests/app/test_layers.py checks), so
a viser upgrade that moves one is found in one file; each function says what it needs and
raises ``RuntimeError`` (the page will not serve unguarded) where viser no longer has it."""

from __future__ import annotations

from typing import Any

import viser
from viser import _messages

GuiUpdateMessage = _messages.GuiUpdateMessage


def message_types() -> dict[str, type]:
    """viser's message classes by their wire name (``"GuiUpdateMessage"`` → its class)."""
    return dict(_messages.Message._subclass_from_type_string())


def control_table(gui: Any) -> dict[str, Any]:
    """The controls a GUI api (the server's or one client's) has now, by uuid (a live dict)."""
    table = getattr(gui, "_gui_input_handle_from_uuid", None)
    return table if isinstance(table, dict) else {}


def require_control_table(server: viser.ViserServer) -> None:
    """Raise unless viser exposes its controls (the input filter cannot judge without them)."""
    if not isinstance(getattr(server.gui, "_gui_input_handle_from_uuid", None), dict):
        raise RuntimeError(f"viser {viser.__version__} does not expose its controls; the page's input filter"
                           " cannot check what clients send, so it will not serve")


def uuid_of(handle: Any) -> str:
    """A control's id, as it travels in messages."""
    return str(handle._impl.uuid)


def removed(handle: Any) -> bool:
    return bool(handle._impl.removed)


def send_to(client: viser.ClientHandle, message: Any) -> bool:
    """Queue ``message`` to one client alone (viser's public API only broadcasts property
    changes); whether the client still had a connection."""
    connection = getattr(client, "_websock_connection", None)
    if connection is None:
        return False
    connection.queue_message(message)
    return True


def connection_hooks(server: viser.ViserServer) -> tuple[dict[int, Any], list[Any]]:
    """viser's table of live websockets (client id → connection, with its request) and its list
    of connect callbacks (a callback inserted first runs before viser builds anything)."""
    infra = getattr(server, "_websock_server", None)
    table = getattr(infra, "_live_connections", None)
    callbacks = getattr(infra, "_client_connect_cb", None)
    if infra is None or not isinstance(table, dict) or not isinstance(callbacks, list):
        raise RuntimeError(f"viser {viser.__version__} does not expose its connections; the dashboard's gate"
                           " cannot guard viser's loopback port, so it will not serve")
    return table, callbacks
