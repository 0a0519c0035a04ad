"""The parameter store: what the operator sets, read by the loop once per tick.

GUI callbacks run on viser's thread pool, concurrently with the loop. They
only ever call :meth:`ParamsStore.update`, which validates, clamps (with a
notice saying what was changed and why) and swaps in a new frozen
:class:`Params` under a lock. The loop calls :meth:`ParamsStore.get` once per
tick and sees either the old or the new set, never a mix.

A change that depends on what is in force (the loop clearing ``leader_hold`` once the team is
whole, Pause toggling) is one atomic read-modify-write, :meth:`ParamsStore.change`: the decision
is made on the parameters in force under the lock, never on a copy read earlier (a STOP pressed
between the read and the write would otherwise be half undone).

One-shot requests (single step, reset) are counters rather than flags, so
that a request made while the loop is busy is never lost and never done twice.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field
from typing import Any, Literal, get_args
from collections.abc import Callable

import numpy as np

from core.control.presets import FORMATION_PRESETS, PRESET_REACH_M, default_formation, formation_preset
from core.bounds import (GOAL_LIMIT_M, LEADER_SPEED, LEADER_TURN, MAX_FOLLOWERS, MIN_SCALE, PARAMETERS,
                         SAFETY_DISTANCE, SETTERS, SLOT_COORD, SLOT_LIMIT_M, number_default)
from core.types import Bound, FloatArray, Gains

# what the page, the CLI and the tests take from here: the store, and the bounds and presets (core's) it uses
__all__ = ["FORMATION_PRESETS", "GOAL_LIMIT_M", "LEADER_MODES", "LEADER_SPEED", "LEADER_TURN", "MAX_FOLLOWERS",
           "MIN_SCALE", "PARAMETERS", "PRESET_REACH_M", "SAFETY_DISTANCE", "SLOT_COORD", "SLOT_LIMIT_M", "LeaderMode",
           "Notice", "Params", "ParamsStore", "default_slots", "formation_preset", "params_events"]

LeaderMode = Literal["stop", "straight", "circle", "eq39", "goal"]
LEADER_MODES: tuple[LeaderMode, ...] = get_args(LeaderMode)
assert LEADER_MODES == PARAMETERS["leader_mode"].choices  # the type's values are the table's


def _default(name: str) -> Any:
    return PARAMETERS[name].default


@dataclass(frozen=True)
class Params:
    """Everything the operator can change, as one consistent snapshot."""

    # every default is its row's in the parameter table (core.bounds.PARAMETERS)
    gains: Gains = field(default_factory=Gains)
    leader_mode: LeaderMode = _default("leader_mode")
    leader_speed_mps: float = number_default("leader_speed_mps")
    leader_turn_deg_s: float = number_default("leader_turn_deg_s")
    slots: FloatArray = field(default_factory=lambda: np.array(_default("slots"), dtype=np.float64))
    n_followers: int = int(number_default("n_followers"))
    paused: bool = _default("paused")
    stop: bool = _default("stop")  # the big STOP: every actuator commanded (0, 0), the leader too; the loop keeps observing
    # after STOP is released the leader waits where it is until every follower is tracked again;
    # STOP sets it, the loop clears it, "release anyway" releases without it
    leader_hold: bool = _default("leader_hold")
    safety: bool = _default("safety")  # the barrier-certificate filter on every command (core.control.safety)
    safety_distance_m: float = number_default("safety_distance_m")  # its minimum distance, centre to centre
    goal: tuple[float, float] | None = _default("goal")  # leader mode "goal": where the leader drives (odometry frame, m)
    min_scale: float = number_default("min_scale")  # how narrow the formation may get to pass a gap (core.control.navigation)
    step_requests: int = _default("step_requests")
    reset_requests: int = _default("reset_requests")
    version: int = 0

    def __post_init__(self) -> None:
        """A snapshot is valid or is not made: ValueError (one line) naming the field and what is
        allowed, whoever builds it (the store, a scenario's starting values, an arena's)."""
        if self.leader_mode not in LEADER_MODES:
            raise ValueError(f"leader_mode = {self.leader_mode!r}: must be one of {', '.join(LEADER_MODES)}")
        LEADER_SPEED.check("leader_speed_mps", self.leader_speed_mps)
        LEADER_TURN.check("leader_turn_deg_s", self.leader_turn_deg_s)
        SAFETY_DISTANCE.check("safety_distance_m", self.safety_distance_m)
        MIN_SCALE.check("min_scale", self.min_scale)
        if isinstance(self.n_followers, bool) or not 1 <= int(self.n_followers) <= MAX_FOLLOWERS \
                or int(self.n_followers) != self.n_followers:
            raise ValueError(f"n_followers = {self.n_followers!r}: must be a whole number from 1 to {MAX_FOLLOWERS}")
        slots = np.asarray(self.slots)
        if slots.ndim != 2 or slots.shape[1] != 2 or slots.shape[0] < 1 or not np.all(np.isfinite(slots)) \
                or np.abs(slots).max() > SLOT_LIMIT_M:
            raise ValueError(f"slots: must be rows of [x, y] with |x|, |y| <= {SLOT_LIMIT_M:g} m")
        if self.goal is not None and not (all(math.isfinite(v) for v in self.goal)
                                          and max(abs(v) for v in self.goal) <= GOAL_LIMIT_M):
            raise ValueError(f"goal = {self.goal!r}: must be [x, y] with |x|, |y| <= {GOAL_LIMIT_M:g} m, or none")

    def replace(self, **changes: Any) -> "Params":
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class Notice:
    """Something the operator should see: a value clamped or refused."""

    key: str
    message: str


class ParamsStore:
    """Thread-safe holder of the current :class:`Params`; atomic swaps, validation, notices."""

    def __init__(self, initial: Params | None = None, fixed_followers: int | None = None) -> None:
        """``fixed_followers``: a real team's size (e.g. the robots on a serial link); the
        follower count then cannot be changed from the page."""
        self._lock = threading.Lock()
        self.fixed_followers = fixed_followers
        self._params = initial or Params()
        if fixed_followers is not None and self._params.n_followers != fixed_followers:
            self._params = self._params.replace(n_followers=fixed_followers)
        self._listeners: list[Callable[[Params, str, tuple[Notice, ...]], None]] = []
        self.goal_check: Callable[[tuple[float, float]], str | None] | None = None  # why a goal cannot be reached

    def get(self) -> Params:
        return self._params  # a reference read is atomic; Params is immutable

    def load(self, params: Params, source: str) -> None:
        """Put a whole parameter set in force (a replay showing what was in force at a moment); the
        listeners hear it like any change."""
        with self._lock:
            new = self._params = params.replace(version=self._params.version + 1)
            listeners = list(self._listeners)
        for fn in listeners:
            fn(new, source, ())

    def subscribe(self, fn: Callable[[Params, str, tuple[Notice, ...]], None]) -> None:
        """Call fn(params, source, notices) after every change (e.g. to sync other browsers)."""
        with self._lock:
            self._listeners.append(fn)

    def update(self, source: str = "server", **changes: Any) -> tuple[Params, tuple[Notice, ...]]:
        """Validate and apply changes; out-of-range numbers are clamped with a notice.

        ``source`` says who changed it ("browser:<client id>", "server", "cli"),
        so listeners can tell a person's change from the server's own echo.
        Unknown keys and values of the wrong kind are refused (ValueError).
        """
        return self.change(source, lambda _: changes)

    def update_from(self, who: str, source: str, **changes: Any) -> tuple[Params, tuple[Notice, ...]]:
        """:meth:`update` for a party the table names (core.bounds.SETTERS: the fleet's bus, ROS):
        a key its row does not let ``who`` set is refused (ValueError naming it and what ``who``
        may set), and nothing changes."""
        assert who in SETTERS, who
        for key in changes:
            row = PARAMETERS.get(key)
            if row is None or who not in row.setters:
                allowed = ", ".join(n for n, r in PARAMETERS.items() if who in r.setters)
                raise ValueError(f"{key}: cannot be set from the {who} (allowed: {allowed})")
        return self.update(source, **changes)

    def change(self, source: str, decide: Callable[[Params], dict[str, Any]]) -> tuple[Params, tuple[Notice, ...]]:
        """Atomic read-modify-write: ``decide(params in force)`` names the changes, applied as
        :meth:`update` applies them, with no other change in between; ``{}`` changes nothing."""
        with self._lock:
            current = self._params
            changes = decide(current)
            if not changes:
                return current, ()
            notices: list[Notice] = []
            new_values: dict[str, Any] = {}
            gain_changes: dict[str, float] = {}
            for key, value in changes.items():
                row = PARAMETERS.get(key)
                if row is None:
                    raise ValueError(f"{key}: not a parameter the operator can set")
                if row.kind == "gain":
                    assert row.bound is not None
                    gain_changes[key] = _clamped(key, value, row.bound, notices)
                elif row.kind == "number":  # the speed, the turn rate, the safety distance, the narrowest scale
                    assert row.bound is not None
                    new_values[key] = _clamped(key, value, row.bound, notices)
                elif key == "leader_mode":
                    if value not in LEADER_MODES:
                        raise ValueError(f"leader_mode = {value!r}: must be one of {', '.join(LEADER_MODES)}")
                    new_values[key] = value
                elif key == "slot":
                    index, x, y = value
                    slots = np.array(new_values.get("slots", current.slots), dtype=np.float64)
                    if not 0 <= int(index) < slots.shape[0]:
                        raise ValueError(f"slot {index}: must be 0..{slots.shape[0] - 1}")
                    slots[int(index)] = [
                        _clamped(f"slot {int(index) + 1} x", x, SLOT_COORD, notices),
                        _clamped(f"slot {int(index) + 1} y", y, SLOT_COORD, notices),
                    ]
                    new_values["slots"] = slots
                elif key == "slots":
                    arr = np.asarray(value, dtype=np.float64)
                    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 1:
                        raise ValueError(f"slots: must be a list of [x, y], got shape {arr.shape}")
                    if not np.all(np.isfinite(arr)):
                        raise ValueError("slots: every x and y must be a finite number (m); unchanged")
                    clipped = np.clip(arr, -SLOT_LIMIT_M, SLOT_LIMIT_M)
                    if not np.array_equal(clipped, arr):
                        notices.append(Notice("slots", f"slots clamped to +-{SLOT_LIMIT_M:g} m"))
                    new_values["slots"] = clipped
                elif key == "n_followers":
                    n = _whole(key, value)
                    if self.fixed_followers is not None and n != self.fixed_followers:
                        notices.append(Notice(key, f"followers = {value}: the team on the link has"
                                                   f" {self.fixed_followers}; the count is fixed"))
                        n = self.fixed_followers
                    elif not 1 <= n <= MAX_FOLLOWERS:
                        notices.append(Notice(key, f"followers = {value}: allowed 1..{MAX_FOLLOWERS}, set to {min(max(n, 1), MAX_FOLLOWERS)}"))
                        n = min(max(n, 1), MAX_FOLLOWERS)
                    new_values[key] = n
                elif row.kind == "flag":
                    if not isinstance(value, (bool, int, np.bool_)):
                        raise ValueError(f"{key} = {value!r}: must be true or false")
                    new_values[key] = bool(value)
                    if key == "stop" and value and "leader_hold" not in changes:
                        new_values["leader_hold"] = True  # a release waits for the team unless told otherwise
                elif key == "goal":
                    goal = _goal(value)
                    if goal is not None and max(abs(goal[0]), abs(goal[1])) > GOAL_LIMIT_M:
                        notices.append(Notice(key, f"goal ({goal[0]:.2f}, {goal[1]:.2f}) m is off the floor the leader"
                                                   f" can reach (|x|, |y| <= {GOAL_LIMIT_M:g} m from where it started);"
                                                   " refused"))
                        continue
                    if goal is not None and self.goal_check is not None:
                        why = self.goal_check(goal)
                        if why:
                            notices.append(Notice(key, f"goal ({goal[0]:.2f}, {goal[1]:.2f}) m {why}; refused"))
                            continue
                    new_values[key] = goal
                elif row.kind == "request":
                    new_values[key] = getattr(current, key) + 1
                else:
                    raise ValueError(f"{key}: not a parameter the operator can set")
            if gain_changes:
                new_values["gains"] = current.gains.replace(**gain_changes)
            new = current.replace(**new_values, version=current.version + 1)
            slots = new.slots
            if slots.shape[0] < new.n_followers:
                extra = default_slots(new.n_followers)[slots.shape[0]:]
                new = new.replace(slots=np.vstack([slots, extra]))
            self._params = new
            listeners = list(self._listeners)
        result = tuple(notices)
        for fn in listeners:
            fn(new, source, result)
        return new, result


def params_events(old: Params, new: Params, source: str) -> list[tuple[str, str]]:
    """What an operator change did, in words (the recording's events, the fleet's, Foxglove's)."""
    ev: list[tuple[str, str]] = []
    og, ng = old.gains.as_dict(), new.gains.as_dict()
    changed = [f"{k} {og[k]:g} -> {ng[k]:g}" for k in ng if og[k] != ng[k]]
    if changed:
        ev.append(("gain", ", ".join(changed)))
    if old.slots.shape != new.slots.shape or not np.array_equal(old.slots, new.slots):
        kind = "preset" if "preset" in source else "target"
        ev.append((kind, f"{source.split(' ', 1)[-1] if kind == 'preset' else 'slots'}: "
                   + "; ".join(f"({x:.2f}, {y:.2f})" for x, y in new.slots)))
    for key in ("leader_mode", "leader_speed_mps", "leader_turn_deg_s", "n_followers", "paused"):
        if getattr(old, key) != getattr(new, key):
            ev.append(("setting", f"{key} {getattr(old, key)} -> {getattr(new, key)}"))
    if new.stop and not old.stop and " STOP by " in source:  # who pressed it (the tick's own event says it held)
        ev.append(("stop_by", f"STOP pressed by {source.split(' STOP by ', 1)[1]}"))
    if old.reset_requests != new.reset_requests:
        ev.append(("reset", "team reset"))
    return ev


def _goal(value: Any) -> tuple[float, float] | None:
    """A goal from a person: None (no goal) or two finite numbers (m), else one line."""
    if value is None:
        return None
    try:
        x, y = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"goal = {value!r}: must be [x, y] in metres, or none") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"goal = {value!r}: must be two finite numbers (m); unchanged")
    return x, y


def _clamped(key: str, value: Any, bound: Bound, notices: list[Notice]) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key} = {value!r}: must be a number") from None
    lo_br = "[" if bound.lo_inclusive else "("
    if not math.isfinite(number):  # NaN or infinity is no value at all: refused, not clamped to a bound
        raise ValueError(f"{key} = {value!r}: must be a finite number in {lo_br}{bound.lo:g}, {bound.hi:g}] {bound.unit}"
                         "; unchanged")
    clamped = bound.clamp(number)
    if clamped != number:
        unit = f" {bound.unit}" if bound.unit else ""
        notices.append(Notice(key, f"{key} = {value!r} is outside {lo_br}{bound.lo:g}, {bound.hi:g}]{unit}: set to {clamped:g}"))
    return clamped


def _whole(key: str, value: Any) -> int:
    """A count from a person: a whole number (a float that is one is fine), else one line."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{key} = {value!r}: must be a whole number") from None
    if not math.isfinite(number) or number != int(number):
        raise ValueError(f"{key} = {value!r}: must be a whole number; unchanged")
    return int(number)


default_slots = default_formation  # the page's name for it
