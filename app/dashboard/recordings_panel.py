"""The live dashboard's "Recordings" panel: pick a session from recordings/ and replay it.

The replay opens as its own dashboard on another port (a link appears here), not in place
of the live page: the operator keeps the live view and the STOP button while robots move.
At most ``MAX_OPEN`` replays are served at once; opening another closes the oldest.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING

import viser

from app.paths import RECORDINGS, display_path

if TYPE_CHECKING:
    from app.replay import ReplayService

MAX_OPEN = 3
NONE = "(no recordings yet)"


def list_recordings(folder: Path = RECORDINGS) -> list[str]:
    """Recordings under ``folder`` (samples included), newest first, as paths people read."""
    files = [p for p in folder.rglob("*.mcap") if p.is_file()]
    files.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    return [display_path(p) for p in files]


class RecordingsPanel:
    def __init__(self, server: viser.ViserServer, host: str, folder: Path = RECORDINGS,
                 current: str = "") -> None:
        self.server, self.host, self.folder = server, host, folder
        self.current = current  # the file this live run records to: not offered while it is written
        self.replays: list[ReplayService] = []
        self._lock = threading.Lock()
        gui = server.gui
        with gui.add_folder("Recordings", expand_by_default=False):
            options = self._options()
            self.menu = gui.add_dropdown("Session", options=options, initial_value=options[0],
                                         hint="recorded sessions in recordings/, newest first")
            self.refresh = gui.add_button("Refresh list")
            self.open = gui.add_button("Replay in a new tab", disabled=options == [NONE],
                                       hint="serves the recording on another port; this live page keeps running")
            self.links = gui.add_markdown("")
        self.refresh.on_click(lambda _: self.rescan())
        self.open.on_click(lambda _: self.open_selected())

    def _options(self) -> list[str]:
        names = [n for n in list_recordings(self.folder) if n != self.current]
        return names or [NONE]

    def rescan(self) -> None:
        options = self._options()
        keep = self.menu.value if self.menu.value in options else options[0]
        self.menu.options = options
        self.menu.value = keep
        self.open.disabled = options == [NONE]

    def open_selected(self) -> str:
        """Serve the selected recording; returns its URL (or the reason it could not)."""
        from app.paths import PROJECT_ROOT
        from app.recorder import RecordingError, read_recording
        from app.replay import ReplayService

        name = self.menu.value
        if name == NONE:
            return ""
        path = Path(name) if Path(name).is_absolute() else PROJECT_ROOT / name
        try:
            rec = read_recording(path)
        except RecordingError as exc:
            self._show(f"**cannot replay**: {exc}")
            return str(exc)
        with self._lock:
            while len(self.replays) >= MAX_OPEN:
                self.replays.pop(0).close()
            replay = ReplayService(rec, host=self.host, port=0)
            replay.start()
            self.replays.append(replay)
            lines = [f"- [{r.rec.path.name}]({r.url}) — {r.url}" for r in self.replays]
        note = f"  \n{rec.loss_note()}" if rec.loss_note() else ""
        self._show("Replays being served (open in a new tab):  \n" + "\n".join(lines) + note)
        return replay.url

    def _show(self, text: str) -> None:
        self.links.content = text

    def close(self) -> None:
        with self._lock:
            for r in self.replays:
                r.close()
            self.replays.clear()
