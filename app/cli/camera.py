"""`omniformation render`, `calibrate` and `locate`: the camera commands."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

from app.cli.args import Parser, float_in, int_in, port, seed, token_arg
from app.files import (SYNTHETIC_CAMERA, UserError, check_new_file, display_path, load_camera, load_scenario,
                       load_table, read_image, require_gamma, write_table)

if TYPE_CHECKING:
    from core.camera.gamma import GammaFit, MatchingTable


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    render = sub.add_parser("render", help="write one synthetic camera frame of a scenario",
                            description="Simulate SCENARIO up to --t and write what the leader's camera sees.")
    render.add_argument("scenario", help="scenario name or .toml path")
    render.add_argument("--t", type=float_in(0.0, 86400.0, "s", lo_inclusive=True),
                        default=0.0, help="time in the scenario (s, default 0)")
    render.add_argument("--out", type=Path, required=True, help="image file (.png or .jpg)")
    render.add_argument("--camera", type=Path, default=SYNTHETIC_CAMERA, help="synthetic camera config (default: the built-in rig)")
    render.add_argument("--seed", type=seed, help="noise seed (default: the scenario's)")
    render.set_defaults(func=cmd_render)

    cal = sub.add_parser("calibrate", help="fit Γ (pixel -> metres) from a matching table or the synthetic rig",
                         description="Fit the per-sector Γ polynomials and bearing corrections (paper §3). "
                                     "TABLE.csv has the header bearing_deg,metres,u,v (docs/calibration.md).")
    cal.add_argument("table", nargs="?", type=Path, help="matching table CSV: bearing_deg,metres,u,v")
    cal.add_argument("--synthetic", type=Path, metavar="CAMERA.toml", help="measure the table on the synthetic rig instead")
    cal.add_argument("--center", nargs=2, type=float_in(-100_000.0, 100_000.0, "px", lo_inclusive=True), metavar=("CX", "CY"),
                     help="image centre (px); default: estimated")
    cal.add_argument("--sectors", type=int_in(1, 360), help="number of sectors (default: one per table bearing)")
    cal.add_argument("--degree", type=int_in(1, 7), help="polynomial degree (default 3)")
    cal.add_argument("--bearing-offset", type=float_in(-360.0, 360.0, "deg", lo_inclusive=True), metavar="DEG",
                     help="leader bearing that appears straight up (deg)")
    cal.add_argument("--flip", action="store_true", help="the image is mirrored left/right")
    cal.add_argument("--out", type=Path, help="camera.toml to write (never over an existing file unless --overwrite);"
                                              " with --page, what the page's Save proposes (default camera.toml)")
    cal.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    cal.add_argument("--save-table", type=Path, help="also write the matching table used (CSV)")
    cal.add_argument("--seed", type=seed, default=0, help="noise seed for --synthetic (default 0)")
    cal.add_argument("--propose-centre", type=Path, metavar="IMAGE",
                     help="find the mirror's rim in a picture (from its edges) and print {\"cx\", \"cy\", \"r\"} in"
                          " pixels as one JSON line; what the page's Propose from image does")
    cal.add_argument("--page", action="store_true", help="serve the calibration page: a live camera (--camera) or"
                                                         " the synthetic rig (--synthetic), a guided table, Save")
    cal.add_argument("--camera", metavar="SOURCE", help="--page: a camera index, device, video file or folder")
    cal.add_argument("--tilt", type=float_in(-10.0, 10.0, "deg", lo_inclusive=True),
                     help="--page --synthetic: tilt the rig's mirror this much (a flawed rig to calibrate)")
    cal.add_argument("--off-centre", type=float_in(-50.0, 50.0, "px", lo_inclusive=True), metavar="PX",
                     help="--page --synthetic: move the mirror's centre this far right in the image")
    cal.add_argument("--host", default="127.0.0.1", help="--page: address to serve on (default 127.0.0.1)")
    cal.add_argument("--port", type=port, default=8080, help="--page: port (default 8080)")
    cal.add_argument("--token", type=token_arg, help="--page: the token clients must present (else made up off loopback)")
    cal.set_defaults(func=cmd_calibrate)

    loc = sub.add_parser("locate", help="find the coloured rectangles in one picture and print where they are",
                         description="Print one JSON object per colour blob in the working area: hue, pixel, area, x, y (m, leader frame).")
    loc.add_argument("image", type=Path, help="an omnidirectional picture (PNG, JPEG, ...)")
    loc.add_argument("--camera", type=Path, required=True, help="calibrated camera.toml (from calibrate)")
    loc.set_defaults(func=cmd_locate)


def cmd_render(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from core.camera.gamma import CalibrationError
    from core.camera.synthetic import renderer_for
    from core.sim.run import simulate

    scenario = load_scenario(args.scenario)
    camera = load_camera(args.camera)
    check_new_file(args.out, "image", ".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
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
    try:
        written = cv2.imwrite(str(args.out), frame)
    except cv2.error:
        written = False
    if not written:
        raise UserError(f"{args.out}: OpenCV cannot write this file type (use .png or .jpg)")
    print(f"wrote {display_path(args.out)}: {scenario.name} at t = {t:.2f} s, {len(followers)} followers,"
          f" {frame.shape[1]}x{frame.shape[0]}")
    return 0


def _report(fit: "GammaFit") -> None:
    g = fit.gamma
    how = "estimated from the markers" if fit.center_estimated else "given"
    print(f"image centre ({g.cx:.2f}, {g.cy:.2f}) px ({how}); {g.n_sectors} sectors, degree {g.degree};"
          f" radii {g.r_min_px:.1f}..{g.r_max_px:.1f} px")
    print("sector  markers  residual RMS  max      bearing correction")
    for s in fit.sectors:
        print(f"{s.bearing_deg:6.1f}  {s.points:7d}  {s.rms_cm:8.2f} cm  {s.max_cm:5.2f} cm  {s.bearing_correction_deg:+7.2f} deg")


def _propose_centre(args: argparse.Namespace) -> int:
    """`calibrate --propose-centre IMAGE`: the mirror's rim as one JSON line (core.camera.guide)."""
    import json

    from core.camera.guide import find_mirror_rim

    others = [flag for flag, value in (("TABLE", args.table), ("--synthetic", args.synthetic), ("--out", args.out),
                                       ("--page", args.page or None), ("--camera", args.camera)) if value is not None]
    if others:
        raise UserError(f"--propose-centre takes one picture and nothing else (not {', '.join(others)})")
    image = read_image(args.propose_centre)
    rim = find_mirror_rim(image)
    if rim is None:
        h, w = image.shape[:2]
        raise UserError(f"{display_path(args.propose_centre)}: no mirror rim found in this {w}x{h} picture (no circle"
                        " with an edge along most of its visible arc); set the centre by hand on the calibration page")
    print(json.dumps({"cx": round(rim.cx, 2), "cy": round(rim.cy, 2), "r": round(rim.radius, 2)}))
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    import numpy as np

    from core.camera.config import WorkingArea, gamma_toml
    from core.camera.gamma import CalibrationError, fit_gamma
    from core.camera.synthetic import synthetic_table

    if args.propose_centre is not None:
        return _propose_centre(args)
    if args.page:
        return _calibration_page(args)
    if args.camera is not None or args.tilt is not None or args.off_centre is not None:
        raise UserError("--camera, --tilt and --off-centre go with --page")
    if (args.table is None) == (args.synthetic is None):
        raise UserError("give either TABLE.csv or --synthetic CAMERA.toml (not both)")
    if args.out is None:
        raise UserError("--out camera.toml is needed (the camera file to write)")
    check_new_file(args.out, "camera file", ".toml")
    if args.out.exists() and not args.overwrite:
        raise UserError(f"{args.out}: exists; give another --out, or --overwrite to replace it")
    if args.save_table is not None:
        check_new_file(args.save_table, "matching table", ".csv")
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
        flip, offset = _mounting(table, args, source)
    try:
        fit = fit_gamma(table, center=tuple(args.center) if args.center else None, sectors=args.sectors,
                        degree=degree, bearing_offset_deg=offset, flip=flip, source=source)
    except CalibrationError as exc:
        raise UserError(str(exc)) from None
    _report(fit)
    from core.camera.quality import WARN_CM, coverage_warnings, held_out_error

    held = held_out_error(table, fit.gamma, fit.gamma.degree)
    worst_rms = max(s.rms_cm for s in fit.sectors)
    print(f"held-out error (markers the fit did not see; {held.refits} refits): median {held.median_cm:.2f} cm,"
          f" p95 {held.p95_cm:.2f} cm (the fit's own residuals: worst sector RMS {worst_rms:.2f} cm)")
    warnings = coverage_warnings(table)
    if held.p95_cm > WARN_CM:
        warnings.insert(0, f"positions may be off by more than {WARN_CM:g} cm: held-out p95 {held.p95_cm:.1f} cm;"
                           " measure more bearings or distances (docs/calibration.md)")
    for w in warnings:
        print(f"warning: {w}")
    bad = [s for s in fit.sectors if abs(s.bearing_correction_deg) > 45.0]
    if bad:
        raise UserError(f"{source}: sector at {bad[0].bearing_deg:g} deg needs a bearing correction of"
                        f" {bad[0].bearing_correction_deg:+.1f} deg (at most 45): the camera is turned or mirrored"
                        " otherwise than given; leave out --bearing-offset and --flip to have them read from the table")
    if working_area is None:
        # the calibrated radii, a little widened: outside them Γ extrapolates
        working_area = WorkingArea(max(0.0, fit.gamma.r_min_px - 5.0), fit.gamma.r_max_px + 5.0)
        from core.camera.config import DetectSettings

        detect = DetectSettings()
    assert detect is not None
    header = (f"Camera calibration (Γ, paper §3) made by: omniformation calibrate from {source}\n"
              f"{fit.gamma.n_sectors} sectors, degree {fit.gamma.degree}; worst sector residual RMS"
              f" {worst_rms:.2f} cm; held-out error median {held.median_cm:.2f} cm, p95 {held.p95_cm:.2f} cm"
              + "".join(f"\nwarning: {w}" for w in warnings))
    args.out.write_text(gamma_toml(fit.gamma, working_area, detect, header), encoding="utf-8")
    print(f"wrote {display_path(args.out)}")
    if args.save_table is not None:
        write_table(table, args.save_table)
        print(f"wrote {display_path(args.save_table)}")
    return 0


