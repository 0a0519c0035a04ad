"""What several test modules use: the repository's folders, the command line run as a user
runs it (a subprocess, or the same entry point in-process), emulated followers on a real pty,
Debian's Chromium driven by Playwright, and waiting for a condition."""

from __future__ import annotations

import contextlib
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.backends.emulator import FollowerEmulator, PtyEndpoint, serve
from app.processes import interrupt  # noqa: F401  (the tests stop their processes with the app's one helper)

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = ROOT / "test-artifacts"
SCENARIOS = ROOT / "static_config" / "scenarios"
SAMPLES = ROOT / "recordings" / "samples"


def fleet_session(keys: Path | None, identity: str | None, endpoint: str) -> Any:
    """A third party on a fleet's bus, written from docs/fleet-protocol.md: a Zenoh client of the
    hub at ``endpoint`` showing ``identity``'s certificate of the fleet at ``keys`` (mutual TLS);
    with no identity, a plain peer (a client could not even open its session on a hub that
    does not let it in; a peer opens and keeps trying)."""
    import json

    import zenoh

    conf: dict[str, Any] = {"mode": "client" if identity else "peer",
                            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                            "listen": {"endpoints": []}, "connect": {"endpoints": [endpoint]}}
    if identity is not None:
        assert keys is not None
        conf["transport"] = {"link": {"tls": {
            "root_ca_certificate": str(keys / "ca.pem"), "enable_mtls": True,
            "connect_private_key": str(keys / f"{identity}.key"), "connect_certificate": str(keys / f"{identity}.pem"),
            "verify_name_on_connect": False}}}
    return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))


