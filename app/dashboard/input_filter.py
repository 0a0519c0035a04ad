"""What a client may send the page: a value for a known control, of the right type, within that
control's declared bounds, and nothing else.

viser applies any property a client names in a ``GuiUpdateMessage`` to the control's server-side
state, not only its value: ``{"update_cb": []}`` removes what a button does (STOP included, for
every tab), and an integer of 2**64 stored as a value breaks the page for every later browser
(it can no longer be serialised). A malformed message raises inside viser's reader, which logs a
traceback and drops the connection. viser has no hook for any of this, so the gate
(app.dashboard.gate) runs every message a client sends through :meth:`InputFilter.judge` before
it reaches viser (a layer in front of it, no fork, no patch).

What passes:

* ``GuiUpdateMessage`` whose only field is ``value``, for a control that exists, is enabled and
  visible, and only when the value fits the control: a button's is ``true`` (a click); a slider's
  or a number box's is a finite number (never a string, never a boolean) within its ``min`` and
  ``max`` (and, with neither, within ±2**53: the largest whole number a browser holds exactly), a
  whole number where the control holds whole numbers (an integral step from an integral start);
  a checkbox's is a boolean; a dropdown's or a button group's is one of its options; a text box's
  is a string of at most ``TEXT_MAX`` characters. Fractional steps are not enforced: the number box
  beside a slider takes what a person types (0.123 in a 0.01-step box), and the value is in range.
* the 3D view's own messages (the camera, clicks, drags of a handle) when they have exactly the
  fields of viser's message type (``msgspec.convert`` ignores unknown fields, and viser then raises
  on them and drops the client), decode as that type, with finite numbers that mean something (a
  unit quaternion, a non-zero up and ray direction, 0 < fov < pi, 0 < near < far, image sizes
  1..16384: a zero "up" makes every later placement of that client's camera raise, on the page's
  thread, for every client); a viewer may only move its own camera. The contract: docs/page-access.md.
* nothing else: other message types (file uploads, share links, commands, form events) are
  dropped; the project uses none of them.

A viewer (a client let in with the viewer token) may press only the controls the page marked as
safe for anyone (:meth:`InputFilter.allow_viewer`: STOP); everything else it sends is refused.

The verdict says why a message was refused and which control's value in force to send back, so
the gate can answer the client (and only that client) and log it, briefly.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import msgspec
import viser

from app.dashboard import viser_private

TEXT_MAX = 1000  # characters a text box may be sent
WHOLE_MAX = 2.0 ** 53  # beyond this a browser's number is no longer a whole number it can hold
SCENE_MESSAGES = ("ViewerCameraMessage", "ScenePointerMessage", "SceneNodeClickMessage", "SceneNodeDragMessage",
                  "TransformControlsUpdateMessage", "TransformControlsDragStartMessage",
                  "TransformControlsDragEndMessage")
VIEWER_SCENE = ("ViewerCameraMessage",)  # a viewer moves its own camera, nothing in the world
# a browser sends these by itself (a button's hold, a form's state); the page uses none: dropped without a word
QUIET = ("GuiButtonHoldMessage", "GuiFormDirtyMessage", "GuiFormSubmitMessage")

OPERATOR = "operator"
VIEWER = "viewer"


@dataclass(frozen=True)
class Verdict:
    """What to do with one message: forward it, or refuse it (``why``, one line) and answer the
    client with the value in force of control ``uuid`` (when the message named one; a forwarded
    control update names its control too)."""

    forward: bool
    why: str = ""
    uuid: str = ""
    quiet: bool = False  # refused without a word (a browser's own chatter the page does not use)
    kind: str = ""  # a forwarded scene message's type


PASS = Verdict(True)


def _finite(x: Any) -> bool:
    """Every number in a decoded message is finite (NaN and infinities are no position)."""
    if isinstance(x, float):
        return math.isfinite(x)
    if isinstance(x, (list, tuple)):
        return all(_finite(v) for v in x)
    if isinstance(x, dict):
        return all(_finite(v) for v in x.values())
    return True


POSITION_MAX_M = 1e6  # a position, look-at point or ray origin, each coordinate (m)
DIRECTION_MIN, DIRECTION_MAX = 1e-6, 1e6  # a direction's length: not zero, not absurd
FAR_MAX_M = 1e9
IMAGE_MAX_PX = 16384
SCREEN_MAX = 10.0  # viser's screen positions are 0..1; a little outside is a pointer at the edge
UNIT_TOLERANCE = 0.01  # how far from 1 a rotation's norm may be (a browser's float32 rounding)


def _norm(v: Any) -> float:
    return math.sqrt(sum(float(x) * float(x) for x in v))


def scene_fault(body: dict[str, Any]) -> str:
    """'' when a scene message's (decoded, finite) fields mean something, else what is allowed
    (docs/page-access.md): each field is checked by its name, whatever message carries it."""
    for name, value in body.items():
        if value is None:
            continue
        if name == "wxyz" and abs(_norm(value) - 1.0) > UNIT_TOLERANCE:
            return "wxyz must be a unit quaternion"
        if name in ("position", "look_at", "ray_origin", "start_position", "end_position") \
                and max(abs(float(x)) for x in value) > POSITION_MAX_M:
            return f"{name} must be within {POSITION_MAX_M:g} m in each coordinate"
        if name in ("up_direction", "ray_direction") and not DIRECTION_MIN <= _norm(value) <= DIRECTION_MAX:
            return f"{name} must be a direction (not zero)"
        if name == "fov" and not 0.0 < float(value) < math.pi:
            return "fov must be in (0, pi) radians"
        if name == "near" and not float(value) > 0.0:
            return "near must be positive"
        if name == "far" and not float(body.get("near", 0.0)) < float(value) <= FAR_MAX_M:
            return f"far must be beyond near and at most {FAR_MAX_M:g}"
        if name in ("image_width", "image_height") and (isinstance(value, bool) or not isinstance(value, int)
                                                        or not 1 <= value <= IMAGE_MAX_PX):
            return f"{name} must be a whole number from 1 to {IMAGE_MAX_PX}"
        if name in ("screen_pos", "start_screen_pos", "end_screen_pos") \
                and not all(abs(float(x)) <= SCREEN_MAX for x in _flat(value)):
            return f"{name} must be within [-{SCREEN_MAX:g}, {SCREEN_MAX:g}]"
    return ""


def _flat(value: Any) -> list[Any]:
    if isinstance(value, (list, tuple)):
        return [x for v in value for x in _flat(v)]
    return [value]


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


class InputFilter:
    """Judges each message a client sends against the controls ``server`` has now."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self._viewer_may: set[str] = set()
        viser_private.require_control_table(server)
        self._types = viser_private.message_types()
        self._fields = {kind: {f.name for f in dataclasses.fields(self._types[kind])} for kind in SCENE_MESSAGES}

    def allow_viewer(self, *handles: Any) -> None:
        """Controls a viewer may press too (STOP: stopping is always safe)."""
        self._viewer_may.update(viser_private.uuid_of(h) for h in handles)

    def viewer_may(self, uuid: str) -> bool:
        return uuid in self._viewer_may

    def handle(self, uuid: str) -> Any:
        """The control with this id: the page's, or one a client was shown (a modal), or None."""
        found = viser_private.control_table(self.server.gui).get(uuid)
        if found is not None:
            return found
        for client in list(self.server.get_clients().values()):
            table = viser_private.control_table(client.gui)
            if uuid in table:
                return table[uuid]
        return None

    def judge(self, raw: bytes | str, role: str = OPERATOR) -> Verdict:
        if not isinstance(raw, bytes):
            return Verdict(False, "a text frame (the page speaks binary msgpack)")
        try:
            message = msgspec.msgpack.decode(raw)
        except (msgspec.DecodeError, ValueError, TypeError, RecursionError):
            return Verdict(False, f"{len(raw)} bytes that are not a message")
        if not isinstance(message, dict) or not isinstance(message.get("type"), str):
            return Verdict(False, "a message without a type")
        kind = message["type"]
        if kind == "GuiUpdateMessage":
            return self._gui_update(message, role)
        if kind in SCENE_MESSAGES:
            if role != OPERATOR and kind not in VIEWER_SCENE:
                return Verdict(False, f"{kind}: a viewer cannot change the scene")
            body = {k: v for k, v in message.items() if k != "type"}
            unknown = set(body) - self._fields[kind]
            if unknown:
                names = ", ".join(sorted(str(k)[:20] for k in unknown))[:80]
                return Verdict(False, f"{kind}: fields it does not have ({names})")
            try:
                msgspec.convert(body, self._types[kind])
            except (msgspec.ValidationError, TypeError, ValueError, KeyError) as exc:
                return Verdict(False, f"{kind}: {str(exc).splitlines()[0][:120]}")
            if not _finite(body):
                return Verdict(False, f"{kind}: a number that is not finite")
            why = scene_fault(body)
            return Verdict(False, f"{kind}: {why}") if why else Verdict(True, kind=kind)
        if kind in QUIET:
            return Verdict(False, f"{kind}: not used here", quiet=True)
        return Verdict(False, f"message type {kind[:60]!r} is not one a client may send")

    def _gui_update(self, message: dict[str, Any], role: str) -> Verdict:
        uuid, updates = message.get("uuid"), message.get("updates")
        if not isinstance(uuid, str) or not isinstance(updates, dict) or set(message) != {"type", "uuid", "updates"}:
            return Verdict(False, "a control update that is not {uuid, updates}")
        handle = self.handle(uuid)
        if handle is None or viser_private.removed(handle):
            return Verdict(False, "an update for a control that does not exist")
        name = str(getattr(handle, "label", "") or "")[:40] or "a control"
        if set(updates) != {"value"}:
            fields = ", ".join(sorted(str(k)[:20] for k in updates if k != "value")) or "nothing"
            return Verdict(False, f"{name}: only its value may be changed, not {fields}", uuid)
        if role != OPERATOR and uuid not in self._viewer_may:
            return Verdict(False, f"{name}: this page is view only (only STOP may be pressed)", uuid)
        disabled, visible = bool(getattr(handle, "disabled", False)), bool(getattr(handle, "visible", True))
        if disabled or not visible:
            return Verdict(False, f"{name}: {'disabled' if disabled else 'hidden'} now", uuid)
        why = _value_fault(handle, updates["value"])
        return Verdict(False, f"{name} = {_short(updates['value'])}: {why}", uuid) if why else Verdict(True, uuid=uuid)


