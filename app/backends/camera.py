"""Frame sources for a real rig: an OpenCV camera, a video file, a folder of images.

Each source runs its own capture thread and keeps only the newest frame with the
monotonic time it arrived, so the loop never waits for a camera: it asks ``latest()``
once per tick and decides from the frame's age (no fresh frame for 0.3 s: every follower
to zero, see app.backends.feedback). A camera that disappears is reopened with back-off; a video
file or folder that ends says so. Nothing here raises into the loop.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import os

# FFmpeg's own log lines would stand beside our one-line messages (e.g. 'moov atom not found'):
# quiet unless the user asked for them. Read when OpenCV's FFmpeg backend starts.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

import cv2
import numpy as np

from core.camera.config import CaptureSettings

from app.contracts import RealtimeFrameSource
from app.realtime import make_realtime

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class ThreadedSource:
    """The newest frame, written by one capture thread, read by the loop."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)  # notified with every new frame (frame-triggered ticks)
        self._frame: np.ndarray | None = None
        self._t = -math.inf
        self._count = 0
        self._state = "starting"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"omniformation-frames-{name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def make_realtime(self) -> str:
        """The capture thread on SCHED_FIFO (app.realtime): a frame is stamped when it arrives,
        not when the system gets round to it. '' when granted, else why not."""
        ident = self._thread.native_id
        return make_realtime(ident) if ident is not None else "the capture thread has not started"

    @property
    def state(self) -> str:
        with self._lock:
            return self._state

    def _set_state(self, text: str) -> None:
        with self._lock:
            self._state = text

    def _put(self, frame: np.ndarray) -> None:
        with self._lock:
            self._frame, self._t = frame, time.monotonic()
            self._count += 1
            self._arrived.notify_all()

    def wait_newer(self, count: int, timeout: float) -> int:
        """Wait until a frame newer than number ``count`` has arrived, at most ``timeout`` s; the
        newest frame's number (``count`` itself if none came)."""
        with self._lock:
            self._arrived.wait_for(lambda: self._count > count, timeout)
            return self._count

    def latest(self) -> tuple[np.ndarray | None, float, int]:
        with self._lock:
            return self._frame, self._t, self._count

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)

    def _run(self) -> None:  # pragma: no cover - replaced by subclasses
        raise NotImplementedError


def _as_bgr(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


# OpenCV's V4L2 backend takes 1 for manual exposure; older ones took 0.25 (what each backend
# accepts differs: the value is read back and the page shows what the camera took)
MANUAL_EXPOSURE = (1.0, 0.25)


def apply_capture_settings(cap: Any, settings: CaptureSettings) -> dict[str, tuple[Any, Any]]:
    """Set a freshly opened ``cv2.VideoCapture`` as ``settings`` say (format and size first: a
    driver may reset the rest when they change; then frame rate, queue, exposure, gain, white
    balance) and read each back: {name: (asked, got)}. A camera that refuses one keeps going;
    the report shows it."""
    report: dict[str, tuple[Any, Any]] = {}

    def put(name: str, prop: int, value: float, shown: Any = None) -> None:
        cap.set(prop, float(value))
        report[name] = (value if shown is None else shown, cap.get(prop))

    if settings.pixel_format is not None:
        cap.set(cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*settings.pixel_format)))
        got = int(cap.get(cv2.CAP_PROP_FOURCC))
        report["pixel_format"] = (settings.pixel_format,
                                  "".join(chr((got >> (8 * k)) & 0xFF) for k in range(4)) if got > 0 else "?")
    if settings.width is not None:
        put("width", cv2.CAP_PROP_FRAME_WIDTH, settings.width)
    if settings.height is not None:
        put("height", cv2.CAP_PROP_FRAME_HEIGHT, settings.height)
    if settings.fps is not None:
        put("fps", cv2.CAP_PROP_FPS, settings.fps)
    if settings.buffer_size is not None:
        put("buffer_size", cv2.CAP_PROP_BUFFERSIZE, settings.buffer_size)
    if settings.exposure is not None:
        for manual in MANUAL_EXPOSURE:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, manual)
            if cap.get(cv2.CAP_PROP_AUTO_EXPOSURE) == manual:
                break
        report["auto_exposure"] = ("off", "off" if cap.get(cv2.CAP_PROP_AUTO_EXPOSURE) in MANUAL_EXPOSURE else
                                   f"{cap.get(cv2.CAP_PROP_AUTO_EXPOSURE):g}")
        put("exposure", cv2.CAP_PROP_EXPOSURE, settings.exposure)
    if settings.gain is not None:
        put("gain", cv2.CAP_PROP_GAIN, settings.gain)
    if settings.white_balance_k is not None:
        cap.set(cv2.CAP_PROP_AUTO_WB, 0.0)
        report["auto_white_balance"] = ("off", "off" if cap.get(cv2.CAP_PROP_AUTO_WB) == 0.0 else
                                        f"{cap.get(cv2.CAP_PROP_AUTO_WB):g}")
        put("white_balance_k", cv2.CAP_PROP_WB_TEMPERATURE, settings.white_balance_k)
    return report


