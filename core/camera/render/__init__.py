"""Synthetic omnidirectional frames: what the leader's camera sees, given the team's state.

    looks      marker hues (the one list), robot-like boxes, render settings
    textures   floor and wall textures
    kernels    the compiled per-pixel and per-box passes
    renderer   Renderer and the lazily rendered SyntheticFrame
"""

from core.camera.render.looks import (DEFAULT_HUES_DEG, Boxes, BoxLook, RenderSettings, follower_bgr, follower_hex,
                                      follower_rgb, marker_bgr)
from core.camera.render.renderer import Renderer, SyntheticFrame

__all__ = ["DEFAULT_HUES_DEG", "BoxLook", "Boxes", "RenderSettings", "Renderer", "SyntheticFrame", "follower_bgr", "follower_hex",
           "follower_rgb", "marker_bgr"]
