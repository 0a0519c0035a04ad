"""Camera config files (static_config/camera/*.toml): parse, validate, write back.

One file describes one rig. Sections (all optional except ``working_area``):

- ``[model]``: the synthetic camera (unified sphere model and its flaws) — only for simulation;
- ``[render]``: how synthetic frames look;
- ``[working_area]``: the annulus (pixels about the image centre) where followers are looked for (paper fig. 8);
- ``[detect]``: what counts as a marker colour blob;
- ``[calibration]``: where ``calibrate --synthetic`` places its markers, how many sectors, which degree;
- ``[gamma]``: the fitted Γ (written by ``omniformation calibrate``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.camera.gamma import Gamma
from core.camera.model import CameraModel
from core.camera.render import BoxLook, RenderSettings
from core.config import ConfigError, Table, toml_loads
from core.types import FloatArray


@dataclass(frozen=True)
class WorkingArea:
    """The annulus between inner and outer radius (pixels) about the image centre."""

    inner_px: float = 55.0
    outer_px: float = 195.0

    def mask(self, width: int, height: int, center: tuple[float, float]) -> np.ndarray:
        """uint8 mask (255 inside) of this annulus in an image of the given size."""
        vv, uu = np.mgrid[0:height, 0:width]
        r = np.hypot(uu - center[0], vv - center[1])
        return ((r >= self.inner_px) & (r <= self.outer_px)).astype(np.uint8) * 255

    def contains(self, u: FloatArray, v: FloatArray, center: tuple[float, float], margin_px: float = 0.0) -> np.ndarray:
        r = np.hypot(np.asarray(u) - center[0], np.asarray(v) - center[1])
        return (r >= self.inner_px - margin_px) & (r <= self.outer_px + margin_px)


@dataclass(frozen=True)
class DetectSettings:
    """A marker blob: saturated and bright enough, big enough; same-hue pieces merged."""

    min_saturation: int = 90  # 0..255 (OpenCV HSV)
    min_value: int = 50
    min_area_px: int = 12
    merge_distance_px: float = 12.0  # same-hue blobs closer than this are one rectangle (fig. 10)
    merge_hue_deg: float = 8.0  # a rectangle's pieces differ by a degree or two; under MIN_HUE_SEPARATION_DEG


MIN_HUE_SEPARATION_DEG = 12.0  # two markers' hues at least this far apart (measured: docs/calibration.md)


def hue_distance_deg(a: float, b: float) -> float:
    """The angle between two hues on the colour circle, degrees in [0, 180]."""
    d = abs((a - b) % 360.0)
    return min(d, 360.0 - d)


def too_close_hues(hues_deg: tuple[float, ...] | list[float],
                   min_deg: float = MIN_HUE_SEPARATION_DEG) -> tuple[int, int] | None:
    """The first pair of indices whose hues are closer than ``min_deg``, or None."""
    for i in range(len(hues_deg)):
        for j in range(i + 1, len(hues_deg)):
            if hue_distance_deg(hues_deg[i], hues_deg[j]) < min_deg:
                return i, j
    return None


def check_team_hues(hues_deg: tuple[float, ...] | list[float], where: str) -> None:
    """ValueError (one line) when two markers' hues are closer than MIN_HUE_SEPARATION_DEG."""
    pair = too_close_hues(hues_deg)
    if pair is not None:
        i, j = pair
        raise ValueError(f"{where}: markers {i + 1} and {j + 1} have hues {hues_deg[i]:g} and {hues_deg[j]:g} deg,"
                         f" {hue_distance_deg(hues_deg[i], hues_deg[j]):g} deg apart; two markers need at least"
                         f" {MIN_HUE_SEPARATION_DEG:g} deg (one behind the other they would look like one robot)")


@dataclass(frozen=True)
class CalibrationPlan:
    """Where ``calibrate --synthetic`` puts markers (leader frame) and how it fits them."""

    bearings_deg: tuple[float, ...] = tuple(float(b) for b in range(0, 360, 45))
    distances_m: tuple[float, ...] = tuple(round(0.25 + 0.1 * i, 2) for i in range(15))
    degree: int = 3


