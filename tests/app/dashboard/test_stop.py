"""STOP is absolute, in real Chromium: it stays in view wherever the panel is scrolled (1280×720),
it stops the leader as well as the followers (and the recording says so tick by tick), and no
message a client sent before can take it away from a page opened afterwards.

The tests run the service as `run` does by default, the page in a process of its own: they read
the page only as its clients do (a browser, or a raw client that reads the controls off the wire),
and the loop, its store and its recording here."""

from __future__ import annotations

import dataclasses
import numpy as np
import pytest

from app.services.live import Service
from app.recording.reader import read_recording
from tests.helpers import ARTIFACTS, chromium_browser, click_3d, control_id, keep_ticks, new_page, settle, start_timer
from tests.helpers import RawPage, timed_ms, wait_for

playwright_api = pytest.importorskip("playwright.sync_api")
PAGE_MS = 30_000


def _service(tmp_path, page_process: bool):
    """The built-in team on truth feedback, leader driving straight, recording to a file."""
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.recording import start_recording

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, seed=4, dynamics=config.dynamics,
                  recordings=tmp_path, page_process=page_process)
    keep_ticks(svc, 3000)
    svc.recorder = start_recording(svc, config, None, None, None, 1.0, path=tmp_path / "stop.mcap")
    svc.start()
    yield svc
    svc.close()
    svc.recorder.close()


@pytest.fixture()
def page_process_service(tmp_path):
    """As `run` serves it: the page in a process of its own."""
    yield from _service(tmp_path, page_process=True)


def open_page(browser, url: str, width: int = 1280, height: int = 720, scene: bool = True):
    page = new_page(browser, width, height, scene)
    page.goto(url)
    page.wait_for_selector('canvas[data-engine^="three.js"]', timeout=PAGE_MS)
    page.get_by_role("button", name="STOP", exact=True).wait_for(timeout=PAGE_MS)
    settle(page)
    return page


def scroll_every_panel_to_the_bottom(page) -> None:
    page.evaluate("""() => { for (const el of document.querySelectorAll('*')) {
        if (el.scrollHeight > el.clientHeight + 20 && getComputedStyle(el).overflowY !== 'visible')
            el.scrollTop = el.scrollHeight; } }""")


def in_view_and_on_top(page, locator) -> bool:
    box = locator.bounding_box()
    if box is None:
        return False
    vw, vh = page.viewport_size["width"], page.viewport_size["height"]
    if not (box["x"] >= 0 and box["y"] >= 0 and box["x"] + box["width"] <= vw and box["y"] + box["height"] <= vh):
        return False
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    return bool(page.evaluate("([x, y]) => !!document.elementFromPoint(x, y).closest('#omni-stopbar')", [cx, cy]))