def wait_for(pred: Callable[[], object], timeout: float = 10.0, what: str = "condition") -> float:
    """Poll ``pred`` until it is true; the seconds it took. A time-out fails the test, naming ``what``."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        if pred():
            return time.monotonic() - start
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app.cli", *args], capture_output=True, text=True, timeout=300,
        cwd=cwd or ROOT,
    )


# A fleet test starts several leaders side by side on a two-CPU machine: each runs as one process
# (`run --one-process`, the page in its loop's), half as many interpreters starting at once. An arena
# leader and a fleet leader with the page in a process of its own, the default, are tested in
# tests/app/services/test_loop_process.py.
LEADER_PROCESS = "--one-process"


def spawn_cli(*args: str) -> subprocess.Popen[str]:
    """`omniformation ARGS` as a child in the repository, stdout and stderr piped as text."""
    return subprocess.Popen([sys.executable, "-m", "app.cli", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@dataclass
class ServedRun:
    returncode: int
    startup: str  # stdout up to and including the "dashboard at" line
    stdout: str  # the rest
    stderr: str


def serve_then_signal(*args: str, until: Callable[[], bool] | None = None, hold_s: float = 1.0,
                      sig: int = signal.SIGTERM, command: list[str] | None = None, cwd: Path = ROOT,
                      start_timeout_s: float = 60.0) -> ServedRun:
    """`omniformation run ARGS` as a real process (``command``: another way to start it, e.g. an
    installed console script): wait for its dashboard line, then for ``until`` (or ``hold_s``),
    send ``sig`` and collect everything it printed."""
    proc = subprocess.Popen([*(command or [sys.executable, "-m", "app.cli", "run"]), *args], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines: list[str] = []
        deadline = time.monotonic() + start_timeout_s
        while time.monotonic() < deadline and not (lines and "dashboard at" in lines[-1]):
            line = proc.stdout.readline() if proc.stdout else ""
            if not line and proc.poll() is not None:
                break
            lines.append(line)
        if until is None:
            time.sleep(hold_s)
        else:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not until():
                time.sleep(0.02)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    return ServedRun(proc.returncode, "".join(lines), out, err)


def main_cli(*args: str) -> subprocess.CompletedProcess[str]:
    """The same ``omniformation`` entry point, called in this process: no interpreter start-up
    (~3 s each with the compiled core), the same parsing, messages and exit codes. Only for
    commands that end by themselves; signals and the console script are tested as subprocesses."""
    import contextlib
    import io

    from app.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:  # argparse's usage errors
            code = exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess(["omniformation", *args], code, out.getvalue(), err.getvalue())


class EmulatorThread:
    """Emulated followers on a real pty, in this process so a test can look at the robots."""

    def __init__(self, n: int = 3, drop: float = 0.0, corrupt: float = 0.0, addresses: list[int] | None = None) -> None:
        self.emulator = FollowerEmulator(addresses or list(range(1, n + 1)), drop=drop, corrupt=corrupt, seed=3)
        self.endpoint = PtyEndpoint()
        self.path = self.endpoint.path
        self._stop = threading.Event()
        self._thread = threading.Thread(target=serve, args=(self.emulator, self.endpoint, self._stop), daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.endpoint.close()


def start_emulator_process(link_path: Path, *extra: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "emulate-follower", "--pty", "--link-path", str(link_path),
                             *extra], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "emulating followers 1..3" in line, line + proc.stderr.read()
    return proc


@contextlib.contextmanager
def chromium_browser() -> Iterator[Any]:
    """Debian's Chromium driven by Playwright (Playwright cannot download its own browsers here).

    One a test: launching takes about a second; loading the dashboard took 6-18 s and 9-27 s of
    Chromium's CPU here (its renderer about 5 s, its GPU process, software WebGL, most of the rest),
    alike with a new browser for each of three loads, one browser for all three, and a profile
    kept with its GPU cache. Sharing one browser would save little.

    While a page is open, Chromium's GPU process runs every WebGL frame's shaders on the CPU
    (SwiftShader), about one CPU. Each frame is that costly, not the frames many: a 4 s trace held
    9 frames, in each of which the renderer's main thread waited about 366 ms to read the frame
    back (the compositing is in software here); the page asked for 9-12 animation frames a second.
    Capping the page's animation frames at 4 a second cut that to 63-68 % in one browser, and
    test_stop.py with test_calibration_page.py, by turns, took 167 and 225 CPU-s against 289 and
    235. But viser applies what it receives once a frame, so every wait on the page got up to
    250 ms longer, and fresh-clone CI the same day took 1170 s with the cap and 1187 s without:
    no shorter (its replay and tuning tests 0.7-3.2 times as long with it). Dropped: a cap that
    gains would need the page to apply messages between frames."""
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is missing: `make test` installs it (scripts/ensure-chromium)"
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


def new_page(browser: Any, width: int, height: int, scene: bool = True) -> Any:
    """A page of ``width`` x ``height`` CSS pixels at half the device pixels. These machines
    have no GPU: Chromium renders the 3D scene and the charts on the CPU every frame, and a
    page busy drawing answers clicks seconds late. Half the device pixels (the layout, every
    box and every click position unchanged) is a quarter of that work: the browser tests ran
    about a third faster (the tuning page's three: 86 s -> 56 s).

    ``scene=False``, for a test of the page's panels, not of its 3D view: the view is kept off
    the screen from the start (OFF_SCREEN_VIEW), so viser never draws it. Everything else is the
    page as served: viser still runs a frame for every message it receives and applies the
    messages in it; it only skips drawing a view that is not on the screen. Measured here (the
    built-in team, one page, two turns): loading took 3.4 s and 5.8-5.9 CPU-s against 10.9-11.3 s
    and 18.6-19.6 CPU-s; while open, Chromium used 25-47 % of a CPU against 92-93 %, and the page
    ran 60 animation frames a second against 4-5. ``settle`` checks that the view was found."""
    page = browser.new_page(viewport={"width": width, "height": height}, device_scale_factor=0.5)
    if not scene:
        page.add_init_script(OFF_SCREEN_VIEW)
    return page


# viser's 3D view draws only while its box is on the screen (an IntersectionObserver on the box
# that holds the canvas: the one styled position relative, z-index 0). Moved off the screen
# (a transform: the page's layout is unchanged), it is not drawn.
FIND_VIEW = """() => { for (const canvas of document.querySelectorAll("canvas")) {
    let box = canvas;
    for (let up = 0; box && up < 5; up++, box = box.parentElement)
      if (box.style && box.style.zIndex === "0" && box.style.position === "relative") return box; }
  return null; }"""
OFF_SCREEN = "'translateX(-300vw)'"  # the view's box's CSS transform while it is off the screen (a JS string)
# before the first frame: as soon as the view's box is in the page, it goes off the screen
OFF_SCREEN_VIEW = """
window.__omniView = "looking";
new MutationObserver((_, watch) => {
  const box = (""" + FIND_VIEW + """)();
  if (box) { box.style.transform = """ + OFF_SCREEN + """; window.__omniView = "off screen"; watch.disconnect(); }
}).observe(document, {childList: true, subtree: true});
"""


def view_on_screen(page: Any, on: bool) -> None:
    """Put the page's 3D view back on the screen, or take it off (as new_page's ``scene=False``
    does from the start), for the rest of a test that no longer looks at it."""
    found = page.evaluate("(on) => { const box = (" + FIND_VIEW + ")(); if (!box) return false;"
                          " box.style.transform = on ? '' : " + OFF_SCREEN + "; return true; }", on)
    assert found, "the page's 3D view was not found"
    if on:
        settle(page)


def settle(page) -> None:
    """Wait until the page's main thread is free: right after loading, software WebGL compiles
    its shaders there for seconds on these machines (no GPU)."""
    page.evaluate("() => new Promise(r => requestAnimationFrame(() => r(true)))")
    where = page.evaluate("() => window.__omniView || null")  # a page opened with scene=False
    assert where in (None, "off screen"), f"the 3D view was not found to keep it off the screen: {where}"


# Click-to-visible, timed in the page itself: from the next pointer press (the event's own time, so
# a press that waited for a busy main thread counts its wait) to the first frame drawn after the
# page shows the effect. ``shown`` is one of SHOWN's conditions, with its argument.
SHOWN = {
    "text": "([sel, re]) => { const e = document.querySelector(sel); return !!e && new RegExp(re).test(e.textContent); }",
    "hidden_3d": "(name) => { const m = window.__viserMutable; const o = m && m.nodeRefFromName[name];"
                 " return !!o && o.visible === false; }",
    "card_in_view": """(re) => { const s = Array.from(document.querySelectorAll('strong')).find(e =>
        new RegExp(re).test(e.textContent.trim()) && /\\((tracked|not tracked)\\)/.test(e.parentNode.textContent));
        if (!s) return false; const r = s.parentNode.getBoundingClientRect();
        return r.height > 0 && r.top >= 0 && r.left >= 0 && r.bottom <= innerHeight && r.right <= innerWidth; }""",
}


def start_timer(page, shown: str, arg: Any) -> None:
    """Time the next click on ``page`` until ``SHOWN[shown](arg)`` holds and a frame is drawn (timed_ms)."""
    page.evaluate("""([test, arg]) => { const shown = eval(test);
      window.omniTimer = new Promise(res => { let down = null, done = false;
        document.addEventListener('pointerdown', e => { down = e.timeStamp; }, {capture: true, once: true});
        const check = () => { if (done || down === null || !shown(arg)) return; done = true; ob.disconnect();
          clearInterval(poll); requestAnimationFrame(() => res(performance.now() - down)); };
        const ob = new MutationObserver(check);
        ob.observe(document.body, {subtree: true, childList: true, characterData: true, attributes: true});
        const poll = setInterval(check, 10); }); }""", [SHOWN[shown], arg])


def timed_ms(page) -> float:
    """The click-to-visible time start_timer began (ms); waits for it."""
    return float(page.evaluate("window.omniTimer"))


def click_3d(page, node: str) -> None:
    """Click the 3D view where scene node ``node`` (its centre) is drawn now."""
    at = page.evaluate("""(name) => { const m = window.__viserMutable, o = m.nodeRefFromName[name];
        const v = o.position.clone(); o.getWorldPosition(v); v.project(m.camera);
        const r = m.canvas.getBoundingClientRect();
        return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height]; }""", node)
    page.mouse.click(at[0], at[1])


def control_id(page, label: str) -> str:
    loc = page.locator("label", has_text=label).first
    loc.wait_for(timeout=30_000)
    ident = loc.get_attribute("for")
    assert ident, f"label {label!r} has no control id"
    return ident




def keep_ticks(service: Any, limit: int = 3000) -> list[Any]:
    """Subscribe to a service's loop and keep its last ``limit`` ticks (as ``service.seen``)."""
    seen: list[Any] = []
    lock = threading.Lock()

    def keep(state: Any) -> None:
        with lock:
            seen.append(state)
            del seen[:-limit]

    service.loop.subscribe(keep)
    service.seen = seen
    return seen