@dataclass(frozen=True)
class CaptureSettings:
    """What a real camera is set to when it opens (``[capture]``): nothing the tracker depends on
    is left to float. Automatic exposure and white balance move the hues and brightness the
    tracker and the background model learnt; a driver's frame queue hands the loop old frames.
    A key left out is left as the camera has it (the page then says "not locked")."""

    width: int | None = None
    height: int | None = None
    fps: float | None = None
    pixel_format: str | None = None  # FOURCC, e.g. "MJPG" or "YUYV"
    exposure: float | None = None  # manual exposure, in the driver's units (V4L2: 100 µs); auto exposure off
    gain: float | None = None
    white_balance_k: float | None = None  # manual white balance (kelvin); auto white balance off
    buffer_size: int | None = 1  # frames the driver may queue: 1, the newest

    def asked(self) -> dict[str, float | str]:
        """The settings given, by name (what the page and the recording show as "asked")."""
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass(frozen=True)
class CameraConfig:
    source: str
    working_area: WorkingArea
    detect: DetectSettings = DetectSettings()
    model: CameraModel | None = None
    render: RenderSettings = RenderSettings()
    calibration: CalibrationPlan = CalibrationPlan()
    gamma: Gamma | None = None
    capture: CaptureSettings | None = None  # a real camera's settings ([capture]); None: as the camera has them
    lighting: tuple[float, float, float] | None = None  # the floor's light at calibration ([lighting]): value, b/g, r/g

    @property
    def center(self) -> tuple[float, float]:
        """The image centre: Γ's when calibrated, else the synthetic model's principal point."""
        if self.gamma is not None:
            return (self.gamma.cx, self.gamma.cy)
        if self.model is not None:
            return self.model.center
        raise ConfigError(f"{self.source}: neither [gamma] nor [model]: the image centre is unknown")

    def require_gamma(self) -> Gamma:
        if self.gamma is None:
            raise ConfigError(f"{self.source}: has no [gamma] section; make one with omniformation calibrate")
        return self.gamma


def _number_list(t: Table, name: str, lo: float, hi: float, min_len: int, default: tuple[float, ...] | None = None,
                 unit: str = "") -> tuple[float, ...]:
    if default is not None and not t.has(name):
        t.used.add(name)
        return default
    value = t.raw(name)
    allowed = f"a list of at least {min_len} numbers in [{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")
    if (not isinstance(value, list) or len(value) < min_len
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(float(x))
                       and lo <= float(x) <= hi for x in value)):
        raise t.fail(name, value, allowed)
    return tuple(float(x) for x in value)


def _parse_model(t: Table) -> CameraModel:
    width = t.integer("width", 64, 4096)
    height = t.integer("height", 48, 4096)
    model = CameraModel(
        width=width,
        height=height,
        xi=t.number("xi", 0.0, 1.0, lo_open=True),
        gamma_px=t.number("gamma_px", 1.0, 1e5, unit="px"),
        cx=t.number("cx", 0.0, float(width), unit="px"),
        cy=t.number("cy", 0.0, float(height), unit="px"),
        mirror_height_m=t.number("mirror_height_m", 0.05, 5.0, unit="m"),
        tilt_deg=t.number("tilt_deg", 0.0, 10.0, default=0.0, unit="deg"),
        tilt_bearing_deg=t.number("tilt_bearing_deg", -360.0, 360.0, default=0.0, unit="deg"),
        bearing_offset_deg=t.number("bearing_offset_deg", -360.0, 360.0, default=0.0, unit="deg"),
        flip=t.flag("flip", False),
        rim_elevation_deg=t.number("rim_elevation_deg", -30.0, 30.0, default=2.0, unit="deg"),
        body_radius_m=t.number("body_radius_m", 0.0, 2.0, default=0.25, unit="m"),
    )
    t.finish()
    return model