def settings_text(report: dict[str, tuple[Any, Any]], settings: CaptureSettings | None) -> str:
    """One line for the page: each setting asked -> got, a mismatch marked, what is not locked."""
    if settings is None:
        return "camera settings: none locked (no [capture] table: exposure and white balance may float)"

    def shown(v: Any) -> str:
        return f"{v:g}" if isinstance(v, float) else str(v)

    parts = []
    for name, (asked, got) in report.items():
        same = (isinstance(asked, (int, float)) and isinstance(got, (int, float)) and abs(float(asked) - float(got))
                <= 1e-6 * max(1.0, abs(float(asked)))) or asked == got
        parts.append(f"{name} {shown(asked)}" + ("" if same else f" (got {shown(got)})"))
    loose = [n for n, v in (("exposure", settings.exposure), ("white balance", settings.white_balance_k)) if v is None]
    return "camera settings: " + ", ".join(parts) + (f"; not locked: {', '.join(loose)}" if loose else "")


class CaptureSource(ThreadedSource):
    """``cv2.VideoCapture`` on a camera (index or device path) or a video file.

    A camera is read as fast as it delivers and reopened (0.5 s doubling to 4 s) when it
    stops; a file is paced at its own frame rate (or ``fps``) and ends with "end of file".
    A camera is set as ``settings`` say every time it opens, before its first frame is taken
    (so before the pipeline learns its background), and what it took is read back
    (``settings_report``, ``settings_line``)."""

    def __init__(self, target: int | str, is_file: bool, fps: float | None = None,
                 settings: CaptureSettings | None = None, opener: Callable[[int | str], Any] | None = None) -> None:
        super().__init__(str(target))
        self.target, self.is_file, self.fps = target, is_file, fps
        self.settings = None if is_file else settings
        self._opener = opener or cv2.VideoCapture
        self.settings_report: dict[str, tuple[Any, Any]] = {}
        self.start()

    @property
    def settings_line(self) -> str:
        if self.is_file:
            return ""
        with self._lock:
            return settings_text(dict(self.settings_report), self.settings)

    def _open(self) -> Any:
        cap = self._opener(self.target)
        if not cap.isOpened():
            cap.release()
            return None
        if self.settings is not None:
            report = apply_capture_settings(cap, self.settings)
            with self._lock:
                self.settings_report = report
        return cap

    def _run(self) -> None:
        backoff = 0.5
        while not self._stop.is_set():
            cap = self._open()
            if cap is None:
                if self.is_file:
                    self._set_state(f"cannot read video {self.name}")
                    return
                self._set_state(f"camera {self.name} not available; retrying in {backoff:.2g} s")
                self._stop.wait(backoff)
                backoff = min(backoff * 2, 4.0)
                continue
            backoff = 0.5
            self._set_state(f"{'video' if self.is_file else 'camera'} {self.name}: ok")
            fps = self.fps or (cap.get(cv2.CAP_PROP_FPS) if self.is_file else 0.0) or 30.0
            next_t = time.monotonic()
            try:
                while not self._stop.is_set():
                    ok, frame = cap.read()
                    if not ok or frame is None:
                        break
                    self._put(_as_bgr(frame))
                    if self.is_file:
                        next_t += 1.0 / fps
                        self._stop.wait(max(0.0, next_t - time.monotonic()))
            finally:
                cap.release()
            if self.is_file:
                self._set_state(f"end of file {self.name}")
                return
            self._set_state(f"camera {self.name} lost; reopening")


