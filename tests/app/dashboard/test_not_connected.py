"""A page with no link to the loop says so (issue 82, item 2), in Chromium, for the three ways a link
goes: the service ended (Ctrl-C), the loop's process killed while the page's lives, and the network
between the browser and the service down (a TCP relay written here, on 127.0.0.1, that drops every
connection and refuses new ones, then lets them through again).

Each time the bar turns into a full-width NOT CONNECTED that names the robots' own watchdog, its
STOP and the panel's are disabled, the last t and loop rate stay on it with their age; when the link
comes back the page reconnects by itself and says so. `run` is a real process here, in its default
mode (the page in a process of its own)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from tests.helpers import ARTIFACTS, ROOT, chromium_browser, new_page, settle, wait_for

playwright_api = pytest.importorskip("playwright.sync_api")
PAGE_MS = 60_000
SAID_S = 30.0  # how long the page may take to say it on a loaded machine (a page that never says it fails)
NOT_CONNECTED = "NOT CONNECTED — STOP unavailable from this page; robots stop on their own watchdog in 0.5 s"


@contextlib.contextmanager
def served(*args: str) -> Iterator[tuple[subprocess.Popen[str], int]]:
    """`omniformation run --port 0 --no-record --feedback truth --followers 2 ARGS` as a real process: (it, its page's
    port); killed on the way out whatever happened."""
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--feedback", "truth",
                             "--followers", "2", *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.stdout is not None
    watchdog = threading.Timer(300.0, proc.kill)  # a run that never serves fails, it does not hang
    watchdog.start()
    try:
        port = 0
        for line in proc.stdout:
            found = re.search(r"dashboard at http://127\.0\.0\.1:(\d+)/", line)
            if found:
                port = int(found.group(1))
                break
        assert port, "run did not say where it serves"
        threading.Thread(target=proc.stdout.read, daemon=True).start()  # the rest of what it says, unread
        yield proc, port
    finally:
        watchdog.cancel()
        proc.kill()
        proc.wait(30)


class Relay:
    """The browser's network to the service: a TCP relay on 127.0.0.1 that passes bytes both ways
    (the page's Host and Origin name the relay's port: rewritten to the service's in what goes
    up, as the gate accepts only its own; the page sends no request with a body), ``down()`` drops every connection and refuses new ones, ``up()`` lets
    them through again."""

    def __init__(self, target: int) -> None:
        self.target = target
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self._ours, self._theirs = f"127.0.0.1:{self.port}".encode(), f"127.0.0.1:{target}".encode()
        self.is_up = True
        self.open: list[socket.socket] = []
        self.lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                a, _ = self.server.accept()
            except OSError:
                return
            if not self.is_up:
                a.close()  # the network is down: nothing gets through
                continue
            try:
                b = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                a.close()
                continue
            with self.lock:
                self.open += [a, b]
            threading.Thread(target=self._pump, args=(a, b, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(b, a, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, upstream: bool) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data.replace(self._ours, self._theirs) if upstream else data)
        except OSError:
            pass
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.close()

    def down(self) -> None:
        self.is_up = False
        with self.lock:
            gone, self.open = self.open, []
        for s in gone:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    def up(self) -> None:
        self.is_up = True

    def close(self) -> None:
        self.down()
        self.server.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium_browser() as b:
        yield b


def open_console(browser: Any, port: int) -> Any:
    page = new_page(browser, 1280, 720, scene=False)
    page.goto(f"http://127.0.0.1:{port}/")
    page.get_by_role("button", name="STOP", exact=True).wait_for(timeout=PAGE_MS)
    settle(page)
    connected(page)
    return page


def bar_text(page: Any) -> str:
    return str(page.locator("#omni-stopstate").inner_text())


def connected(page: Any) -> None:
    """The bar as it is with a live link: the loop's state, STOP enabled."""
    wait_for(lambda: re.match(r"^(running|STOPPED|PAUSED)", bar_text(page)) is not None, SAID_S, "the loop's state on the bar")
    wait_for(lambda: page.locator("#omni-stopbar > button").is_enabled(), SAID_S, "STOP enabled")


def not_connected(page: Any, why: str) -> float:
    """The page says it has no link, as the issue asks; how long after the last tick it said so (ms)."""
    wait_for(lambda: bar_text(page).startswith(NOT_CONNECTED), SAID_S, f"NOT CONNECTED on the bar ({why})")
    bar = page.locator("#omni-stopbar")
    stop = page.locator("#omni-stopbar > button")
    assert stop.is_disabled() and stop.inner_text() == "STOP unavailable"
    box = bar.bounding_box()
    assert box is not None and box["x"] <= 1 and box["width"] >= page.viewport_size["width"] - 2, box  # full width
    age = page.locator("#omni-linkage").inner_text()
    assert re.search(r"last from the loop \d+\.\d s ago .*t = \d+\.\d s · loop \d+\.\d Hz · reconnecting by itself",
                     age), age
    assert page.evaluate("() => getComputedStyle(document.getElementById('omni-linkage')).color") == "rgb(134, 142, 150)"
    # the panel's own STOP, where viser still shows it, is disabled to the eye and the pointer
    assert page.evaluate("""() => [...document.querySelectorAll('button')].filter(b => b.textContent.trim() === 'STOP'
        && !b.closest('#omni-stopbar')).every(b => b.hasAttribute('data-omni-down')
        && getComputedStyle(b).pointerEvents === 'none')""")
    page.keyboard.press("Space")  # the keyboard's STOP says nothing and reaches nothing: the bar stays as it is
    assert bar_text(page).startswith(NOT_CONNECTED)
    return float(page.evaluate("() => window.omniLink.downAt - window.omniLink.at"))


def test_the_network_down_then_back(browser: Any) -> None:
    with served() as (proc, port):
        relay = Relay(port)
        try:
            page = open_console(browser, relay.port)
            relay.down()
            ms = not_connected(page, "the network down")
            print(f"\nnetwork down: NOT CONNECTED {ms:.0f} ms after the last tick the page had")
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "not-connected-1280x720.png"))
            assert proc.poll() is None  # the service runs on: only the page's link went
            relay.up()
            wait_for(lambda: "RECONNECTED at" in bar_text(page), SAID_S, "the page reconnecting by itself")
            connected(page)
            assert page.evaluate("() => window.omniLink.reconnects") == 1
            page.close()
        finally:
            relay.close()


def test_the_loops_process_killed(browser: Any) -> None:
    with served() as (proc, port):
        page = open_console(browser, port)
        proc.kill()  # the loop's process, at once; the page's process lives on for a while and says so
        ms = not_connected(page, "the loop's process killed")
        print(f"\nloop's process killed: NOT CONNECTED {ms:.0f} ms after the last tick the page had")
        page.close()


def test_the_service_ended(browser: Any) -> None:
    with served() as (proc, port):
        page = open_console(browser, port)
        proc.send_signal(signal.SIGINT)  # Ctrl-C: the service ends as it should, its page with it
        assert proc.wait(60) == 0
        ms = not_connected(page, "the service ended")
        print(f"\nservice ended: NOT CONNECTED {ms:.0f} ms after the last tick the page had")
        page.close()