def _parse_render(t: Table) -> RenderSettings:
    d = RenderSettings()
    hues = _number_list(t, "hues_deg", 0.0, 360.0, 1, default=d.hues_deg, unit="deg")
    try:
        check_team_hues(hues, t.key("hues_deg"))
    except ValueError as exc:
        raise ConfigError(f"{t.source}: {exc}") from None
    fl = t.table("follower")
    follower = BoxLook(
        length_m=fl.number("length_m", 0.02, 2.0, default=d.follower.length_m, unit="m"),
        width_m=fl.number("width_m", 0.02, 2.0, default=d.follower.width_m, unit="m"),
        height_m=fl.number("height_m", 0.0, 2.0, default=d.follower.height_m, unit="m"),
        top_length_m=fl.number("top_length_m", 0.01, 2.0, default=d.follower.top_length_m, unit="m"),
        top_width_m=fl.number("top_width_m", 0.01, 2.0, default=d.follower.top_width_m, unit="m"),
    )
    fl.finish()
    settings = RenderSettings(
        hues_deg=hues,
        marker_saturation=t.number("marker_saturation", 0.0, 1.0, default=d.marker_saturation),
        marker_value=t.number("marker_value", 0.0, 1.0, default=d.marker_value),
        follower=follower,
        noise_sigma=t.number("noise_sigma", 0.0, 50.0, default=d.noise_sigma, unit="grey levels"),
        blur_sigma_px=t.number("blur_sigma_px", 0.0, 5.0, default=d.blur_sigma_px, unit="px"),
        jpeg_quality=t.integer("jpeg_quality", 0, 100, default=d.jpeg_quality),
        drift_gain=t.number("drift_gain", 0.0, 0.9, default=d.drift_gain),
        drift_offset=t.number("drift_offset", 0.0, 100.0, default=d.drift_offset, unit="grey levels"),
        drift_period_s=t.number("drift_period_s", 0.0, 1e6, default=d.drift_period_s, unit="s"),
        clutter=t.flag("clutter", d.clutter),
        distractor=t.flag("distractor", d.distractor),
        distractor_hue_deg=t.number("distractor_hue_deg", 0.0, 360.0, default=d.distractor_hue_deg, unit="deg"),
        clutter_period_m=t.number("clutter_period_m", 1.0, 100.0, default=d.clutter_period_m, unit="m"),
        floor_far_m=t.number("floor_far_m", 0.5, 100.0, default=d.floor_far_m, unit="m"),
        texture_seed=t.integer("texture_seed", 0, 2**32 - 1, default=d.texture_seed),
    )
    if follower.top_length_m > follower.length_m or follower.top_width_m > follower.width_m:
        raise fl.fail("top_length_m", follower.top_length_m, "no larger than the body (length_m, width_m)")
    t.finish()
    return settings


def _parse_gamma(t: Table) -> Gamma:
    cx = t.number("cx", -1e5, 1e5, unit="px")
    cy = t.number("cy", -1e5, 1e5, unit="px")
    flip = t.flag("flip", False)
    offset = math.radians(t.number("bearing_offset_deg", -360.0, 360.0, default=0.0, unit="deg"))
    r_min = t.number("r_min_px", 0.0, 1e5, unit="px")
    r_max = t.number("r_max_px", 0.0, 1e5, unit="px")
    if r_max <= r_min:
        raise t.fail("r_max_px", r_max, f"> r_min_px ({r_min:g})")
    sectors = t.tables("sectors")
    if not sectors:
        raise t.fail("sectors", [], "at least one [[gamma.sectors]] table")
    bearings, coeffs, corrections = [], [], []
    for st in sectors:
        bearings.append(math.radians(st.number("image_bearing_deg", -180.0, 180.0, unit="deg")))
        coeffs.append(_number_list(st, "coeffs", -1e6, 1e6, 2))
        corrections.append(math.radians(st.number("bearing_correction_deg", -45.0, 45.0, unit="deg")))
        st.finish()
    if len({len(c) for c in coeffs}) != 1:
        raise t.fail("sectors", [len(c) for c in coeffs], "sectors whose coeffs lists have one length (one degree)")
    if bearings != sorted(bearings) or len(set(bearings)) != len(bearings):
        raise t.fail("sectors", [round(math.degrees(b), 3) for b in bearings], "in increasing image_bearing_deg order")
    t.finish()
    return Gamma(cx, cy, flip, offset, np.array(bearings), np.array(coeffs), np.array(corrections), r_min, r_max)


def parse_camera(text: str, source: str) -> CameraConfig:
    top = Table(toml_loads(text, source), source, "")
    model = _parse_model(top.table("model", optional=False)) if top.has("model") else None
    top.used.add("model")
    render = _parse_render(top.table("render"))
    wa = top.table("working_area", optional=False)
    inner = wa.number("inner_px", 0.0, 1e5, unit="px")
    outer = wa.number("outer_px", 0.0, 1e5, lo_open=True, unit="px")
    if outer <= inner:
        raise wa.fail("outer_px", outer, f"> inner_px ({inner:g})")
    wa.finish()
    dt = top.table("detect")
    dd = DetectSettings()
    detect = DetectSettings(
        min_saturation=dt.integer("min_saturation", 0, 255, default=dd.min_saturation),
        min_value=dt.integer("min_value", 0, 255, default=dd.min_value),
        min_area_px=dt.integer("min_area_px", 1, 10**7, default=dd.min_area_px),
        merge_distance_px=dt.number("merge_distance_px", 0.0, 1e4, default=dd.merge_distance_px, unit="px"),
        merge_hue_deg=dt.number("merge_hue_deg", 0.0, MIN_HUE_SEPARATION_DEG - 2.0, default=dd.merge_hue_deg, unit="deg"
                                " (under the smallest hue separation of two markers, so two are never one blob)"),
    )
    dt.finish()
    ct = top.table("calibration")
    dc = CalibrationPlan()
    plan = CalibrationPlan(
        bearings_deg=_number_list(ct, "bearings_deg", -360.0, 360.0, 1, default=dc.bearings_deg, unit="deg"),
        distances_m=_number_list(ct, "distances_m", 0.01, 100.0, 2, default=dc.distances_m, unit="m"),
        degree=ct.integer("degree", 1, 7, default=dc.degree),
    )
    ct.finish()
    gamma = _parse_gamma(top.table("gamma", optional=False)) if top.has("gamma") else None
    top.used.add("gamma")
    capture = _parse_capture(top.table("capture", optional=False)) if top.has("capture") else None
    top.used.add("capture")
    lighting = None
    if top.has("lighting"):
        lt = top.table("lighting", optional=False)
        lighting = (lt.number("floor_value", 0.0, 255.0), lt.number("cast_bg", 0.0, 100.0, lo_open=True),
                    lt.number("cast_rg", 0.0, 100.0, lo_open=True))
        lt.finish()
    top.used.add("lighting")
    top.finish()
    return CameraConfig(source, WorkingArea(inner, outer), detect, model, render, plan, gamma, capture, lighting)