class FolderSource(ThreadedSource):
    """The images of a folder in name order, at ``fps``; says "end of folder" after the last."""

    def __init__(self, folder: Path, fps: float = 30.0, loop: bool = False) -> None:
        super().__init__(str(folder))
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        self.fps, self.loop = fps, loop
        self.unreadable = 0
        self.start()

    def _run(self) -> None:
        if not self.files:
            self._set_state(f"no images in {self.name}")
            return
        self._set_state(f"folder {self.name}: ok")
        next_t = time.monotonic()
        while not self._stop.is_set():
            for path in self.files:
                if self._stop.is_set():
                    return
                img = cv2.imread(str(path), cv2.IMREAD_COLOR)
                if img is None:
                    self.unreadable += 1
                    self._set_state(f"folder {self.name}: {self.unreadable} unreadable file(s), last {path.name}")
                else:
                    self._put(img)
                next_t += 1.0 / self.fps
                self._stop.wait(max(0.0, next_t - time.monotonic()))
            if not self.loop:
                self._set_state(f"end of folder {self.name}")
                return


def open_frame_source(spec: str, fps: float | None = None, settings: CaptureSettings | None = None) -> RealtimeFrameSource:
    """``0`` (a camera index), a device path, a video file or a folder of images; a camera is set
    as ``settings`` say (the camera file's ``[capture]``).

    ValueError with one line naming what was given and what is allowed."""
    if spec.isdigit():
        return CaptureSource(int(spec), is_file=False, settings=settings)
    path = Path(spec)
    if path.is_dir():
        return FolderSource(path, fps or 30.0)
    if spec.startswith("/dev/"):
        return CaptureSource(spec, is_file=False, settings=settings)
    if path.is_file():
        probe = cv2.VideoCapture(spec)
        try:
            ok = probe.isOpened() and probe.read()[0]
        finally:
            probe.release()
        if not ok:
            raise ValueError(f"--camera {spec!r}: OpenCV cannot read a frame from this file (not a video it knows:"
                             " give a video, an image folder, a camera index or a /dev/video* device)")
        return CaptureSource(spec, is_file=True, fps=fps)
    raise ValueError(f"--camera {spec!r}: not a camera index (0, 1, ...), a /dev/video* device, a video file"
                     " or a folder of images")


class SyntheticMarkerRig:
    """The synthetic rig standing in for a real camera while calibrating: an empty floor seen
    through the rig's model (tilted, off-centre, as its config says) with markers where a
    helper put them. ``place`` is the helper: the calibration page asks for each marker where
    its guide wants it, and the helper puts it there give or take ``placement_sd_m``, as a
    person with a tape measure would. The pictures are rendered, and the page finds the marker
    in them as in a real camera's (core.camera.guide.find_marker)."""

    def __init__(self, config: Any, seed: int = 0, placement_sd_m: float = 0.003) -> None:
        from core.camera.synthetic import renderer_for

        self.name = f"synthetic rig {config.source}"
        self.config = config
        self._renderer = renderer_for(config, clutter=False, distractor=False)
        self._rng = np.random.default_rng(seed)
        self.placement_sd_m = placement_sd_m
        self._markers: list[tuple[float, float]] = []
        self._frame: np.ndarray | None = None
        self._k = 0
        self._lock = threading.Lock()

    @property
    def state(self) -> str:
        return "ok"

    def place(self, markers: list[tuple[float, float]]) -> None:
        """Markers at (bearing deg, distance m), leader frame (bearing 0 ahead, counter-clockwise)."""
        from core.camera.model import bearing_range_to_xy

        rows = []
        for b, d in markers:
            db = self._rng.normal(0.0, self.placement_sd_m)
            xy = bearing_range_to_xy(np.array(math.radians(b)), np.array(d + db))
            rows.append([float(xy[0]), float(xy[1]), math.radians(b) + math.pi / 2])
        followers = np.array(rows, dtype=np.float64).reshape(-1, 3)
        frame = self._renderer.render(np.array([0.0, 0.0, math.pi / 2]), followers, 0.0, self._rng)
        with self._lock:
            self._markers = list(markers)
            self._frame = frame
            self._k += 1

    def wait_newer(self, count: int, timeout: float) -> int:
        """Pictures are rendered when a marker is placed: there is nothing to wait for."""
        return self.latest()[2]

    def latest(self) -> tuple[np.ndarray | None, float, int]:
        if self._frame is None:
            self.place([])  # nothing placed yet: the empty floor
        with self._lock:
            return self._frame, time.monotonic(), self._k

    def close(self) -> None:
        pass
