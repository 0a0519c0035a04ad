"""`omniformation replay`, `report` and `rerun`: what is done with a recorded session."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from app.cli.args import Parser, port, token_arg
from app.files import UserError, display_path

if TYPE_CHECKING:
    from app.recording.reader import Recording


def load_recording(path: Path) -> "Recording":
    """A recording for a command, its loss (if any) said on stderr; unreadable: one line."""
    from app.recording.reader import RecordingError, check_ticks, read_recording

    try:
        rec = read_recording(path)
        check_ticks(rec)
    except RecordingError as exc:
        raise UserError(str(exc)) from None
    if rec.loss_note():
        print(f"omniformation: {rec.loss_note()}", file=sys.stderr, flush=True)
    return rec


def cmd_replay(args: argparse.Namespace) -> int:
    from app.cli.args import serve_page
    from app.cli.foxglove_args import check_foxglove_args, serve_replay
    from app.services.replay import ReplayService

    check_foxglove_args(args)
    rec = load_recording(args.file)
    t = rec.t
    fox = serve_replay(args, rec)

    def make() -> ReplayService:
        svc = ReplayService(rec, host=args.host, port=args.port, token=args.token)
        if fox is not None:
            svc.listeners.append(fox.on_tick)
        return svc

    try:
        return serve_page(make, args.host, args.port, "see the recording",
                          lambda svc: f"omniformation: replaying {display_path(args.file)} ({len(rec.ticks)} ticks,"
                                      f" {t[-1] - t[0]:.1f} s, {len(rec.frames)} frames, {len(rec.events)} events) at"
                                      f" {svc.url}  (Ctrl-C to stop)")
    finally:
        if fox is not None:
            fox.close()


def cmd_report(args: argparse.Namespace) -> int:
    from app.recording.report import write_report

    from app.files import prepare_out_dir

    if args.file.is_dir():  # a study's folder: its summary and plots again, from its files
        from app.study.session import redraw

        if args.out is not None:
            raise UserError(f"--out: a study's report is written into its folder ({display_path(args.file)});"
                            " leave --out out")
        for p in redraw(args.file, args.format):
            print(f"wrote {display_path(p)}")
        return 0
    if args.out is None:
        raise UserError("--out DIR is needed for a recording's report")
    out: Path = args.out
    prepare_out_dir(out)
    rec = load_recording(args.file)

    def progress(done: int, total: int, what: str) -> None:
        print(f"  [{done}/{total}] {what}", flush=True)

    try:
        written = write_report(rec, out, progress, fmt=args.format)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise UserError(f"{args.file}: its ticks are not what omniformation records ({type(exc).__name__}: {exc})"[:300]) from None
    for p in written:
        print(f"wrote {display_path(p)}")
    return 0


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    rp = sub.add_parser("replay", help="serve a recording in the dashboard, with a timeline",
                        description="Replay a recorded session (MCAP) in the same dashboard: timeline, play/pause,"
                                    " speed 0.25x-8x, step, previous/next event.")
    rp.add_argument("file", type=Path, help="a recording (.mcap), e.g. from recordings/")
    rp.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; others need a token)")
    rp.add_argument("--token", type=token_arg, help="the token browsers must present on a non-loopback --host"
                                                     " (default: a new one, printed in the URL)")
    rp.add_argument("--port", type=port, default=8080, help="port (default 8080)")
    from app.cli.foxglove_args import add_foxglove_args

    add_foxglove_args(rp)
    rp.set_defaults(func=cmd_replay)

    rep = sub.add_parser("report", help="turn a recording into the paper's figures and a summary (or redraw a study's)",
                         description="Write figures in the paper's style (PNG, SVG or PDF) and summary.md / summary.json;"
                                     " given a study's folder (omniformation study --out DIR), draw its summary.md and"
                                     " plots/ again from its files.")
    rep.add_argument("file", type=Path, help="a recording (.mcap), or a study's folder")
    rep.add_argument("--out", type=Path, help="folder for the figures and summary (a recording's report)")
    rep.add_argument("--format", choices=("png", "svg", "pdf"), default="png",
                     help="the figures' file format (default png)")
    rep.set_defaults(func=cmd_report)

    rr = sub.add_parser("rerun", help="re-run a recording's frames (or its simulation) with other settings",
                        description="Feed a recording's camera frames through the vision pipeline again with other"
                                    " settings (--pipeline-config), or re-simulate a simulated session with other"
                                    " controller gains (--gains); writes a new recording and prints what changed.")
    rr.add_argument("file", type=Path, help="a recording (.mcap)")
    rr.add_argument("--out", type=Path, required=True, metavar="NEW.mcap", help="the new recording")
    rr.add_argument("--gains", metavar="k_f1=0.12,...", help="re-simulate with these controller gains")
    rr.add_argument("--pipeline-config", type=Path, metavar="PIPELINE.toml",
                    help="a [pipeline] table of vision settings (see core/vision/pipeline.py, PIPELINE_BOUNDS)")
    rr.add_argument("--calibration", type=Path, metavar="CAMERA.toml",
                    help="Γ to use instead of the one recorded with the session")
    rr.set_defaults(func=cmd_rerun)


def cmd_rerun(args: argparse.Namespace) -> int:
    from app.recording.reader import params_from_recording, read_recording
    from app.recording.report import summarise
    from app.recording.rerun import (frame_summary, parse_gains, recorded_calibration, rerun_frames, resimulate,
                                     write_frame_rerun)
    from core.config import ConfigError
    from core.types import Gains
    from core.vision.pipeline import PipelineSettings

    if not args.out.parent.is_dir():
        raise UserError(f"{args.out}: folder {args.out.parent} does not exist")
    if args.out.resolve() == args.file.resolve():
        raise UserError(f"--out {args.out}: would overwrite the recording being re-run; give another file")
    settings = PipelineSettings()
    if args.pipeline_config is not None:
        if not args.pipeline_config.is_file():
            raise UserError(f"{args.pipeline_config}: no such pipeline config file")
        from core.vision.pipeline import parse_pipeline_settings

        from app.files import read_text

        try:
            settings = parse_pipeline_settings(read_text(args.pipeline_config, "pipeline config"),
                                               display_path(args.pipeline_config))
        except ConfigError as exc:
            raise UserError(str(exc)) from None
    if args.gains is not None:
        parse_gains(args.gains, Gains())  # the arguments first: no need to read a large file to refuse them
    rec = load_recording(args.file)
    camera = recorded_calibration(rec, args.calibration) if len(rec.frames) else None
    note = {"rerun_of": rec.path.name, "pipeline_settings": json.dumps(settings.__dict__)}

    def progress(done: int, total: int) -> None:
        if done == total or done % max(1, total // 10) == 0:
            print(f"  [{done}/{total}] frames", flush=True)

    if args.gains is not None:
        gains = parse_gains(args.gains, params_from_recording(rec).gains)
        print(f"re-simulating {rec.metadata.get('scenario', rec.path.stem)} with "
              + ", ".join(f"{k}={v:g}" for k, v in gains.as_dict().items()), flush=True)
        resimulate(rec, gains, settings, args.out, camera)
        new = read_recording(args.out)
        old_sum, new_sum = summarise(rec), summarise(new)
        print("per follower: settling time (s) and steady error RMS (cm), recorded -> new")
        def settled(x: object) -> str:
            return "not settled" if x is None else f"{x}"

        for a, b in zip(old_sum["followers"], new_sum["followers"]):
            print(f"  F{a['follower']}: settling {settled(a['settling_time_s'])} -> {settled(b['settling_time_s'])},"
                  f" steady RMS {a['steady_error_rms_cm']} -> {b['steady_error_rms_cm']},"
                  f" max {a['steady_error_max_cm']} -> {b['steady_error_max_cm']}")
    else:
        if camera is None:
            raise UserError(f"{rec.path.name}: has no camera frames to re-run (recorded with --frames-hz 0, or"
                            " without the camera); --gains re-simulates a simulated session")
        print(f"re-running {len(rec.frames)} recorded frames through the vision pipeline ({camera.source})",
              flush=True)
        r = rerun_frames(rec, camera, settings, progress)
        write_frame_rerun(rec, r, args.out, note)
        print("per follower: new estimates against the recorded ones (RMS), and against the truth where recorded")
        for row in frame_summary(r):
            line = (f"  F{row['follower']}: position {row['position_change_rms_cm']:.2f} cm, heading"
                    f" {row['heading_change_rms_deg']:.2f} deg; tracked {row['tracked_new_pct']:.0f} %"
                    f" (recorded {row['tracked_recorded_pct']:.0f} %)")
            if "new_error_rms_cm" in row:
                line += (f"; error vs truth {row['recorded_error_rms_cm']:.2f} -> {row['new_error_rms_cm']:.2f} cm,"
                         f" {row['recorded_heading_error_rms_deg']:.2f} -> {row['new_heading_error_rms_deg']:.2f} deg")
            print(line)
    print(f"wrote {display_path(args.out)}")
    return 0