def _parse_capture(t: Table) -> CaptureSettings:
    def opt_int(name: str, lo: int, hi: int) -> int | None:
        return t.integer(name, lo, hi) if t.has(name) else None

    def opt_num(name: str, lo: float, hi: float, unit: str) -> float | None:
        return t.number(name, lo, hi, lo_open=True, unit=unit) if t.has(name) else None

    fourcc = None
    if t.has("pixel_format"):
        fourcc = t.text("pixel_format")
        if not (len(fourcc) == 4 and fourcc.isascii() and fourcc.isprintable()):
            raise t.fail("pixel_format", fourcc, "a four-character code such as \"MJPG\" or \"YUYV\"")
    settings = CaptureSettings(
        width=opt_int("width", 16, 8192), height=opt_int("height", 16, 8192), fps=opt_num("fps", 0.0, 1000.0, "Hz"),
        pixel_format=fourcc, exposure=opt_num("exposure", 0.0, 1e7, "(the driver's units)"),
        gain=t.number("gain", 0.0, 1e4, unit="(the driver's units)") if t.has("gain") else None,
        white_balance_k=t.number("white_balance_k", 1000.0, 15000.0, unit="K") if t.has("white_balance_k") else None,
        buffer_size=t.integer("buffer_size", 1, 32, default=1),
    )
    t.used.update(CaptureSettings.__dataclass_fields__)  # a misspelt key is told the whole list
    t.finish()
    return settings


def _fmt(x: float) -> str:
    return repr(float(x))


def gamma_toml(gamma: Gamma, working_area: WorkingArea, detect: DetectSettings, header: str = "",
               lighting: tuple[float, float, float] | None = None) -> str:
    """A camera.toml for a calibrated rig: Γ, its working area and detection settings, and the
    floor's light it was calibrated in (``lighting``: value, b/g, r/g) when known."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    if lighting is not None:
        lines += ["", "[lighting]  # the floor's light at calibration: a live camera is compared with it",
                  f"floor_value = {_fmt(lighting[0])}", f"cast_bg = {_fmt(lighting[1])}", f"cast_rg = {_fmt(lighting[2])}"]
    lines += [
        "",
        "[working_area]",
        f"inner_px = {_fmt(working_area.inner_px)}",
        f"outer_px = {_fmt(working_area.outer_px)}",
        "",
        "[detect]",
        f"min_saturation = {detect.min_saturation}",
        f"min_value = {detect.min_value}",
        f"min_area_px = {detect.min_area_px}",
        f"merge_distance_px = {_fmt(detect.merge_distance_px)}",
        f"merge_hue_deg = {_fmt(detect.merge_hue_deg)}",
        "",
        "[gamma]",
        f"cx = {_fmt(gamma.cx)}",
        f"cy = {_fmt(gamma.cy)}",
        f"flip = {'true' if gamma.flip else 'false'}",
        f"bearing_offset_deg = {_fmt(math.degrees(gamma.bearing_offset))}",
        f"r_min_px = {_fmt(gamma.r_min_px)}",
        f"r_max_px = {_fmt(gamma.r_max_px)}",
    ]
    for b, c, k in zip(gamma.sector_bearings, gamma.range_coeffs, gamma.bearing_corrections):
        lines += [
            "",
            "[[gamma.sectors]]",
            f"image_bearing_deg = {_fmt(math.degrees(b))}",
            f"coeffs = [{', '.join(_fmt(x) for x in c)}]  # metres = sum c_i (r / 100 px)^i",
            f"bearing_correction_deg = {_fmt(math.degrees(k))}",
        ]
    return "\n".join(lines) + "\n"
