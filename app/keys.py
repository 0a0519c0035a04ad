"""The names on a fleet's bus (docs/fleet-protocol.md): the key root of a fleet and the
robots' names in an arena. Shared by the fleet's programs and the arena backend."""

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