class TcpRelay:
    """A TCP relay on a loopback port to ``target_port``, for network partitions on a kernel
    without netem: ``cut(seconds)`` holds every byte in both directions for that long, as a
    link that went away and came back does (TCP keeps what was sent and delivers it late)."""

    def __init__(self, target_port: int) -> None:
        import socket

        self._target = ("127.0.0.1", target_port)
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self._open = threading.Event()
        self._open.set()  # set: bytes flow; clear: cut
        self._closed = False
        self._socks: list[Any] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        import socket

        while not self._closed:
            try:
                a, _ = self._server.accept()
            except OSError:
                return
            try:
                b = socket.create_connection(self._target)
            except OSError:
                a.close()
                continue
            self._socks += [a, b]
            for src, dst in ((a, b), (b, a)):
                threading.Thread(target=self._pump, args=(src, dst), daemon=True).start()

    def _pump(self, src: Any, dst: Any) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                self._open.wait()  # a cut: held here, delivered when it heals
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.close()

    def cut(self, seconds: float) -> None:
        self._open.clear()
        timer = threading.Timer(seconds, self._open.set)
        timer.daemon = True
        timer.start()

    @property
    def is_cut(self) -> bool:
        return not self._open.is_set()

    def close(self) -> None:
        self._closed = True
        self._open.set()
        with contextlib.suppress(OSError):
            self._server.close()
        for s in self._socks:
            with contextlib.suppress(OSError):
                s.close()