def _calibration_page(args: argparse.Namespace) -> int:
    import dataclasses

    from app.backends.camera import SyntheticMarkerRig, open_frame_source
    from app.cli.args import serve_page
    from app.contracts import FrameSource
    from app.dashboard.calibration_panel import CalibrationService
    from core.camera.config import DetectSettings

    if args.table is not None:
        raise UserError("--page builds the table in the browser: give --camera SOURCE or --synthetic CAMERA.toml, no TABLE")
    if (args.camera is None) == (args.synthetic is None):
        raise UserError("--page needs either --camera SOURCE (a real camera) or --synthetic CAMERA.toml (not both)")
    save_as = args.out or Path("camera.toml")
    if save_as.suffix.lower() != ".toml":
        raise UserError(f"--out {save_as}: the camera file must be a .toml file")
    if args.synthetic is not None:
        camera = load_camera(args.synthetic)
        if camera.model is None:
            raise UserError(f"{display_path(args.synthetic)}: has no [model], so it cannot stand in for a camera")
        model = camera.model
        if args.tilt is not None:
            model = model.replace(tilt_deg=args.tilt)
        if args.off_centre is not None:
            model = model.replace(cx=model.cx + args.off_centre)
        camera = dataclasses.replace(camera, model=model)
        source: FrameSource = SyntheticMarkerRig(camera, seed=args.seed)
        detect = camera.detect
    else:
        if args.tilt is not None or args.off_centre is not None:
            raise UserError("--tilt and --off-centre shape the synthetic rig; a real camera is as it is")
        try:
            source = open_frame_source(args.camera)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        detect = DetectSettings()
    return serve_page(lambda: CalibrationService(source, detect, save_as, host=args.host, port=args.port,
                                                 token=args.token),
                      args.host, args.port, "use the page",
                      lambda svc: f"omniformation: calibration page at {svc.url}  (Ctrl-C to stop)")


