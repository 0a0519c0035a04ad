"""The paper's vision pipeline (§3) as a state machine the loop steps once per frame.

Phases
------
``find``      instead of ``base`` and ``probe`` when the team's marker hues are known (a fleet's
              arena assigns them, and other teams' robots move in view, which the background
              differencing of §3.1 would take for ours): each follower is looked for by its
              hue in the whole working area, never a blob nearer another robot's hue; its
              window and colour are learned there as after a probe. Then ``heading``.
``base``      everyone still: the base background (mean of K grey frames, working area only).
``probe``     follower i makes a short forward move (the pipeline asks for it through
              ``VisionOutput.manoeuvre``), stops, the discriminant background is built,
              the thresholded difference gives its blob, and its colour (hue histogram)
              and window are learned from the rectangle inside that blob (§3.1). The
              discriminant is the next follower's base: n + 1 backgrounds for n followers.
``heading``   all found followers drive forward together; CAMSHIFT tracks each; the
              positions (through Γ) are fitted by RANSAC then least squares; the line's
              direction, signed by the motion, is a₀ (§3.2).
``tracking``  every frame: CAMSHIFT → window centroid → Γ → position; headings by eq. 34–37
              with eq. 38 between measurements and a Kalman filter (core.vision.heading).
              A follower whose colour mass collapses, whose window leaves the working area,
              or that is not seen for N frames is lost: ``tracked`` goes False at once (the
              controller stops it) and it is searched for by colour until it is found.

Nothing here knows whether frames are synthetic: it sees BGR images, the leader's odometry
and the commands that were sent. It asks a frame for the rectangles it needs (CAMSHIFT's
regions of interest) and for the whole image only where §3 needs it (backgrounds, the
search for a lost follower), so an image that makes its pixels on demand is cheap to follow. Slot assignment (eq. 33) is the caller's, once ``ready``.
"""

from __future__ import annotations

import math
import dataclasses
from dataclasses import dataclass, field

from typing import Literal, get_args

import cv2
import numpy as np

from core.camera.config import DetectSettings, WorkingArea
from core.camera.gamma import Gamma
from core.geometry import reexpress_in_new_frame, wrap_angle
from core.types import BoolArray, FloatArray, Image, IntArray
from core.vision.background import BackgroundAccumulator, motion_blob
from core.vision.blobs import MIN_HUE_SEPARATION_DEG, Blob, find_blobs, hue_distance_deg, nearest_hue, saturated_mask
from core.vision.heading import HeadingBank, arc_measurements, fit_heading_line
from core.vision.tracking import Track, camshift, hue_histogram


@dataclass(frozen=True)
class PipelineSettings:
    background_frames: int = 8  # K grey frames per background
    settle_s: float = 0.5  # wait after a move before building a background (actuator lag)
    probe_speed_mps: float = 0.08  # §3.1: a short forward move ...
    probe_s: float = 0.8  # ... of 6.4 cm
    heading_speed_mps: float = 0.06  # §3.2: all drive forward ...
    heading_s: float = 1.6  # ... about 10 cm
    diff_threshold: float = 18.0  # grey levels between the two backgrounds
    min_blob_px: int = 30
    lost_after_frames: int = 3  # unseen this many frames in a row: lost (0.1 s at 30 Hz)
    min_mass_fraction: float = 0.25  # colour mass below this share of the learned area: unseen
    roi_margin_px: int = 16
    hue_tolerance_deg: float = 15.0  # a blob this close in hue may be a lost follower
    ransac_tolerance_m: float = 0.006
    kalman_sigma0_deg: float = 8.0
    kalman_process_deg: float = 6.0  # per sqrt(s)
    kalman_measurement_deg: float = 6.0
    find_timeout_s: float = 3.0  # known hues: go on with the followers found by then (the rest are looked for later)


Phase = Literal["find", "base", "probe", "heading", "tracking"]
"""The pipeline's phases: finding the team by known hues (a fleet), base background (§3.1),
probing each follower (§3.1), first headings (§3.2), tracking for formation control (§3.3)."""
PHASES: tuple[Phase, ...] = get_args(Phase)
Stage = Literal["settle", "collect", "move", "run"]
"""Within a start-up phase: wait for stillness, collect background frames, make the manoeuvre;
"run" while tracking."""


