"""Initial detection by background subtraction (paper §3.1, fig. 9).

Instead of comparing one image with a background, two backgrounds are compared: the
base background (everyone still) and the discriminant background (after follower i
made a short forward move). Each is the mean of K grey frames inside the working area,
which averages out sensor noise and the low resolution. The discriminant background of
follower i is the base of follower i + 1: n + 1 backgrounds for n followers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


class BackgroundAccumulator:
    """Mean of grey frames (float32) inside a mask."""

    def __init__(self, mask: np.ndarray) -> None:
        self.mask = mask
        self._sum: np.ndarray | None = None
        self.count = 0

    def add(self, frame_bgr: np.ndarray, origin: tuple[int, int] = (0, 0)) -> None:
        """One frame, or the part of it at ``origin`` (x, y) that covers the mask (outside
        the part the background is 0, as it is outside the mask)."""
        grey = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
        if self._sum is None:
            self._sum = np.zeros(self.mask.shape, np.float32)
        x0, y0 = origin
        self._sum[y0:y0 + grey.shape[0], x0:x0 + grey.shape[1]] += grey
        self.count += 1

    def mean(self) -> np.ndarray:
        if self._sum is None or self.count == 0:
            raise ValueError("no frames added")
        out = self._sum / float(self.count)
        out[self.mask == 0] = 0.0
        return out


@dataclass(frozen=True)
class MotionBlob:
    bbox: tuple[int, int, int, int]  # x, y, w, h
    area_px: int


def motion_blob(base: np.ndarray, discriminant: np.ndarray, mask: np.ndarray, threshold: float,
                min_area_px: int, merge_distance_px: float) -> MotionBlob | None:
    """Threshold |discriminant − base|, clean it with morphology, and keep the mover's blob:
    pieces close together are one blob (fig. 10), otherwise the largest is kept."""
    diff = cv2.absdiff(discriminant, base)
    binary: np.ndarray = ((diff > threshold) & (mask > 0)).astype(np.uint8) * 255
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    pieces = [tuple(int(v) for v in stats[k]) for k in range(1, count)]
    if not pieces:
        return None
    pieces.sort(key=lambda s: -s[4])
    x, y, w, h, area = pieces[0]
    grown = True
    while grown:
        grown = False
        for px, py, pw, ph, parea in pieces[1:]:
            gap_x = max(0, max(x, px) - min(x + w, px + pw))
            gap_y = max(0, max(y, py) - min(y + h, py + ph))
            inside = px >= x and py >= y and px + pw <= x + w and py + ph <= y + h
            if not inside and max(gap_x, gap_y) <= merge_distance_px:
                nx, ny = min(x, px), min(y, py)
                w, h = max(x + w, px + pw) - nx, max(y + h, py + ph) - ny
                x, y = nx, ny
                area += parea
                grown = True
    if area < min_area_px:
        return None
    return MotionBlob((x, y, w, h), area)