def _mounting(table: "MatchingTable", args: argparse.Namespace, source: str) -> tuple[bool, float]:
    """The flip and bearing offset to fit with: read from the table when it tells (and then
    any given must agree), else as given (default: not mirrored, not turned)."""
    from core.camera.gamma import estimate_center
    from core.camera.quality import detect_mounting

    given_flip, given_offset = bool(args.flip), args.bearing_offset
    if args.center is not None:
        centre = (float(args.center[0]), float(args.center[1]))
    elif len(table) >= 6:
        centre = estimate_center(table)
    else:
        return given_flip, given_offset if given_offset is not None else 0.0
    m = detect_mounting(table, centre)
    if m is None or not m.certain:
        return given_flip, given_offset if given_offset is not None else 0.0
    told = f"turned by {m.offset_deg:+.1f} deg" + (" and mirrored" if m.flip else "")
    use = f"--bearing-offset {m.offset_deg:.1f}" + (" --flip" if m.flip else "")
    differs = (args.flip and not m.flip) or (given_offset is not None and
                                             abs((given_offset - m.offset_deg + 180.0) % 360.0 - 180.0) > 20.0)
    if differs:
        raise UserError(f"{source}: the table shows the camera {told}, not as given; use {use}"
                        " (or leave both out: calibrate then reads them from the table)")
    if given_offset is None or m.flip != given_flip:
        print(f"{source}: the markers show the camera {told}: fitted with {use}")
    return m.flip, given_offset if given_offset is not None else round(m.offset_deg, 1)


def cmd_locate(args: argparse.Namespace) -> int:
    import numpy as np

    from core.vision.blobs import find_blobs

    camera = load_camera(args.camera)
    gamma = require_gamma(camera)
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