class PtyRelay:
    """A leader's radio link through a lossy hop, for partitions on a serial line: the leader
    opens :attr:`path` (a fresh pty); bytes go to and from ``target`` (the radio's pty for this
    leader) ``delay_s`` late, a chunk lost with probability ``drop``; ``cut(seconds)`` loses
    everything both ways for that long (a radio out of range keeps nothing for later)."""

    def __init__(self, target: str, delay_s: float = 0.0, drop: float = 0.0, seed: int = 0) -> None:
        import os
        import random
        import tty

        self._far = os.open(target, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self._far)
        self._near = PtyEndpoint()
        self.path = self._near.path
        self.delay_s, self.drop = delay_s, drop
        self._rng = random.Random(seed)
        self._cut_until = 0.0
        self._closed = threading.Event()
        self.lost = 0  # chunks lost (dropped or cut)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def cut(self, seconds: float) -> None:
        self._cut_until = time.monotonic() + seconds

    @property
    def is_cut(self) -> bool:
        return time.monotonic() < self._cut_until

    def _run(self) -> None:
        import heapq
        import itertools
        import os
        import select

        near = self._near.master
        queue: list[tuple[float, int, int, bytes]] = []  # (due, order, destination fd, bytes)
        order = itertools.count()
        while not self._closed.is_set():
            wait = max(0.0, min(0.01, queue[0][0] - time.monotonic())) if queue else 0.01
            ready, _, _ = select.select([near, self._far], [], [], wait)
            now = time.monotonic()
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                if not data:
                    continue
                if now < self._cut_until or self._rng.random() < self.drop:
                    self.lost += 1
                    continue
                heapq.heappush(queue, (now + self.delay_s, next(order), self._far if fd == near else near, data))
            while queue and queue[0][0] <= now:
                _, _, dst, data = heapq.heappop(queue)
                if now < self._cut_until:
                    self.lost += 1
                    continue
                with contextlib.suppress(OSError):
                    os.write(dst, data)

    def close(self) -> None:
        import os

        self._closed.set()
        self._thread.join(2.0)
        self._near.close()
        with contextlib.suppress(OSError):
            os.close(self._far)


def plain(frames: list[Any], key: bytes | None = None) -> list[Any]:
    """Frames as a robot reads them: an authenticated frame that ``key`` (default: the open key)
    verifies becomes the frame inside it; anything else is left as it came."""
    from core.link import protocol as p

    keys = (key if key is not None else p.OPEN_KEY,)
    return [o.frame if (o := p.open_sealed(f, keys)) is not None else f for f in frames]


