"""Recording a live session, `omniformation replay` and `omniformation report`."""

from __future__ import annotations

import argparse
import datetime as _dt
import re
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.paths import RECORDINGS, UserError, display_path, resolve_scenario_path

if TYPE_CHECKING:
    from app.recorder import Recorder, Recording
    from app.service import Service
    from app.service_config import ServiceConfig
    from core.camera.config import CameraConfig
    from core.camera.gamma import Gamma
    from core.config import Scenario


def session_metadata(scenario_name: str, scenario_path: str | None, camera: "tuple[CameraConfig, Gamma] | None",
                     config_path: Path | None = None) -> dict[str, str]:
    """What a recording keeps about how it was made: config and scenario text, the command."""
    meta = {"command": " ".join(shlex.quote(a) for a in ["omniformation", *sys.argv[1:]]),
            "scenario": scenario_name}
    if scenario_path:
        meta["scenario_toml"] = resolve_scenario_path(scenario_path).read_text(encoding="utf-8")
    if config_path is not None:
        meta["config_toml"] = config_path.read_text(encoding="utf-8")
    if camera is not None:
        rig, gamma = camera
        wa = rig.working_area
        meta["working_area"] = f"{gamma.cx},{gamma.cy},{wa.inner_px},{wa.outer_px}"
        meta["camera"] = rig.source
        from core.camera.config import gamma_toml

        meta["calibration_toml"] = gamma_toml(gamma, wa, rig.detect, header=f"the calibration recorded with {rig.source}")
    return meta


def recording_path(name: str, now: _dt.datetime | None = None) -> Path:
    """recordings/<UTC timestamp>_<name>.mcap, never an existing file."""
    stamp = (now or _dt.datetime.now(_dt.timezone.utc)).strftime("%Y%m%dT%H%M%SZ")
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", name) or "session"
    RECORDINGS.mkdir(exist_ok=True)
    path = RECORDINGS / f"{stamp}_{safe}.mcap"
    k = 1
    while path.exists():
        k += 1
        path = RECORDINGS / f"{stamp}_{safe}-{k}.mcap"
    return path


def start_recording(service: "Service", config: "ServiceConfig", scenario: "Scenario | None",
                    scenario_arg: str | None, camera: "tuple[CameraConfig, Gamma] | None",
                    frames_hz: float, path: Path | None = None) -> "Recorder":
    name = scenario.name if scenario is not None else "sim"
    meta = session_metadata(name, scenario_arg, camera, config.path)
    path = path or recording_path(name)
    from app.recorder import Recorder

    recorder = Recorder(path, meta, service.store.get(), frame_rate_hz=frames_hz)
    service.loop.subscribe(recorder.on_tick)
    service.store.subscribe(recorder.on_params)
    service.dashboard.controls.recording = display_path(path)
    service.recordings.current = display_path(path)  # not offered for replay while it is being written
    service.recordings.rescan()
    return recorder


def _load(path: Path) -> "Recording":
    from app.recorder import RecordingError, read_recording

    try:
        rec = read_recording(path)
    except RecordingError as exc:
        raise UserError(str(exc)) from None
    if rec.loss_note():
        print(f"omniformation: {rec.loss_note()}", file=sys.stderr, flush=True)
    return rec


def cmd_replay(args: argparse.Namespace) -> int:
    import signal

    from app.replay import ReplayService

    rec = _load(args.file)
    try:
        svc = ReplayService(rec, host=args.host, port=args.port)
    except OSError as exc:
        raise UserError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: svc.stop())
    svc.start()
    t = rec.t
    print(f"omniformation: replaying {display_path(args.file)} ({len(rec.ticks)} ticks, {t[-1] - t[0]:.1f} s,"
          f" {len(rec.frames)} frames, {len(rec.events)} events) at {svc.url}  (Ctrl-C to stop)", flush=True)
    try:
        svc.wait()
    except KeyboardInterrupt:
        pass
    finally:
        svc.close()
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from app.report import write_report

    rec = _load(args.file)
    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)

    def progress(done: int, total: int, what: str) -> None:
        print(f"  [{done}/{total}] {what}", flush=True)

    written = write_report(rec, out, progress)
    for p in written:
        print(f"wrote {display_path(p)}")
    return 0


def add_parsers(sub: Any, int_in: Any) -> None:
    rp = sub.add_parser("replay", help="serve a recording in the dashboard, with a timeline",
                        description="Replay a recorded session (MCAP) in the same dashboard: timeline, play/pause,"
                                    " speed 0.25x-8x, step, previous/next event.")
    rp.add_argument("file", type=Path, help="a recording (.mcap), e.g. from recordings/")
    rp.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    rp.add_argument("--port", type=int_in(0, 65535, " (0 = any free port)"), default=8080, help="port (default 8080)")
    rp.set_defaults(func=cmd_replay)

    rep = sub.add_parser("report", help="turn a recording into the paper's figures and a summary",
                         description="Write PNG figures in the paper's style and summary.md / summary.json.")
    rep.add_argument("file", type=Path, help="a recording (.mcap)")
    rep.add_argument("--out", type=Path, required=True, help="folder for the figures and summary")
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
    rr.set_defaults(func="app.rerun:cmd_rerun")
