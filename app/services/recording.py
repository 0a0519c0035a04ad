"""A live service's recording: the writer wired to the loop, the parameter store, the
tuning bench and the page, as the CLI asks."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

from app.contracts import Rig
from app.files import display_path
from app.recording.session import recording_path, session_metadata

if TYPE_CHECKING:
    from app.live.config import ServiceConfig
    from app.recording.writer import Recorder
    from app.services.live import Service
    from core.config import Scenario


def start_recording(service: "Service", config: "ServiceConfig", scenario: "Scenario | None",
                    scenario_arg: str | None, camera: Rig | None,
                    frames_hz: float, path: Path | None = None, folder: Path | None = None) -> "Recorder":
    """Start recording the service's session: the retention budget is applied to the folder first
    (the oldest of the service's sessions deleted; never one being written, never the samples,
    never what another command wrote); a full disk or a write error later stops the
    recording cleanly, and the page, the log and stderr say so (the robots carry on).
    RecordingRefused (one line) when it cannot start."""
    from app.recording.writer import RETENTION_KEY, RETENTION_SERVICE, Recorder, apply_retention

    name = scenario.name if scenario is not None else "sim"
    meta = {**session_metadata(name, scenario_arg, camera, config.path), RETENTION_KEY: RETENTION_SERVICE}
    path = path or recording_path(name, folder=folder)
    for gone in apply_retention(path.parent, config.max_total_bytes):
        print(f"omniformation: recordings over {config.max_total_bytes / 1e9:g} GB: deleted the oldest,"
              f" {display_path(gone)}", file=sys.stderr, flush=True)
    shown = display_path(path)

    def stopped(why: str) -> None:
        service.dashboard.controls.recording = f"STOPPED ({why}); {shown} keeps what was written"
        service.recordings.current = ""  # what was written can be replayed now
        service.recordings.rescan()
        print(f"omniformation: recording stopped: {why}; {shown} keeps what was written; the robots carry on",
              file=sys.stderr, flush=True)

    recorder = Recorder(path, meta, service.store.get(), frame_rate_hz=frames_hz,
                        free_floor_bytes=config.free_floor_bytes, on_stopped=stopped)
    service.loop.subscribe(recorder.on_tick)
    service.tests.listeners.append(recorder.on_trial)
    service.store.subscribe(recorder.on_params)
    service.dashboard.controls.health.listeners.append(lambda _t, text: recorder.event_now("alarm", text))
    service.dashboard.controls.recording = shown
    service.recordings.current = shown  # not offered for replay while it is being written
    service.recordings.rescan()
    return recorder