@dataclass(frozen=True)
class VisionOutput:
    phase: Phase
    probing: int  # follower being probed (0-based), -1 otherwise
    positions: FloatArray  # (n, 2) leader frame, m; NaN until first seen
    headings: FloatArray  # (n,) Kalman-filtered, rad; NaN until known
    heading_measured: FloatArray  # (n,) this frame's eq. 34–37 measurement, NaN if none
    tracked: BoolArray  # (n,)
    manoeuvre: FloatArray | None  # (n, 2) (v, w) the pipeline needs sent during start-up
    windows: np.ndarray  # (n, 4) x, y, w, h; zeros when unknown
    hues_deg: FloatArray  # (n,) learned colours, NaN until learned

    @property
    def ready(self) -> bool:
        return self.phase == "tracking"


@dataclass
class _Follower:
    track: Track | None = None
    tracked: bool = False
    path: list[FloatArray] = field(default_factory=list)  # heading phase positions


class VisionPipeline:
    """One leader's vision: feed it frames; it tells you where the followers are."""

    def __init__(
        self,
        n: int,
        gamma: Gamma,
        working_area: WorkingArea,
        detect: DetectSettings,
        image_size: tuple[int, int],
        rng: np.random.Generator,
        settings: PipelineSettings = PipelineSettings(),
        hues_deg: tuple[float, ...] | None = None,
        foreign_hues_deg: tuple[float, ...] = (),
    ) -> None:
        """``hues_deg``: the followers' marker hues when they are known (start-up by ``find``
        instead of probing); ``foreign_hues_deg``: other robots' markers that may be in view
        (another team's), never taken for a follower's."""
        if hues_deg is not None and len(hues_deg) != n:
            raise ValueError(f"{len(hues_deg)} known hues for {n} followers")
        self.n = n
        self.given_hues = None if hues_deg is None else tuple(float(h) for h in hues_deg)
        self.foreign_hues = tuple(float(h) for h in foreign_hues_deg)
        self.gamma = gamma
        self.area = working_area
        self.detect = detect
        self.settings = settings
        self.rng = rng
        width, height = image_size
        self.center = (gamma.cx, gamma.cy)
        self.mask = working_area.mask(width, height, self.center)
        ys, xs = np.nonzero(self.mask)
        self._area_box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1) if len(xs) else (0, 0, 0, 0)
        self.followers = [_Follower() for _ in range(n)]
        # per follower, one row each, so a frame's arithmetic is done for the team at once:
        self.positions = np.full((n, 2), np.nan)  # leader frame, m; NaN until first seen
        self.headings = HeadingBank(n, math.radians(settings.kalman_process_deg),
                                    math.radians(settings.kalman_measurement_deg))
        # eq. 34-37 anchors: the point of the last heading measurement (current leader frame),
        # and the follower's commanded turn and travel since then
        self._anchor = np.full((n, 2), np.nan)
        self._anchor_turn = np.zeros(n)
        self._anchor_travel = np.zeros(n)
        self.phase: Phase = "base" if self.given_hues is None else "find"
        self.probing = -1
        self._timer = 0.0
        self._stage: Stage = "settle"
        self._acc: BackgroundAccumulator | None = None
        self._base: np.ndarray | None = None

    # -- helpers -------------------------------------------------------------------------

    def _to_leader(self, u: float, v: float) -> FloatArray:
        return self.gamma.pixel_to_leader(np.array(u), np.array(v))

    def _set_anchor(self, i: int) -> None:
        self._anchor[i] = self.positions[i]
        self._anchor_turn[i] = 0.0
        self._anchor_travel[i] = 0.0

    def _marker_hue(self, k: int) -> float:
        """Follower k's hue: learned, else given, else NaN (not known yet)."""
        track = self.followers[k].track
        if track is not None:
            return track.hue_deg
        return self.given_hues[k] if self.given_hues is not None else math.nan

    def _known_hues(self, but: int | None = None) -> tuple[float, ...]:
        """The hues of every marker known (but follower ``but``'s): the followers' and the
        foreign ones."""
        own = (self._marker_hue(k) for k in range(self.n) if k != but)
        return tuple(h for h in own if math.isfinite(h)) + self.foreign_hues

    def _learn(self, frame: Image, bbox: tuple[int, int, int, int], i: int) -> Track | None:
        """Follower i's rectangle at the motion blob: its window and hue histogram.

        The blob is where the robot was and now is; a dark-blue rectangle on a dark body can
        hardly change the grey image, so the rectangle is looked for around the blob too.
        Another follower's marker near it (one standing behind the other) is told apart by the
        hues already learned: pieces nearest another's hue are neither merged with it nor taken
        for it, and its pixels stay out of this follower's colour.
        """
        x, y, w, h = bbox
        pad = 6 + int(0.6 * max(w, h))
        hgt, wid = frame.shape[:2]
        x0, y0 = max(0, x - pad), max(0, y - pad)
        x1, y1 = min(wid, x + w + pad), min(hgt, y + h + pad)
        roi = frame[y0:y1, x0:x1]
        hsv = cv2.cvtColor(roi, cv2.COLOR_BGR2HSV)
        others = self._known_hues(i)
        blobs = find_blobs(roi, self.mask[y0:y1, x0:x1], self.detect, hsv=hsv, known_hues=others)
        blobs = [b for b in blobs if not others
                 or hue_distance_deg(b.hue_deg, others[nearest_hue(b.hue_deg, others)]) >= MIN_HUE_SEPARATION_DEG / 2]
        if not blobs:
            return None
        cx, cy = x + w / 2 - x0, y + h / 2 - y0
        best = max(blobs, key=lambda b: b.area_px / (1.0 + math.hypot(b.u - cx, b.v - cy) / max(w, h)))
        bx, by, bw, bh = best.bbox
        sat = saturated_mask(hsv, self.mask[y0:y1, x0:x1], self.detect)
        hue = hsv[..., 0].astype(np.float64) * 2.0
        near = np.minimum(np.abs(hue - best.hue_deg), 360.0 - np.abs(hue - best.hue_deg)) <= self.settings.hue_tolerance_deg
        sel = np.zeros(sat.shape, np.uint8)
        sel[by:by + bh, bx:bx + bw] = 255
        for other in others:  # a pixel nearer another follower's hue is that follower's
            near &= np.minimum(np.abs(hue - best.hue_deg), 360.0 - np.abs(hue - best.hue_deg)) \
                < np.minimum(np.abs(hue - other), 360.0 - np.abs(hue - other))
        m = cv2.bitwise_and(sat, sel)
        m[~near] = 0
        hist = hue_histogram(hsv, m)
        return Track(hist, best.hue_deg, (x0 + bx - 2, y0 + by - 2, bw + 4, bh + 4), float(best.area_px),
                     u=x0 + best.u, v=y0 + best.v, mass_px=float(best.area_px))

    def _keep_colours_apart(self) -> None:
        """Each tracker's back-projection counts only hues nearer its own colour than any other
        follower's: two markers close in hue never pull one window (core.vision.tracking)."""
        hues = [f.track.hue_deg if f.track is not None else math.nan for f in self.followers]
        for i, f in enumerate(self.followers):
            if f.track is not None:
                f.track.keep_apart(tuple(h for k, h in enumerate(hues) if k != i and math.isfinite(h)) + self.foreign_hues)

    def _track_all(self, frame: Image) -> None:
        """CAMSHIFT every follower that has a colour; update position and tracked.

        The image work is per follower; the checks and Γ run once for all of them."""
        s = self.settings
        idx = [i for i, f in enumerate(self.followers) if f.track is not None and f.tracked]
        if not idx:
            return
        seen = np.zeros(len(idx), dtype=bool)
        uv = np.zeros((len(idx), 2))
        strong = np.zeros(len(idx), dtype=bool)
        for k, i in enumerate(idx):
            t = self.followers[i].track
            assert t is not None
            seen[k] = camshift(frame, t, self.mask, self.detect, s.roi_margin_px)
            uv[k] = (t.u, t.v)
            strong[k] = t.mass_px >= s.min_mass_fraction * t.area_px
        inside = self.area.contains(uv[:, 0], uv[:, 1], self.center)
        good = seen & strong & inside
        rows = np.asarray(idx)[good]
        if len(rows):
            self.positions[rows] = self.gamma.pixel_to_leader(uv[good, 0], uv[good, 1])
        for k, i in enumerate(idx):
            t = self.followers[i].track
            assert t is not None
            if good[k]:
                t.misses = 0
                continue
            t.misses += 1
            if t.misses >= s.lost_after_frames or (seen[k] and not inside[k]):
                self.followers[i].tracked = False

    def _blobs(self, frame: Image) -> list[Blob]:
        """Every colour blob in the whole working area, pieces nearest different known markers
        never joined."""
        return find_blobs(np.asarray(frame), self.mask, self.detect, known_hues=self._known_hues())

    def _search_lost(self, lost: list[int], blobs: list[Blob]) -> None:
        """Look for lost followers ``lost`` among the frame's ``blobs`` by colour (§3.3, recovery)."""
        owners = [k for k, f in enumerate(self.followers) if f.track is not None]
        # a blob nearest a foreign hue (another team's robot) is nobody's here: owner -1
        known = tuple(self.followers[k].track.hue_deg for k in owners) + self.foreign_hues  # type: ignore[union-attr]
        owners += [-1] * len(self.foreign_hues)
        taken = [f.track.window for f in self.followers if f.track is not None and f.tracked]
        for i in lost:
            f = self.followers[i]
            t = f.track
            assert t is not None
            cands = [b for b in blobs if hue_distance_deg(b.hue_deg, t.hue_deg) <= self.settings.hue_tolerance_deg
                     and owners[nearest_hue(b.hue_deg, known)] == i
                     and b.area_px >= self.settings.min_mass_fraction * t.area_px
                     and not any(_overlaps(b.bbox, w) for w in taken)]
            if not cands:
                continue
            best = max(cands, key=lambda b: b.area_px)
            bx, by, bw, bh = best.bbox
            t.window = (bx - 2, by - 2, bw + 4, bh + 4)
            t.u, t.v, t.misses = best.u, best.v, 0
            f.tracked = True
            self.positions[i] = self._to_leader(best.u, best.v)
            if self.headings.active[i]:
                self._set_anchor(i)
            taken.append(t.window)

    def _find_by_hue(self, frame: Image, ids: list[int], blobs: list[Blob]) -> list[int]:
        """Look for followers ``ids`` (no colour learned yet) by their given hues among the
        frame's ``blobs``; learn the window and colour of each found. Returns the ones found."""
        assert self.given_hues is not None
        every = self.given_hues + self.foreign_hues  # follower i is index i here
        taken = [f.track.window for f in self.followers if f.track is not None]
        found = []
        for i in ids:
            cands = [b for b in blobs if nearest_hue(b.hue_deg, every) == i
                     and hue_distance_deg(b.hue_deg, every[i]) <= self.settings.hue_tolerance_deg
                     and not any(_overlaps(b.bbox, w) for w in taken)]
            if not cands:
                continue
            track = self._learn(frame, max(cands, key=lambda b: b.area_px).bbox, i)
            if track is None:
                continue
            f = self.followers[i]
            f.track, f.tracked = track, True
            self.positions[i] = self._to_leader(track.u, track.v)
            taken.append(track.window)
            found.append(i)
        if found:
            self._keep_colours_apart()
        return found

    # -- the state machine ---------------------------------------------------------------

    def step(
        self,
        frame: Image,
        dt: float,
        odometry: tuple[float, float, float] = (0.0, 0.0, 0.0),
        commands: FloatArray | None = None,
        error_norm: FloatArray | None = None,
    ) -> VisionOutput:
        """One frame. ``odometry``: the leader's (dx, dy, γ) since the previous frame (old frame);
        ``commands``: the (v, w) sent to each follower over that interval; ``error_norm``: ‖P̃‖
        per follower for eq. 34."""
        n = self.n
        s = self.settings
        cmd = np.zeros((n, 2)) if commands is None else np.asarray(commands, dtype=np.float64)
        err = np.zeros(n) if error_norm is None else np.asarray(error_norm, dtype=np.float64)
        dx, dy, gamma = odometry
        # everything remembered in the leader frame moves with the leader (eq. 38)
        if dx != 0.0 or dy != 0.0 or gamma != 0.0:
            both = reexpress_in_new_frame(np.concatenate([self.positions, self._anchor]), dx, dy, gamma)
            self.positions, self._anchor = both[:n], both[n:]  # NaN stays NaN
            for f in self.followers:
                if f.path:
                    f.path = list(reexpress_in_new_frame(np.array(f.path), dx, dy, gamma))
        self._timer += dt
        manoeuvre = np.zeros((n, 2))  # start-up commands (none once tracking)
        tracking = False
        measured = np.full(n, np.nan)

        if self.phase == "find":  # known hues: everyone waits while the team is found by colour
            self._find_by_hue(frame, [i for i, f in enumerate(self.followers) if f.track is None], self._blobs(frame))
            if all(f.track is not None for f in self.followers) or self._timer >= s.find_timeout_s:
                self.phase = "heading"
                self._next_stage("move")
        elif self.phase == "base":
            self._collect_background(frame, first=True)
        elif self.phase == "probe":
            i = self.probing
            if self._stage == "move":
                manoeuvre[i] = (s.probe_speed_mps, 0.0)
                if self._timer >= s.probe_s:
                    self._next_stage("settle")
            else:
                self._collect_background(frame, first=False)
        elif self.phase == "heading":
            self._track_all(frame)
            for i, f in enumerate(self.followers):
                if f.tracked:
                    f.path.append(self.positions[i].copy())
            if self._stage == "move":
                for i, f in enumerate(self.followers):
                    if f.track is not None:
                        manoeuvre[i] = (s.heading_speed_mps, 0.0)
                if self._timer >= s.heading_s:
                    self._next_stage("settle")
            elif self._timer >= s.settle_s:
                self._finish_headings()
        else:
            tracking = True
            self._track_all(frame)
            # by index: comparing followers (dataclasses holding arrays) with == is no way to find one
            lost = [i for i, f in enumerate(self.followers) if f.track is not None and not f.tracked]
            # known hues: one not found at the start-up (hidden then) is looked for by hue
            missing = [i for i, f in enumerate(self.followers) if f.track is None] if self.given_hues is not None else []
            if lost or missing:  # one search of the whole frame serves both
                blobs = self._blobs(frame)
                if lost:
                    self._search_lost(lost, blobs)
                for i in self._find_by_hue(frame, missing, blobs) if missing else ():
                    self._start_heading(i, math.pi / 2)  # not seen moving: assumed aligned; the first arc corrects it
            started = self.headings.active
            self._anchor_turn += np.where(started, cmd[:, 1] * dt, 0.0)
            self._anchor_travel += np.where(started, cmd[:, 0] * dt, 0.0)
            self.headings.predict(cmd[:, 1] * dt - gamma, dt)
            tracked = started & np.array([f.tracked for f in self.followers], dtype=bool)
            z = arc_measurements(self._anchor, self._anchor_turn, self._anchor_travel, self.positions, err)
            new = np.flatnonzero(tracked & np.isfinite(z))
            if len(new):
                self.headings.update(new, z[new])
                measured[new] = z[new]  # shown raw, fused or not (paper fig. 20: raw vs filtered)
                for k in new:
                    self._set_anchor(int(k))

        return VisionOutput(
            phase=self.phase,
            probing=self.probing if self.phase == "probe" else -1,
            positions=self.positions.copy(),
            headings=self.headings.headings,
            heading_measured=measured,
            tracked=np.array([f.tracked for f in self.followers], dtype=bool)
            & (self.headings.active if self.phase == "tracking" else True),
            manoeuvre=None if tracking else manoeuvre,
            windows=np.array([f.track.window if f.track is not None else (0, 0, 0, 0) for f in self.followers],
                             dtype=np.int64).reshape(n, 4),
            hues_deg=np.array([f.track.hue_deg if f.track is not None else np.nan for f in self.followers]),
        )

    def resume_tracking(self, frame: Image, windows: IntArray, headings: FloatArray) -> BoolArray:
        """Enter formation tracking (§3.3) from a known state instead of the start-up: each
        follower's colour is learned again from ``frame`` at its window (pixels x, y, w, h)
        and its Kalman filter starts at ``headings`` (rad). Used to re-run a recording's frames
        with other settings. Returns which followers were found."""
        found = np.zeros(self.n, dtype=bool)
        for i, f in enumerate(self.followers):
            x, y, w, h = (int(v) for v in windows[i])
            track = self._learn(frame, (x, y, w, h), i) if w > 0 and h > 0 else None
            if track is None or not math.isfinite(float(headings[i])):
                continue
            f.track, f.tracked = track, True
            self.positions[i] = self._to_leader(track.u, track.v)
            self._start_heading(i, float(headings[i]))
            found[i] = True
        self._keep_colours_apart()
        self._enter_tracking()
        return found

    def _start_heading(self, i: int, a0: float) -> None:
        """Follower i's Kalman filter on its heading starts at a0; eq. 34-37 measure from here."""
        self.headings.start(i, a0, math.radians(self.settings.kalman_sigma0_deg))
        self._set_anchor(i)

    def _enter_tracking(self) -> None:
        self.phase, self.probing = "tracking", -1
        self._next_stage("run")

    def _next_stage(self, stage: Stage) -> None:
        self._stage = stage
        self._timer = 0.0

    def _collect_background(self, frame: Image, first: bool) -> None:
        s = self.settings
        if self._stage == "settle":
            if self._timer >= s.settle_s:
                self._next_stage("collect")
                self._acc = BackgroundAccumulator(self.mask)
            return
        assert self._acc is not None
        x0, y0, x1, y1 = self._area_box  # only the working area counts: no need for the rest
        self._acc.add(frame[y0:y1, x0:x1], (x0, y0))
        if self._acc.count < s.background_frames:
            return
        background = self._acc.mean()
        if not first:
            assert self._base is not None
            i = self.probing
            blob = motion_blob(self._base, background, self.mask, s.diff_threshold, s.min_blob_px,
                               self.detect.merge_distance_px)
            if blob is not None:
                track = self._learn(frame, blob.bbox, i)
                if track is not None:
                    f = self.followers[i]
                    f.track = track
                    f.tracked = True
                    self.positions[i] = self._to_leader(track.u, track.v)
                    self._keep_colours_apart()
        self._base = background  # the discriminant is the next follower's base
        if self.probing + 1 < self.n:
            self.phase = "probe"
            self.probing += 1
            self._next_stage("move")
        else:
            self.phase = "heading"
            self.probing = -1
            self._next_stage("move")

    def _finish_headings(self) -> None:
        s = self.settings
        for i, f in enumerate(self.followers):
            if f.track is None:
                continue
            if len(f.path) >= 3:
                a0 = fit_heading_line(np.array(f.path), self.rng, tolerance_m=s.ransac_tolerance_m).heading
            else:
                a0 = math.pi / 2  # not seen moving: assume aligned; the first arc will correct it
            self._start_heading(i, a0)
            f.path = []
        self._enter_tracking()


