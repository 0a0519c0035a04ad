"""What each quantity a person or a program sets may be, declared once: the parameter table.

Every parameter is one row (:class:`Parameter`): its name (the key ``ParamsStore.update``
takes), its bound, its default, its unit (the bound's), its label on the page, its slider step
and who may set it (the operator's page, a view-only client, the fleet's bus, ROS, a scenario
file). The scenario and fleet readers (core.config, core.fleet), the parameter store
(app.params; ``Params`` checks itself against these and takes its defaults from here), the
page's controls and the fleet page's (their min, max and step, which the page's input filter
enforces), the bus's and ROS's allowed sets, the recording's decoding and docs/parameters.md
are made from it, so a value one of them takes is a value all of them take. The controller's
gains are bounded in core.types (``GAIN_BOUNDS``) beside ``Gains``, whose field defaults are
their rows' defaults.

A control's range is its row's bound on the step's grid: the bound's ``hi``, and its ``lo``
when that is allowed, else ``lo + step`` (k_f1 > 0 is 0.01 on a slider of step 0.01)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from core.types import GAIN_BOUNDS, Bound, Gains

__all__ = ["BUS", "GAIN_BOUNDS", "GOAL_COORD", "GOAL_LIMIT_M", "GOAL_SPEED", "LEADER_SPEED", "LEADER_TURN",
           "MAX_FOLLOWERS", "MIN_SCALE", "OPERATOR", "PARAMETERS", "ROS", "SAFETY_DISTANCE", "SCENARIO", "SETTERS",
           "SLOT_COORD", "SLOT_LIMIT_M", "VIEWER", "Parameter", "markdown_table", "number_default", "settable_by"]

MAX_FOLLOWERS = 8  # one leader's team, live (the simulator runs any number)
LEADER_SPEED = Bound(-0.3, 0.3, "m/s", "leader forward speed", lo_inclusive=True)
GOAL_SPEED = Bound(0.0, LEADER_SPEED.hi, "m/s", "the leader's cruising speed towards a goal")
LEADER_TURN = Bound(-30.0, 30.0, "deg/s", "leader turn rate, counter-clockwise positive", lo_inclusive=True)
SAFETY_DISTANCE = Bound(0.15, 1.0, "m", "the safety filter's minimum distance between robots, centre to centre",
                        lo_inclusive=True)
MIN_SCALE = Bound(0.3, 1.0, "", "how narrow the formation may get to pass a gap", lo_inclusive=True)
SLOT_LIMIT_M = 2.0  # desired positions must stay where the camera can see them
SLOT_COORD = Bound(-SLOT_LIMIT_M, SLOT_LIMIT_M, "m", "desired position in the leader frame", lo_inclusive=True)
GOAL_LIMIT_M = 10.0  # a goal further than this from where the leader started is off the floor it knows
GOAL_COORD = Bound(-GOAL_LIMIT_M, GOAL_LIMIT_M, "m", "where the leader drives in goal mode (the odometry frame:"
                   " where it started)", lo_inclusive=True)
FOLLOWERS = Bound(1, MAX_FOLLOWERS, "", "followers in the team (a real team's count is its link's)", lo_inclusive=True)

# who may set a parameter
OPERATOR = "page"  # the operator's page (a client with the operator's link)
VIEWER = "viewer"  # a view-only client of the page: STOP only (docs/page-access.md)
BUS = "bus"  # the fleet's bus, to a leader started with --fleet-control (STOP always; docs/fleet-protocol.md)
ROS = "ros"  # ROS 2 with --ros2-control: /omniformation/stop and /omniformation/goal (docs/ros2.md)
SCENARIO = "scenario"  # a scenario or config file (core.config)
SETTERS = (OPERATOR, VIEWER, BUS, ROS, SCENARIO)

# kinds of value: a gain (inside Params.gains), a number, a whole number, a flag, a choice, a point
# [x, y], the formation's slots, one slot (the page's edit of one row), a one-shot request (a counter)
KINDS = ("gain", "number", "count", "flag", "choice", "point", "slots", "slot", "request")


@dataclass(frozen=True)
class Parameter:
    """One row of the parameter table (see the module's docstring)."""

    name: str
    kind: str
    default: Any
    label: str
    setters: frozenset[str]
    bound: Bound | None = None  # numbers, counts, points and slots (each coordinate)
    step: float | None = None  # the page's slider or number step; None: no control of its own
    recorded: bool = True  # restored from a recording's parameter sets (a replay shows what was in force)
    choices: tuple[str, ...] = ()  # a choice's values

    @property
    def unit(self) -> str:
        return self.bound.unit if self.bound is not None else ""

    def control_range(self) -> tuple[float, float]:
        """A control's (min, max): the bound on the step's grid (the module's docstring)."""
        assert self.bound is not None and self.step is not None, self.name
        lo = self.bound.lo if self.bound.lo_inclusive else self.bound.lo + self.step
        return float(lo), float(self.bound.hi)


def _set(*who: str) -> frozenset[str]:
    return frozenset(who)


_GAIN_ROWS = {  # label, step on the page (None: not on the page), who
    "k_f1": ("k_f1 (m/s)", 0.01, _set(OPERATOR, BUS, SCENARIO)),
    "k_f2": ("k_f2 (m/s)", 0.01, _set(OPERATOR, BUS, SCENARIO)),
    "a": ("a (m)", 0.01, _set(OPERATOR, BUS, SCENARIO)),
    "k_w1": ("k_w1 (rad/s)", 0.05, _set(OPERATOR, BUS, SCENARIO)),
    "k_w2": ("k_w2", 0.1, _set(OPERATOR, BUS, SCENARIO)),
    "v_max": ("v_max (m/s)", None, _set(SCENARIO)),
    "w_max": ("w_max (rad/s)", None, _set(SCENARIO)),
    "accel_v_max": ("accel_v_max (m/s^2)", None, _set(SCENARIO)),
    "accel_w_max": ("accel_w_max (rad/s^2)", None, _set(SCENARIO)),
    "tau_ar": ("tau_ar (s)", None, _set(SCENARIO)),
}
_GAIN_DEFAULTS = {f.name: f.default for f in dataclasses.fields(Gains)}

PARAMETERS: dict[str, Parameter] = {
    **{name: Parameter(name, "gain", _GAIN_DEFAULTS[name], label, who, GAIN_BOUNDS[name], step)
       for name, (label, step, who) in _GAIN_ROWS.items()},
    "leader_mode": Parameter("leader_mode", "choice", "stop", "Motion", _set(OPERATOR, BUS, ROS),
                             choices=("stop", "straight", "circle", "eq39", "goal")),
    "leader_speed_mps": Parameter("leader_speed_mps", "number", 0.06, "Speed (m/s)", _set(OPERATOR, BUS, SCENARIO),
                                  LEADER_SPEED, 0.01),
    "leader_turn_deg_s": Parameter("leader_turn_deg_s", "number", 1.5, "Turn (deg/s)", _set(OPERATOR, BUS, SCENARIO),
                                   LEADER_TURN, 0.5),
    "goal": Parameter("goal", "point", None, "Goal (m, odometry frame)", _set(OPERATOR, BUS, ROS, SCENARIO),
                      GOAL_COORD, 0.05),
    "min_scale": Parameter("min_scale", "number", 0.6, "Narrowest formation", _set(OPERATOR, BUS, SCENARIO),
                           MIN_SCALE, 0.05),
    "n_followers": Parameter("n_followers", "count", 2, "Followers", _set(OPERATOR, SCENARIO), FOLLOWERS, 1),
    "safety": Parameter("safety", "flag", True, "Safety filter", _set(OPERATOR, BUS, SCENARIO)),
    "safety_distance_m": Parameter("safety_distance_m", "number", 0.25, "Min distance (m)",
                                   _set(OPERATOR, BUS, SCENARIO), SAFETY_DISTANCE, 0.01),
    "slots": Parameter("slots", "slots", ((-0.5, -0.3), (0.5, -0.3)), "Desired positions (leader frame, m)",
                       _set(OPERATOR, BUS, SCENARIO), SLOT_COORD, 0.01),
    "slot": Parameter("slot", "slot", None, "Slot k x, y", _set(OPERATOR), SLOT_COORD, 0.01, recorded=False),
    "stop": Parameter("stop", "flag", False, "STOP", _set(OPERATOR, VIEWER, BUS, ROS)),
    "leader_hold": Parameter("leader_hold", "flag", False, "Release anyway (clears the leader's wait)",
                             _set(OPERATOR), recorded=False),
    "paused": Parameter("paused", "flag", False, "Pause", _set(OPERATOR)),
    "step_requests": Parameter("step_requests", "request", 0, "Single step", _set(OPERATOR), recorded=False),
    "reset_requests": Parameter("reset_requests", "request", 0, "Reset", _set(OPERATOR), recorded=False),
}


def number_default(name: str) -> float:
    """A number's default, as the table declares it (``Params`` and the safety filter read it)."""
    default = PARAMETERS[name].default
    assert isinstance(default, (int, float)) and not isinstance(default, bool), name
    return float(default)


def settable_by(who: str) -> tuple[str, ...]:
    """The parameters ``who`` (one of SETTERS) may set, in the table's order."""
    return tuple(name for name, row in PARAMETERS.items() if who in row.setters)


def _cell(x: Any) -> str:
    if isinstance(x, float):
        return f"{x:g}"
    if isinstance(x, tuple):
        return "[" + ", ".join(_cell(v) for v in x) + "]"
    return "none" if x is None else str(x).lower() if isinstance(x, bool) else str(x)


def markdown_table() -> str:
    """The table for people (docs/parameters.md holds it; a test keeps the two the same)."""
    rows = ["| name | kind | allowed | default | unit | label | step | who may set it |",
            "|---|---|---|---|---|---|---|---|"]
    for row in PARAMETERS.values():
        b = row.bound
        allowed = ("[" if b.lo_inclusive else "(") + f"{b.lo:g}, {b.hi:g}]" if b is not None else \
            "true, false" if row.kind == "flag" else "counter (+1 per request)" if row.kind == "request" else "-"
        if row.kind == "choice":
            allowed = ", ".join(row.choices)
        rows.append(f"| `{row.name}` | {row.kind} | {allowed} | {_cell(row.default)} | {row.unit or '-'} | {row.label}"
                    f" | {_cell(row.step) if row.step is not None else '-'} |"
                    f" {', '.join(w for w in SETTERS if w in row.setters)} |")
    return "\n".join(rows) + "\n"
