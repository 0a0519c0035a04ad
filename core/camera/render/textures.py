"""The synthetic world's textures: a tiled floor and distant walls, and smooth noise."""

from __future__ import annotations

import cv2
import numpy as np


FLOOR_TEXELS = 256  # the floor texture repeats every 2.56 m (a power of two: wrapping is a mask)
WALL_HEIGHT_M = 2.5
WALL_COLS = 1024
WALL_ROWS = 128


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float, amplitude: float) -> np.ndarray:
    """Gaussian-blurred noise of unit spread times ``amplitude`` (float32)."""
    n: np.ndarray = rng.standard_normal(shape).astype(np.float32)
    n = cv2.GaussianBlur(n, (0, 0), sigma)
    n = n / max(float(np.std(n)), 1e-6)
    return n * amplitude


def floor_texture(rng: np.random.Generator) -> np.ndarray:
    """A tiled floor, low in saturation (a grey-beige, as in a lab), repeating every 2.56 m."""
    size = FLOOR_TEXELS
    tile = 32  # 32 cm tiles
    base = np.array([148.0, 156.0, 164.0], dtype=np.float32)
    tiles = rng.normal(0.0, 7.0, (size // tile, size // tile)).astype(np.float32)
    per_tile = np.kron(tiles, np.ones((tile, tile), np.float32))
    grain = smooth_noise(rng, (size, size), 2.0, 5.0)
    shade = per_tile + grain
    yy, xx = np.mgrid[0:size, 0:size]
    grout = ((xx % tile) < 1) | ((yy % tile) < 1)
    shade[grout] -= 40.0
    tex = np.clip(base[None, None, :] + shade[:, :, None], 0, 255).astype(np.uint8)
    return tex


def wall_texture(rng: np.random.Generator) -> np.ndarray:
    """Distant walls around 360 degrees: doors, cupboards, windows; greys and beiges."""
    tex = np.empty((WALL_ROWS, WALL_COLS, 3), np.float32)
    tex[:] = (170.0, 176.0, 182.0)
    skirting = int(WALL_ROWS * 0.1 / WALL_HEIGHT_M) + 1
    tex[:skirting] = (90.0, 92.0, 95.0)
    col = 0
    while col < WALL_COLS:
        width = int(rng.integers(40, 140))
        kind = rng.integers(0, 4)
        top = int(WALL_ROWS * rng.uniform(0.5, 0.85))
        shade = {0: (120.0, 125.0, 132.0), 1: (200.0, 204.0, 206.0), 2: (95.0, 105.0, 118.0), 3: (150.0, 150.0, 150.0)}[int(kind)]
        if kind != 3:
            tex[skirting:top, col + 4:min(col + width - 4, WALL_COLS)] = shade
        col += width
    tex += smooth_noise(rng, (WALL_ROWS, WALL_COLS), 1.5, 4.0)[:, :, None]
    return np.clip(tex, 0, 255).astype(np.uint8)


