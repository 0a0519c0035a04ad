"""The camera commands' arguments: `render`, `calibrate`, `locate` (implemented in
app.camera_commands, imported only when one of them runs, so that `--help` and argument
errors answer at once)."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.paths import SYNTHETIC_CAMERA

def add_parsers(sub: "argparse._SubParsersAction[argparse.ArgumentParser]", float_in, int_in, seed) -> None:  # type: ignore[type-arg,no-untyped-def]
    """The camera subcommands; the argument types come from app.cli so every command refuses alike."""
    render = sub.add_parser("render", help="write one synthetic camera frame of a scenario",
                            description="Simulate SCENARIO up to --t and write what the leader's camera sees.")
    render.add_argument("scenario", help="scenario name or .toml path")
    render.add_argument("--t", type=float_in(0.0, 86400.0, "s", lo_inclusive=True),
                        default=0.0, help="time in the scenario (s, default 0)")
    render.add_argument("--out", type=Path, required=True, help="image file (.png or .jpg)")
    render.add_argument("--camera", type=Path, default=SYNTHETIC_CAMERA, help="synthetic camera config (default: the built-in rig)")
    render.add_argument("--seed", type=seed, help="noise seed (default: the scenario's)")
    render.set_defaults(func="app.camera_commands:cmd_render")

    cal = sub.add_parser("calibrate", help="fit Γ (pixel -> metres) from a matching table or the synthetic rig",
                         description="Fit the per-sector Γ polynomials and bearing corrections (paper §3). "
                                     "TABLE.csv has the header bearing_deg,metres,u,v (docs/calibration.md).")
    cal.add_argument("table", nargs="?", type=Path, help="matching table CSV: bearing_deg,metres,u,v")
    cal.add_argument("--synthetic", type=Path, metavar="CAMERA.toml", help="measure the table on the synthetic rig instead")
    cal.add_argument("--center", nargs=2, type=float, metavar=("CX", "CY"), help="image centre (px); default: estimated")
    cal.add_argument("--sectors", type=int_in(1, 360), help="number of sectors (default: one per table bearing)")
    cal.add_argument("--degree", type=int_in(1, 7), help="polynomial degree (default 3)")
    cal.add_argument("--bearing-offset", type=float, metavar="DEG", help="leader bearing that appears straight up (deg)")
    cal.add_argument("--flip", action="store_true", help="the image is mirrored left/right")
    cal.add_argument("--out", type=Path, required=True, help="camera.toml to write")
    cal.add_argument("--save-table", type=Path, help="also write the matching table used (CSV)")
    cal.add_argument("--seed", type=seed, default=0, help="noise seed for --synthetic (default 0)")
    cal.set_defaults(func="app.camera_commands:cmd_calibrate")

    loc = sub.add_parser("locate", help="find the coloured rectangles in one picture and print where they are",
                         description="Print one JSON object per colour blob in the working area: hue, pixel, area, x, y (m, leader frame).")
    loc.add_argument("image", type=Path, help="an omnidirectional picture (PNG, JPEG, ...)")
    loc.add_argument("--camera", type=Path, required=True, help="calibrated camera.toml (from calibrate)")
    loc.set_defaults(func="app.camera_commands:cmd_locate")