def _value_fault(handle: Any, value: Any) -> str:
    """'' when ``value`` is one the control can take, else what is allowed."""
    if isinstance(handle, viser.GuiButtonHandle):
        return "" if value is True else "a button can only be clicked"
    if isinstance(handle, viser.GuiCheckboxHandle):
        return "" if isinstance(value, bool) else "must be true or false"
    if isinstance(handle, (viser.GuiDropdownHandle, viser.GuiButtonGroupHandle)):
        options = tuple(handle.options)
        return "" if isinstance(value, str) and value in options else f"must be one of {', '.join(options)[:120]}"
    if isinstance(handle, viser.GuiTextHandle):
        if not isinstance(value, str) or len(value) > TEXT_MAX or "\x00" in value:
            return f"must be text of at most {TEXT_MAX} characters"
        return ""
    if isinstance(handle, (viser.GuiSliderHandle, viser.GuiNumberHandle)):
        return _number_fault(handle, value)
    return "this control takes nothing from a client"


def _number_fault(handle: Any, value: Any) -> str:
    lo = handle.min if handle.min is not None else -WHOLE_MAX
    hi = handle.max if handle.max is not None else WHOLE_MAX
    allowed = f"a number in [{lo:g}, {hi:g}]"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f"must be {allowed}"
    if not math.isfinite(value) or not lo <= value <= hi:
        return f"must be {allowed}"
    step = handle.step
    whole = isinstance(handle.value, int) or (step is not None and float(step).is_integer()
                                               and float(handle.min if handle.min is not None else 0).is_integer())
    if whole and not float(value).is_integer():
        return f"must be a whole number in [{lo:g}, {hi:g}]"
    return ""
