"""What each quantity a person sets may be, declared once.

The scenario and fleet readers (core.config, core.fleet), the parameter store that the
page and the fleet bus go through (app.params; ``Params`` checks itself against these), the
page's controls (their min and max, which the page's input filter enforces) and the command
line all read the bounds from here, so a value one of them takes is a value all of them take.
The controller's gains are bounded in core.types (``GAIN_BOUNDS``) beside ``Gains``."""

from __future__ import annotations

from core.types import GAIN_BOUNDS, Bound

__all__ = ["GAIN_BOUNDS", "GOAL_LIMIT_M", "GOAL_SPEED", "LEADER_SPEED", "LEADER_TURN", "MAX_FOLLOWERS", "MIN_SCALE",
           "SAFETY_DISTANCE", "SLOT_COORD", "SLOT_LIMIT_M"]

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
