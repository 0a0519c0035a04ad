"""The names on a fleet's bus (docs/fleet-protocol.md): the key root of a fleet and the
robots' names in an arena. Shared by the fleet's programs, the arena backend and the pages: a
robot has one name on every page, the fleet's R id (a leader's page adds its slot there)."""

from __future__ import annotations

from typing import Any


def root(fleet: str) -> str:
    return f"omniformation/{fleet}"


def robot_name(r: int) -> str:
    return f"R{r + 1}"


def robot_index(name: Any, count: int) -> int | None:
    """R1 … RR to 0 … R−1; None for anything else."""
    if not isinstance(name, str) or not name.startswith("R") or not name[1:].isdigit():
        return None
    r = int(name[1:]) - 1
    return r if 0 <= r < count else None


def follower_name(i: int, robots: tuple[int, ...] | None = None) -> str:
    """Follower ``i``'s one name for people: the fleet's robot id with this leader's slot, "R3 (F1)",
    when it is an arena's robot (``robots``: the fleet's index of each follower), else "F1"."""
    if robots is not None and 0 <= i < len(robots):
        return f"{robot_name(robots[i])} (F{i + 1})"
    return f"F{i + 1}"


def held_name(r: int, leader_id: str, slot: int) -> str:
    """An arena robot on the fleet page while a leader drives it: "R3 · L1 F1" (its slot there)."""
    return f"{robot_name(r)} · {leader_id} F{slot + 1}"
