"""A replay opened from the live page runs where it cannot slow the loop (issue 82, item 3): with the
page in its own process (`run`'s default), in a process of its own, the leader of its own session
(hence of its own autogroup) at nice 19; a file that is no recording is one line on the panel and
leaves no process; an alarm while it is open names it; closing the service ends the replay's process."""

from __future__ import annotations

import os
import re
import shutil
import threading
import time
import urllib.request
from pathlib import Path

from app.services.live import Service
from tests.helpers import SAMPLES, RawPage, wait_for


def _children(pid: int) -> set[int]:
    found: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        found |= {int(c) for c in (task / "children").read_text().split()}
    return found


def _replays(pid: int) -> set[int]:
    """The replay processes ``pid`` started."""
    return {c for c in _children(pid) if b"app.services.replay_process" in Path(f"/proc/{c}/cmdline").read_bytes()}


def _stat(pid: int) -> list[str]:
    text = Path(f"/proc/{pid}/stat").read_text()
    return text[text.rindex(")") + 2:].split()  # the fields after the command's name (state is field 3)


def test_a_replay_from_the_live_page_runs_in_a_low_priority_process_of_its_own(tmp_path: Path) -> None:
    shutil.copyfile(SAMPLES / "experiment2-vision.mcap", tmp_path / "a.mcap")
    (tmp_path / "b.mcap").write_bytes(b"no recording")  # the newest: listed first
    os.utime(tmp_path / "a.mcap", (1, 1))
    svc = Service(host="127.0.0.1", port=0, n_followers=2, rate_hz=30.0, recordings=tmp_path, page_process=True)
    svc.start()
    try:
        assert svc.page is not None
        page_pid = svc.page.pid
        client = RawPage(svc.page.port)
        options: list[str] = []
        for msg in client.messages(60.0):
            props = msg.get("props") or {}
            if props.get("label") == "Session":
                options = list(props.get("options") or [])
            if options and "Replay in a new tab" in client.buttons:
                break
        assert len(options) == 2 and options[0].endswith("b.mcap"), options
        client.click("Replay in a new tab")  # b.mcap: no recording
        assert client.wait_for("cannot replay")
        assert _replays(page_pid) == set()  # and no process left behind
        client.set("Session", options[1])
        client.click("Replay in a new tab")
        url = ""
        for msg in client.messages(120.0):
            found = re.search(r"\]\((http://127\.0\.0\.1:\d+/[^)]*)\)", str(msg))
            if found:
                url = found.group(1)
                break
        assert url, "the replay's link on the page"
        (replay,) = _replays(page_pid)  # a process of its own: not the loop's, not the page's
        fields = _stat(replay)
        assert int(fields[3]) == replay  # the leader of its own session (field 6: session id) ...
        assert "nice 19" in Path(f"/proc/{replay}/autogroup").read_text()  # ... hence its own autogroup, at 19
        assert int(fields[16]) == 19  # its nice value (field 19)
        with urllib.request.urlopen(url, timeout=30) as response:  # it serves the replay
            assert response.status == 200
        assert svc.loop.tick_count > 0 and not svc.loop.stopping  # the live run went on
        # an alarm while it is open names it beside the alarm (a loop held back: ticks skipped)
        held = threading.Event()
        svc.loop.subscribe(lambda s: None if held.is_set() else time.sleep(0.045))
        try:
            assert client.wait_for("1 replay open from this page, served by a process of its own at the lowest"
                                   " priority", timeout=120.0)
        finally:
            held.set()
        client.close()
    finally:
        svc.close()
    wait_for(lambda: not Path(f"/proc/{replay}").exists() or _stat(replay)[0] == "Z", 30.0,
             "the replay's process to end with the service")
