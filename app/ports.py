"""The loop's ports: where follower poses come from and where commands go.

Until the vision pipeline exists the simulated team measures itself (ground
truth plus noise); a camera FrameSource and the serial FollowerLink plug in
behind the same shapes.
"""

from __future__ import annotations

from typing import Protocol

from core.types import Commands, FloatArray


class TeamObservation(Protocol):
    """Leader-frame poses of the followers, and which of them are seen."""

    def observe(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(p (n, 2) m, a (n,) rad, tracked (n,) bool)."""
        ...


class FollowerLink(Protocol):
    """Delivers each tick's commands to the followers."""

    link_state: str

    def send(self, commands: Commands) -> None: ...

    def close(self) -> None: ...