def test_stop_stays_in_view_and_stops_the_leader_tick_by_tick_in_the_recording(page_process_service):
    service = page_process_service
    wait_for(lambda: service.loop.last is not None and service.loop.last.leader_twist[0] > 0, 30, "the leader to drive")
    with chromium_browser() as browser:
        page = open_page(browser, service.url)
        scroll_every_panel_to_the_bottom(page)
        bar_stop = page.locator("#omni-stopbar button")
        wait_for(lambda: bar_stop.is_visible(), 10, "the STOP bar")
        assert in_view_and_on_top(page, bar_stop), "STOP must stay in view when the panel is scrolled"
        state = page.locator("#omni-stopstate")
        wait_for(lambda: state.inner_text().startswith("running"), 10, "the state line in the bar")
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "stop-bar-scrolled-1280x720.png"))
        # the bar covers neither the panel's header ("Connected") nor the camera: it sits left of the panel
        panel = page.evaluate("""() => { const n = document.querySelector('.uplot'); let root = null;
            for (let e = n; e; e = e.parentElement) if (e.classList && e.classList.contains('mantine-Paper-root')) root = e;
            return root ? root.getBoundingClientRect().left : null; }""")
        bar_box = page.locator("#omni-stopbar").bounding_box()
        assert panel is not None and bar_box["x"] + bar_box["width"] <= panel + 1, (bar_box, panel)
        # the figures issue 48 asks for (printed, not asserted: they depend on the machine's load):
        # `pytest -s tests/app/dashboard/test_stop.py -k tick_by_tick` prints them
        light = page.locator(f'[id="{control_id(page, "Light mode")}"]').first
        wait_for(lambda: light.is_checked(), 30, "light mode (a page that draws slowly)")
        print(f"\npage at 1280x720: {page.evaluate('window.omniFps')} frames/s, main thread busy"
              f" {page.evaluate('window.omniBusy')}, light mode {light.is_checked()}")
        start_timer(page, "text", ["#omni-stopstate", "^STOPPED"])
        bar_stop.click()
        wait_for(lambda: service.store.get().stop, 10, "STOP from the bar")
        print(f"STOP click to STOPPED shown on the bar: {timed_ms(page):.0f} ms")
        # STOP names who pressed it, and when, on the status and in the events
        assert "by operator 127.0.0.1 at" in state.inner_text(), state.inner_text()
        box = page.locator(f'[id="{control_id(page, "Trails")}"]').first
        start_timer(page, "hidden_3d", "/trails/0")
        box.click()
        wait_for(lambda: not box.is_checked(), 10, "the Trails box off")
        print(f"a click to its effect shown (the trails gone from the 3D view): {timed_ms(page):.0f} ms")
        # a robot clicked in the 3D view (the team stands still: stopped) is ringed there and its card
        # is in view beside it at once, whatever the panel's scroll
        ringed = """() => { const o = window.__viserMutable.nodeRefFromName['/followers/1/picked'];
            return !!o && o.visible !== false; }"""
        assert not page.evaluate(ringed), "F2 is not ringed before it is clicked"
        start_timer(page, "card_in_view", "^F2$")
        click_3d(page, "/followers/1/marker")
        print(f"a robot clicked in 3D to its card in view: {timed_ms(page):.0f} ms")  # F2's card: chosen
        wait_for(lambda: page.evaluate(ringed), 10, "F2 ringed in the 3D view")
        page.screenshot(path=str(ARTIFACTS / "robot-card-1280x720.png"))
        version = service.store.get().version
        wait_for(lambda: sum(1 for s in list(service.seen) if s.params_version >= version) > 45, 30, "1.5 s stopped")
    service.loop.stop()
    service._thread.join(30)
    service.recorder.close()
    rec = read_recording(service.recorder.path)
    ticks = list(rec.ticks)
    stopped = [k for k, d in enumerate(ticks) if d["stopped"]]
    assert stopped and ticks[stopped[0] - 1]["leader_twist"][0] > 0  # it was driving the tick before
    assert len(stopped) > 45
    after = [ticks[k] for k in range(stopped[0], len(ticks))]
    assert all(d["stopped"] for d in after)
    assert all(d["leader_twist"] == [0.0, 0.0] for d in after), "the leader's twist is exactly zero once stopped"
    leader = np.array([d["leader"] for d in after], dtype=float)
    assert np.ptp(leader, axis=0).max() == 0.0, "the leader does not move while stopped"
    assert all(np.all(np.array(d["commands"], dtype=float) == 0.0) for d in after)
    assert [e["detail"] for e in rec.events if e["kind"] == "stop_by"] == ["STOP pressed by operator 127.0.0.1"]


