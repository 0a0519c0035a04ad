"""One colour per follower everywhere on the page: the colour of its marker rectangle."""

from __future__ import annotations

from core.camera.render import DEFAULT_HUES_DEG, marker_bgr


def follower_bgr(i: int) -> tuple[int, int, int]:
    b, g, r = marker_bgr(DEFAULT_HUES_DEG[i % len(DEFAULT_HUES_DEG)], 0.85, 0.8)
    return int(b), int(g), int(r)


def follower_rgb(i: int) -> tuple[int, int, int]:
    b, g, r = follower_bgr(i)
    return r, g, b
