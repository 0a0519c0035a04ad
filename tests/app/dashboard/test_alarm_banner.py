"""The health banner names a cause on the page's side (issue 82, item 3): in Chromium, a page whose
own main thread is busy over half of each second, opened on the loop's machine, says beside the
alarm that it takes the loop's CPU. The page is the gate's (its script as served), in front of a
viser server holding a STOP and an alarm line as the live page's are."""

from __future__ import annotations

import threading

import pytest

from app.dashboard.controls import beat
from app.dashboard.gate import quietly, serve_gated
from tests.app.dashboard.test_health import tick
from tests.helpers import ARTIFACTS, chromium_browser, new_page, settle, wait_for

playwright_api = pytest.importorskip("playwright.sync_api")
ALARM = "**ALARM** · frame to command over one period (33 ms): 7 times in the last minute, last 94 ms"


def test_a_busy_browser_on_the_loops_machine_is_named_beside_the_alarm() -> None:
    server, gate = serve_gated("127.0.0.1", 0)
    ticking = threading.Event()
    try:
        server.gui.add_button("STOP", color="red")
        status = server.gui.add_markdown("starting ...")
        server.gui.add_markdown(ALARM)

        def ticks() -> None:  # the state line as the live page redraws it, five times a second, with its tick
            k = 0
            while not ticking.wait(0.2):
                k += 6
                status.content = f"**running** · t = {k / 30:.1f} s · loop 30.0 Hz{beat(tick(k / 30))}"

        threading.Thread(target=ticks, daemon=True).start()
        with chromium_browser() as browser:
            page = new_page(browser, 1280, 720, scene=False)
            page.goto(gate.url)
            page.get_by_role("button", name="STOP", exact=True).first.wait_for(timeout=60_000)
            settle(page)
            box = page.locator("#omni-alarm")
            wait_for(lambda: box.is_visible() and "7 times in the last minute" in box.inner_text(), 30.0, "the alarm")
            wait_for(lambda: "busy" not in box.inner_text(), 30.0, "a page done loading (an idle page names no cause)")
            wait_for(lambda: page.locator("#omni-stopstate").inner_text().startswith("running"), 30.0, "the bar live")
            # the page's own thread held 300 ms of every 400: long tasks, as a browser drawing in software
            page.evaluate("() => { window.__spin = setInterval(() => { const end = performance.now() + 300;"
                          " while (performance.now() < end) {} }, 400); }")
            wait_for(lambda: "this browser, on the loop's machine, is busy" in box.inner_text(), 30.0,
                     "the page's own cause beside the alarm")
            assert "% of its main thread): it takes the loop's CPU" in box.inner_text()
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "alarm-with-page-cause-1280x720.png"))
            page.evaluate("() => clearInterval(window.__spin)")
            wait_for(lambda: "busy" not in box.inner_text(), 30.0, "the cause gone with the busy thread")
    finally:
        ticking.set()
        gate.close()
        quietly(server.stop)
