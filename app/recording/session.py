"""A session's recording: what it keeps about how it was made and where it goes (the
writer is wired to a live service by app.services.recording)."""

from __future__ import annotations

import datetime as _dt
import re
import json
import shlex
import sys
from pathlib import Path
from app.contracts import Rig
from app.files import default_recordings, resolve_scenario_path

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
