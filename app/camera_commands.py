"""`omniformation render`, `calibrate` and `locate`: the camera commands (arguments in app.camera_cli)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np

from app.camera_files import SYNTHETIC_CAMERA, check_out_path, load_camera, load_table, read_image, write_table
from app.paths import UserError, display_path
from core.camera.config import WorkingArea, gamma_toml
from core.camera.gamma import CalibrationError, GammaFit, fit_gamma
from core.camera.synthetic import renderer_for, synthetic_table
from core.config import ConfigError
from core.vision.blobs import find_blobs


def cmd_render(args: argparse.Namespace) -> int:
    from app.scenarios import load_scenario
    from core.sim.run import simulate

    scenario = load_scenario(args.scenario)
    camera = load_camera(args.camera)
    check_out_path(args.out)
    try:
        renderer = renderer_for(camera)
    except CalibrationError as exc:
        raise UserError(str(exc)) from None
    if args.t > scenario.duration_s:
        raise UserError(f"--t {args.t:g}: the scenario {scenario.name} lasts {scenario.duration_s:g} s")
    if args.t > 0:
        log = simulate(scenario.replace(duration_s=args.t))
        leader = log.leader[-1]
        followers = np.column_stack([log.p[-1], log.a[-1]])
        t = float(log.t[-1])
    else:
        leader = np.array([0.0, 0.0, math.pi / 2])
        followers = np.column_stack([scenario.initial_p, scenario.initial_a])
        t = 0.0
    rng = np.random.default_rng(args.seed if args.seed is not None else scenario.seed)
    frame = renderer.render(leader, followers, t, rng)
    if not cv2.imwrite(str(args.out), frame):
        raise UserError(f"{args.out}: OpenCV cannot write this file type (use .png or .jpg)")
    print(f"wrote {display_path(args.out)}: {scenario.name} at t = {t:.2f} s, {len(followers)} followers,"
          f" {frame.shape[1]}x{frame.shape[0]}")
    return 0


def _report(fit: GammaFit) -> None:
    g = fit.gamma
    how = "estimated from the markers" if fit.center_estimated else "given"
    print(f"image centre ({g.cx:.2f}, {g.cy:.2f}) px ({how}); {g.n_sectors} sectors, degree {g.degree};"
          f" radii {g.r_min_px:.1f}..{g.r_max_px:.1f} px")
    print("sector  markers  residual RMS  max      bearing correction")
    for s in fit.sectors:
        print(f"{s.bearing_deg:6.1f}  {s.points:7d}  {s.rms_cm:8.2f} cm  {s.max_cm:5.2f} cm  {s.bearing_correction_deg:+7.2f} deg")


def cmd_calibrate(args: argparse.Namespace) -> int:
    if (args.table is None) == (args.synthetic is None):
        raise UserError("give either TABLE.csv or --synthetic CAMERA.toml (not both)")
    check_out_path(args.out)
    if args.save_table is not None:
        check_out_path(args.save_table)
    if args.synthetic is not None:
        camera = load_camera(args.synthetic)
        try:
            table = synthetic_table(camera, np.random.default_rng(args.seed))
        except CalibrationError as exc:
            raise UserError(str(exc)) from None
        model = camera.model
        assert model is not None
        source = display_path(args.synthetic)
        working_area, detect = camera.working_area, camera.detect
        degree = args.degree if args.degree is not None else camera.calibration.degree
        flip = args.flip or model.flip
        offset = args.bearing_offset if args.bearing_offset is not None else model.bearing_offset_deg
        print(f"{source}: rendered {len(table)} markers at {len(camera.calibration.bearings_deg)} bearings")
    else:
        table = load_table(args.table)
        source = display_path(args.table)
        working_area, detect = None, None
        degree = args.degree if args.degree is not None else 3
        flip = args.flip
        offset = args.bearing_offset if args.bearing_offset is not None else 0.0
    try:
        fit = fit_gamma(table, center=tuple(args.center) if args.center else None, sectors=args.sectors,
                        degree=degree, bearing_offset_deg=offset, flip=flip, source=source)
    except CalibrationError as exc:
        raise UserError(str(exc)) from None
    _report(fit)
    if working_area is None:
        # the calibrated radii, a little widened: outside them Γ extrapolates
        working_area = WorkingArea(max(0.0, fit.gamma.r_min_px - 5.0), fit.gamma.r_max_px + 5.0)
        from core.camera.config import DetectSettings

        detect = DetectSettings()
    assert detect is not None
    header = (f"Camera calibration (Γ, paper §3) made by: omniformation calibrate from {source}\n"
              f"{fit.gamma.n_sectors} sectors, degree {fit.gamma.degree}; worst sector residual RMS"
              f" {max(s.rms_cm for s in fit.sectors):.2f} cm")
    args.out.write_text(gamma_toml(fit.gamma, working_area, detect, header), encoding="utf-8")
    print(f"wrote {display_path(args.out)}")
    if args.save_table is not None:
        write_table(table, args.save_table)
        print(f"wrote {display_path(args.save_table)}")
    return 0


def cmd_locate(args: argparse.Namespace) -> int:
    camera = load_camera(args.camera)
    try:
        gamma = camera.require_gamma()
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    image = read_image(args.image)
    h, w = image.shape[:2]
    if not (0 <= gamma.cx < w and 0 <= gamma.cy < h):
        raise UserError(f"{display_path(args.image)}: {w}x{h} does not contain the calibrated image centre"
                        f" ({gamma.cx:.1f}, {gamma.cy:.1f}); wrong camera file?")
    area = camera.working_area.mask(w, h, (gamma.cx, gamma.cy))
    blobs = find_blobs(image, area, camera.detect)
    for b in sorted(blobs, key=lambda b: -b.area_px):
        xy = gamma.pixel_to_leader(np.array(b.u), np.array(b.v))
        print(json.dumps({"hue_deg": round(b.hue_deg, 1), "pixel": [round(b.u, 2), round(b.v, 2)],
                          "area_px": b.area_px, "x": round(float(xy[0]), 4), "y": round(float(xy[1]), 4)}))
    return 0