def sealed(frame: Any, counter: int, sender: int = 1, key: bytes | None = None) -> bytes:
    """One authenticated frame's bytes (default: the open key, as a leader without a key sends)."""
    from core.link import protocol as p

    return p.encode_frame(p.seal(frame, key if key is not None else p.OPEN_KEY, sender, counter))


class RawPage:
    """A raw client of the page (docs/page-access.md): viser's websocket, as a browser opens it."""

    def __init__(self, port: int, source: str = "127.0.0.1", timeout: float = 60.0, path: str = "/") -> None:
        import viser
        import websockets.sync.client as wsc

        sock = socket.create_connection(("127.0.0.1", port), timeout=timeout, source_address=(source, 0))
        self.ws = wsc.connect(f"ws://127.0.0.1:{port}{path}", sock=sock, subprotocols=[f"viser-v{viser.__version__}"],
                              additional_headers={"Origin": f"http://127.0.0.1:{port}"}, open_timeout=timeout,
                              max_queue=None)
        self.send_camera()  # as a browser does at once (viser counts a client connected from then)
        self.buttons: dict[str, str] = {}  # label -> uuid
        self.controls: dict[str, str] = {}  # every control's label -> uuid

    def messages(self, timeout: float) -> Iterator[dict[str, Any]]:
        import msgspec
        import zstandard

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            frame = self.ws.recv(timeout=max(0.05, end - time.monotonic()))
            if not isinstance(frame, bytes) or len(frame) < 16:
                continue
            inner, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
            body = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:16 + packed],
                                                                                  max_output_size=inner))
            for msg in body.get("messages", []):
                if msg.get("type") == "GuiButtonMessage":
                    self.buttons[msg["props"]["label"]] = msg["uuid"]
                if isinstance(msg.get("props"), dict) and "label" in msg["props"] and "uuid" in msg:
                    self.controls[msg["props"]["label"]] = msg["uuid"]
                yield msg

    def uuids(self, labels: set[str], timeout: float = 60.0) -> dict[str, str]:
        """The uuids of the page's controls by label, as a client reads them off what the page sends it."""
        for _ in self.messages(timeout):
            if labels <= set(self.controls):
                break
        assert labels <= set(self.controls), labels - set(self.controls)
        return {label: self.controls[label] for label in labels}

    def held(self, label: str, timeout: float = 20.0) -> object:
        """The value the page holds for the control ``label``, on a client that just connected: its
        controls and the updates since, up to viser's end of what it replays to a new client."""
        uuid, value = None, None
        for msg in self.messages(timeout):
            props = msg.get("props")
            if isinstance(props, dict) and props.get("label") == label:
                uuid, value = msg.get("uuid"), props.get("value")
            elif uuid is not None and msg.get("type") == "GuiUpdateMessage" and msg.get("uuid") == uuid:
                value = msg["updates"].get("value", value)
            elif msg.get("type") == "ReplayDoneMessage":
                return value
        raise AssertionError(f"no end of the page's replay within {timeout:g} s (looking for {label!r})")

    def wait_for(self, text: str, timeout: float = 60.0) -> bool:
        return any(text in str(msg) for msg in self.messages(timeout))

    def send(self, message: dict[str, Any]) -> None:
        """Any message, as viser's wire carries it (what a page would send, or not)."""
        import msgspec

        self.ws.send(msgspec.msgpack.encode(message))

    def click(self, label: str) -> None:
        self.send_camera()
        self.send({"type": "GuiUpdateMessage", "uuid": self.buttons[label], "updates": {"value": True}})

    def send_camera(self) -> None:
        camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, -3.0, 2.0],
                  "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 720, "image_width": 1280,
                  "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0]}
        self.send(camera)  # a page sends its camera first

    def set(self, label: str, value: Any) -> None:
        """A control's new value, as a browser sends it."""
        self.send({"type": "GuiUpdateMessage", "uuid": self.controls[label], "updates": {"value": value}})

    def close(self) -> None:
        self.ws.close()