def _overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return not (a[0] + a[2] <= b[0] or b[0] + b[2] <= a[0] or a[1] + a[3] <= b[1] or b[1] + b[3] <= a[1])


def heading_error(estimate: FloatArray, truth: FloatArray) -> FloatArray:
    return np.asarray(wrap_angle(np.asarray(estimate) - np.asarray(truth)))


# Allowed ranges of the settings a user may change (rerun --pipeline-config): (lo, hi, unit).
PIPELINE_BOUNDS: dict[str, tuple[float, float, str]] = {
    "background_frames": (1, 120, "frames"),
    "settle_s": (0.0, 10.0, "s"),
    "probe_speed_mps": (0.005, 0.5, "m/s"),
    "probe_s": (0.05, 10.0, "s"),
    "heading_speed_mps": (0.005, 0.5, "m/s"),
    "heading_s": (0.1, 20.0, "s"),
    "diff_threshold": (1.0, 255.0, "grey levels"),
    "min_blob_px": (1, 100_000, "px"),
    "lost_after_frames": (1, 1000, "frames"),
    "min_mass_fraction": (0.0, 1.0, ""),
    "roi_margin_px": (0, 400, "px"),
    "hue_tolerance_deg": (0.5, 90.0, "deg"),
    "ransac_tolerance_m": (0.0005, 0.2, "m"),
    "kalman_sigma0_deg": (0.01, 180.0, "deg"),
    "kalman_process_deg": (0.01, 180.0, "deg per sqrt(s)"),
    "kalman_measurement_deg": (0.01, 180.0, "deg"),
}


def parse_pipeline_settings(text: str, source: str, base: PipelineSettings = PipelineSettings()) -> PipelineSettings:
    """A ``[pipeline]`` TOML table over ``base``; ConfigError (one line) for anything else."""
    from core.config import Table, toml_loads

    top = Table(toml_loads(text, source), source, "")
    table = top.table("pipeline", optional=False)
    changes: dict[str, float | int] = {}
    for name, (lo, hi, unit) in PIPELINE_BOUNDS.items():
        if not table.has(name):
            continue
        if isinstance(getattr(base, name), int):
            changes[name] = table.integer(name, int(lo), int(hi))
        else:
            changes[name] = table.number(name, lo, hi, unit=unit)
    table.finish()
    top.finish()
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]  # each value was read with its field's type and bounds above
