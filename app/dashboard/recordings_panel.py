"""The live dashboard's "Recordings" panel: pick a session from recordings/ and replay it.

The replay opens as its own dashboard on another port (a link appears here), not in place
of the live page: the operator keeps the live view and the STOP button while robots move.
A replay is opened only by a name this panel listed: a value the browser sends that is not
one of them (a path, ``../`` anything) is refused and opens nothing.
At most ``MAX_OPEN`` replays are served at once; opening another closes the oldest.

A replay has credentials of its own (the composition root makes them), and a link carries one: the
panel's links are shown to each client alone (viser's per-client markdown, inside this folder), an
operator the replay's operator link, a viewer its viewer link. What is shown to every client names the
replays, never a link (docs/page-access.md).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import viser

from app.dashboard.input_filter import OPERATOR, VIEWER
from app.dashboard.widgets import as_text

from app.files import default_recordings, display_path


class ReplayedFile(Protocol):
    """What the panel says of a recording being replayed (app.recording.reader.Recording)."""

    @property
    def path(self) -> Path: ...

    def loss_note(self) -> str: ...


class ServedReplay(Protocol):
    """A recording served on a page of its own (app.services.replay.ReplayService)."""

    @property
    def rec(self) -> ReplayedFile: ...

    @property
    def url(self) -> str: ...

    @property
    def viewer_url(self) -> str: ...

    def start(self) -> None: ...

    def close(self) -> None: ...

MAX_OPEN = 3
NONE = "(no recordings yet)"


def list_recordings(folder: Path) -> dict[str, Path]:
    """Recordings under ``folder`` (samples included), newest first: the name people read -> file."""
    files = [p for p in folder.rglob("*.mcap") if p.is_file() and not p.is_symlink()] if folder.is_dir() else []
    files.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    return {display_path(p): p for p in files}


class RecordingsPanel:
    def __init__(self, server: viser.ViserServer, serve: Callable[[Path], ServedReplay],
                 folder: Path | None = None, current: str = "",
                 role_of: Callable[[int], str] = lambda _: VIEWER) -> None:
        """``serve``: a recording's file to a replay page of its own, not yet started (the composition
        root reads the file, a ValueError of one line saying why it cannot be replayed, and says where
        the page is, with credentials of its own); ``role_of``: a client's role (the gate's), which
        says which of a replay's links it is shown (unknown: a viewer's)."""
        self.server, self.serve, self.folder = server, serve, folder or default_recordings()
        self.current = current  # the file this live run records to: not offered while it is written
        self._listed: dict[str, Path] = {}  # what the menu offers: the only files that can be opened
        self.replays: list[ServedReplay] = []
        self._lock = threading.Lock()
        self.role_of = role_of
        self._client_links: dict[int, viser.GuiMarkdownHandle] = {}  # client id -> its own links
        self._links_lock = threading.Lock()  # a client's links are made once (its connect vs. an open)
        gui = server.gui
        with gui.add_folder("Recordings", expand_by_default=False) as self.folder_handle:
            options = self._options()
            self.menu = gui.add_dropdown("Session", options=options, initial_value=options[0],
                                         hint="recorded sessions in recordings/, newest first")
            self.refresh = gui.add_button("Refresh list")
            self.open = gui.add_button("Replay in a new tab", disabled=options == [NONE],
                                       hint="serves the recording on another port; this live page keeps running")
            self.links = gui.add_markdown("")
        self.refresh.on_click(lambda _: self.rescan())
        self.open.on_click(lambda _: self._open_clicked())
        server.on_client_connect(lambda client: self._show_links(client))
        server.on_client_disconnect(self._forget)

    def _options(self) -> list[str]:
        self._listed = {n: f for n, f in list_recordings(self.folder).items() if n != self.current}
        return list(self._listed) or [NONE]

    def _recording_now(self) -> str:
        """What the panel says of the file this session writes (listed once it is closed)."""
        return (f"Recording now: {as_text(self.current)} (offered here once this session stops)"
                if self.current else "")

    def rescan(self) -> None:
        options = self._options()
        if not self.replays:
            self._show(self._recording_now())
        keep = self.menu.value if self.menu.value in options else options[0]
        self.menu.options = options
        self.menu.value = keep  # type: ignore[misc]  # viser's stubs: read-only on the base handle
        self.open.disabled = options == [NONE]

    def _open_clicked(self) -> None:
        self.open_selected()

    def open_selected(self) -> str:
        """Serve the selected recording; returns its URL (or the reason it could not)."""
        name = self.menu.value
        if name == NONE:
            return ""
        path = self._listed.get(str(name))
        if path is None:
            self._show("**cannot replay**: not one of the listed recordings")
            return "not one of the listed recordings"
        with self._lock:
            try:
                replay = self.serve(path)  # read first: a file that cannot be replayed closes no replay
            except ValueError as exc:
                self._show(f"**cannot replay**: {as_text(str(exc))}")
                return str(exc)
            while len(self.replays) >= MAX_OPEN:
                self.replays.pop(0).close()
            replay.start()
            self.replays.append(replay)
            names = ", ".join(as_text(r.rec.path.name) for r in self.replays)
        note = f"  \n{as_text(replay.rec.loss_note())}" if replay.rec.loss_note() else ""
        self._show(f"Replays being served (open in a new tab): {names}" + note)
        for client in list(self.server.get_clients().values()):
            self._show_links(client)
        return replay.url

    def cause(self, where: str) -> str:
        """What the health banner names beside an alarm while replays are open ("": none): a replay's
        tab draws on some machine's CPU, its service on this one's (``where``: which process serves it)."""
        with self._lock:
            n = len(self.replays)
        if not n:
            return ""
        return f"{n} replay{'s' if n > 1 else ''} open from this page, served {where}: a replay playing takes CPU"

    def _forget(self, client: viser.ClientHandle) -> None:
        with self._links_lock:
            self._client_links.pop(client.client_id, None)

    def links_for(self, role: str) -> str:
        """The replays' links for a client of ``role``: an operator's or a viewer's, never another's."""
        with self._lock:
            replays = list(self.replays)
        urls = [(r.rec.path.name, r.url if role == OPERATOR else r.viewer_url) for r in replays]
        return "\n".join(f"- [{as_text(name)}]({url}) — {as_text(url)}" for name, url in urls)

    def _show_links(self, client: viser.ClientHandle) -> None:
        """This client's own links (made the first time there is one to show)."""
        text = self.links_for(self.role_of(client.client_id))
        with self._links_lock:
            shown = self._client_links.get(client.client_id)
            if shown is not None:
                shown.content = text
            elif text:
                with self.folder_handle:  # a client's element inside the page's folder (viser allows that way)
                    self._client_links[client.client_id] = client.gui.add_markdown(text)

    def _show(self, text: str) -> None:
        self.links.content = text

    def close(self) -> None:
        with self._lock:
            for r in self.replays:
                r.close()
            self.replays.clear()
