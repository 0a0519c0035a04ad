"""Synthetic omnidirectional frames: what the leader's camera sees, given the team's state.

    looks      marker hues (the one list), robot-like boxes, render settings
    textures   floor and wall textures
    kernels    the compiled per-pixel and per-box passes
    renderer   Renderer and the lazily rendered SyntheticFrame
"""

from typing import TYPE_CHECKING, Any

from core.camera.render.looks import (DEFAULT_HUES_DEG, Boxes, BoxLook, RenderSettings, follower_bgr, follower_hex,
                                      follower_rgb, marker_bgr)

if TYPE_CHECKING:
    from core.camera.render.renderer import Renderer, SyntheticFrame


def __getattr__(name: str) -> Any:
    """The renderer on first use: a page that only colours its markers (looks) loads no compiled kernel."""
    if name in ("Renderer", "SyntheticFrame"):
        from core.camera.render import renderer

        return getattr(renderer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["DEFAULT_HUES_DEG", "BoxLook", "Boxes", "RenderSettings", "Renderer", "SyntheticFrame", "follower_bgr", "follower_hex",
           "follower_rgb", "marker_bgr"]