def test_a_hostile_client_cannot_take_stop_away_from_a_page_opened_afterwards(page_process_service):
    """A client that reads the page's controls off the wire, as any browser can, and sends what no
    page sends: nothing changes what STOP does, nor any value beyond its bounds."""
    from core.bounds import PARAMETERS

    service = page_process_service
    gains = {name: PARAMETERS[name].label for name in ("k_w1", "k_f1", "a")}
    gains_before = service.store.get().gains
    client = RawPage(service.page.port)
    try:
        ids = client.uuids({"STOP", "Trial #", *gains.values()})
        stop_uuid = ids["STOP"]
        client.send({"type": "GuiUpdateMessage", "uuid": stop_uuid, "updates": {"update_cb": []}})
        client.send({"type": "GuiUpdateMessage", "uuid": stop_uuid, "updates": {"disabled": True, "visible": False}})
        client.send({"type": "GuiUpdateMessage", "uuid": stop_uuid, "updates": {"label": "go", "value": True}})
        client.send({"type": "GuiUpdateMessage", "uuid": ids["Trial #"], "updates": {"value": 2**64 - 1}})
        client.send({"type": "GuiUpdateMessage", "uuid": ids[gains["k_w1"]], "updates": {"value": 50.0}})
        client.send({"type": "GuiUpdateMessage", "uuid": ids[gains["k_f1"]], "updates": {"value": "0.2"}})
        client.send({"type": "GuiUpdateMessage", "uuid": ids[gains["a"]], "updates": {"value": 5e-324}})
        client.send({"type": "ShareUrlRequest"})
        client.ws.send(b"\xc1 not msgpack")
        client.set(gains["k_f1"], 0.12)  # a change any page may make, handled after all of the above
        wait_for(lambda: service.store.get().gains.k_f1 == 0.12, 10, "the client's valid change")
        assert service.store.get().gains == dataclasses.replace(gains_before, k_f1=0.12), "nothing else changed"
        assert not service.store.get().stop, "a STOP message with a label and a value of its own is no click"
        client.click("STOP")  # the same client's plain click: STOP still stops
        wait_for(lambda: service.store.get().stop, 10, "STOP from the client that tried to take it away")
    finally:
        client.close()
    service.store.update("test", stop=False, leader_hold=False)
    with chromium_browser() as browser:
        page = open_page(browser, service.url, scene=False)  # a new page loads (the huge number never reached viser)
        stop = page.get_by_role("button", name="STOP", exact=True)
        assert stop.is_visible() and stop.is_enabled(), "STOP keeps its place, its name and what it does"
        page.get_by_text("Tuning", exact=True).first.click(timeout=PAGE_MS)
        trial = page.locator(f'[id="{control_id(page, "Trial #")}"] input, input[id="{control_id(page, "Trial #")}"]')
        wait_for(lambda: trial.first.input_value() == "1", 10, "Trial # still 1 on a new page")
        # Escape with a dropdown open closes it and stops nothing; with nothing open it is STOP
        page.locator(f'[id="{control_id(page, "3D camera")}"]').first.click()
        page.get_by_role("option", name="above the leader").wait_for(timeout=PAGE_MS)
        page.keyboard.press("Escape")
        page.get_by_role("option", name="above the leader").wait_for(state="hidden", timeout=PAGE_MS)
        page.wait_for_timeout(300)
        assert not service.store.get().stop, "Escape that closed a menu must not STOP"
        page.keyboard.press("Escape")
        wait_for(lambda: service.store.get().stop, 10, "Escape on a fresh page to stop the team")
        version = service.store.get().version
        wait_for(lambda: sum(1 for s in list(service.seen) if s.params_version >= version) > 3, 10, "ticks stopped")
        for s in [s for s in list(service.seen) if s.params_version >= version]:
            assert s.leader_twist == (0.0, 0.0) and np.all(s.commands == 0.0)
        service.store.update("test", stop=False, leader_hold=False)
        stop.click()  # and the panel's own button
        wait_for(lambda: service.store.get().stop, 10, "the STOP button on a fresh page")


def test_a_viewer_watches_and_may_stop_but_changes_nothing_else(page_process_service):
    """A viewer's page (the viewer link) greys out every control but STOP; a change it makes anyway
    is refused (the viewer is told, its box shows the value in force again); its STOP stops; a raw
    client with the viewer's token that sends Release (once it has the page's controls, and again
    with its first camera, before the page reached it) is told each time it was refused, and STOP
    stays."""

    service = page_process_service
    updates: list[tuple[str, bool]] = []  # every change the loop's store took: who, and STOP after it
    service.store.subscribe(lambda p, source, _: updates.append((source, bool(p.stop))))
    with chromium_browser() as browser:
        page = open_page(browser, service.page.viewer_url, scene=False)  # its panels and STOP
        page.get_by_text("View only").first.wait_for(timeout=PAGE_MS)
        wait_for(lambda: page.get_by_role("button", name="Reset", exact=True).is_disabled(), 10,
                 "the viewer's controls to grey out")
        ident = control_id(page, "k_f1")
        box = page.locator(f'[id="{ident}"] + div input').first
        k_f1 = service.store.get().gains.k_f1
        box.evaluate("el => { el.disabled = false; }")  # a viewer that un-greys its page is still refused
        box.fill("0.3")
        box.press("Enter")
        page.get_by_text("Refused").first.wait_for(timeout=PAGE_MS)  # the gate judged it: it never reached the page
        wait_for(lambda: float(box.input_value()) == k_f1, 10, "the value in force back in the viewer's box")
        assert service.store.get().gains.k_f1 == k_f1 and not updates
        page.locator("#omni-stopbar button").click()
        wait_for(lambda: service.store.get().stop, 10, "the viewer's STOP")
    stops = len(updates)
    release = ""
    for at_once in (False, True):  # after the page's controls came; with its first camera, not reading first
        client = RawPage(service.page.port, path=f"/?token={service.page.viewer_token}")
        try:
            if not at_once:
                release = client.uuids({"Release STOP"})["Release STOP"]
            client.send({"type": "GuiUpdateMessage", "uuid": release, "updates": {"value": True}})
            assert any(m["props"]["title"] == "Refused" and "Release STOP" in m["props"]["body"]
                       for m in client.messages(30.0) if m.get("type") == "NotificationShowMessage"), \
                f"the gate's refusal, told to that client ({'at once' if at_once else 'after the controls'})"
        finally:
            client.close()
    assert len(updates) == stops and all(stop for _, stop in updates), updates
    assert service.store.get().stop, "a viewer cannot release STOP"
