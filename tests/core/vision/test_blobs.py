"""Colour blobs (paper §3.1): pieces of one colour merge, grey is ignored."""

import cv2
import numpy as np
from core.vision.blobs import DetectSettings, find_blobs, hue_distance_deg


def test_blobs_merge_same_colour_pieces_and_ignore_grey():
    img = np.full((200, 200, 3), 128, np.uint8)
    cv2.rectangle(img, (40, 40), (60, 50), (0, 0, 220), -1)
    cv2.rectangle(img, (40, 54), (60, 64), (0, 0, 220), -1)  # the same rectangle, cut by a reflection
    cv2.rectangle(img, (120, 120), (140, 150), (0, 200, 0), -1)
    cv2.rectangle(img, (10, 150), (60, 190), (90, 95, 100), -1)  # grey box
    blobs = find_blobs(img, None, DetectSettings())
    assert len(blobs) == 2
    red = min(blobs, key=lambda b: hue_distance_deg(b.hue_deg, 0.0))
    assert hue_distance_deg(red.hue_deg, 0.0) < 3 and red.area_px == 2 * 21 * 11
    assert abs(red.v - 52.0) < 0.6 and abs(red.u - 50.0) < 1e-9
