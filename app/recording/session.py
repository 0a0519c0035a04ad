"""A live session's recording: what it keeps about how it was made, where it goes, and
wiring the writer to the loop and the parameter store."""

from __future__ import annotations

import datetime as _dt
import re
import json
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from app.contracts import Rig
from app.files import default_recordings, display_path, resolve_scenario_path

if TYPE_CHECKING:
    from app.live.config import ServiceConfig
    from app.live.service import Service
    from app.recording.writer import Recorder
    from core.config import Scenario


def session_metadata(scenario_name: str, scenario_path: str | None, camera: Rig | None,
                     config_path: Path | None = None) -> dict[str, str]:
    """What a recording keeps about how it was made: config and scenario text, the command."""
    meta = {"command": " ".join(shlex.quote(a) for a in ["omniformation", *without_secrets(sys.argv[1:])]),
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
        if rig.capture is not None:  # what the camera was asked to be set to; each tick's camera_state says what it took
            meta["capture_asked"] = json.dumps(rig.capture.asked())
    return meta


def without_secrets(argv: list[str]) -> list[str]:
    """The command line as recorded: a dashboard token is not kept in a file people share."""
    out = []
    hide = False
    for a in argv:
        if hide:
            out.append("***")
            hide = False
        elif a == "--token":
            out.append(a)
            hide = True
        elif a.startswith("--token="):
            out.append("--token=***")
        else:
            out.append(a)
    return out


def recording_path(name: str, now: _dt.datetime | None = None, folder: Path | None = None) -> Path:
    """<folder>/<UTC timestamp>_<name>.mcap (folder: recordings/ under the working folder), never an
    existing file."""
    folder = folder or default_recordings()
    stamp = (now or _dt.datetime.now(_dt.UTC)).strftime("%Y%m%dT%H%M%SZ")
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", name) or "session"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{stamp}_{safe}.mcap"
    k = 1
    while path.exists():
        k += 1
        path = folder / f"{stamp}_{safe}-{k}.mcap"
    return path


def start_recording(service: "Service", config: "ServiceConfig", scenario: "Scenario | None",
                    scenario_arg: str | None, camera: Rig | None,
                    frames_hz: float, path: Path | None = None, folder: Path | None = None) -> "Recorder":
    """Start recording the service's session: the retention budget is applied to the folder first
    (oldest sessions deleted, samples never); a full disk or a write error later stops the
    recording cleanly, and the page, the log and stderr say so (the robots carry on).
    RecordingRefused (one line) when it cannot start."""
    from app.recording.writer import Recorder, apply_retention

    name = scenario.name if scenario is not None else "sim"
    meta = session_metadata(name, scenario_arg, camera, config.path)
    path = path or recording_path(name, folder=folder)
    for gone in apply_retention(path.parent, config.max_total_bytes):
        print(f"omniformation: recordings over {config.max_total_bytes / 1e9:g} GB: deleted the oldest,"
              f" {display_path(gone)}", file=sys.stderr, flush=True)
    shown = display_path(path)

    def stopped(why: str) -> None:
        service.dashboard.controls.recording = f"STOPPED ({why}); {shown} keeps what was written"
        service.recordings.current = ""  # what was written can be replayed now
        print(f"omniformation: recording stopped: {why}; {shown} keeps what was written; the robots carry on",
              file=sys.stderr, flush=True)

    recorder = Recorder(path, meta, service.store.get(), frame_rate_hz=frames_hz,
                        free_floor_bytes=config.free_floor_bytes, on_stopped=stopped)
    service.loop.subscribe(recorder.on_tick)
    service.tests.listeners.append(recorder.on_trial)
    service.store.subscribe(recorder.on_params)
    service.dashboard.controls.recording = shown
    service.recordings.current = shown  # not offered for replay while it is being written
    service.recordings.rescan()
    return recorder


