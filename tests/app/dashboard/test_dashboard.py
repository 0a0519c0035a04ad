"""The dashboard in real Chromium (Playwright) against a real viser server and loop."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from app.tick import TickState
from app.services.live import Service

from tests.helpers import ARTIFACTS, new_page
from tests.helpers import chromium_browser, control_id, keep_ticks, settle, start_timer, timed_ms, wait_for

playwright_api = pytest.importorskip("playwright.sync_api")

# Every number a chart draws on its canvas, with the x of its left edge (canvas pixels): a tick
# label whose left edge is left of the canvas has lost its first characters (a minus sign).
CHART_TEXT = r"""
(() => { const fill = CanvasRenderingContext2D.prototype.fillText; window.omniChartText = [];
  CanvasRenderingContext2D.prototype.fillText = function (t, x, y, ...rest) {
    const c = this.canvas, m = this.getTransform();
    if (c.closest && c.closest('.uplot') && m.b === 0 && /^[-\u2212]?\d/.test(String(t))) {
      const w = this.measureText(t).width, a = this.textAlign;
      const left = (a === 'right' || a === 'end') ? x - w : a === 'center' ? x - w / 2 : x;
      window.omniChartText.push({chart: Array.from(document.querySelectorAll('.uplot canvas')).indexOf(c),
                                 text: String(t), left: left * m.a + m.e});
    }
    return fill.call(this, t, x, y, ...rest); }; })();
"""


@pytest.fixture(scope="module")
def service():
    """What `make run` serves: default.toml, the synthetic camera and the vision pipeline, the page
    in a process of its own (so these tests read the page only through the browser; the loop,
    its store and its ticks are here)."""
    from app.params import MAX_FOLLOWERS
    from app.live.config import DEFAULT_CONFIG, load_service_config

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, seed=4, camera=config.camera(),
                  dynamics=config.dynamics, page_process=True)
    keep_ticks(svc, 2000)
    svc.start()
    yield svc
    svc.close()


@pytest.fixture(scope="module")
def page(service):
    with chromium_browser() as browser:
        pg = new_page(browser, 1500, 950)
        pg.add_init_script(CHART_TEXT)
        pg.goto(service.url)
        pg.wait_for_selector('canvas[data-engine^="three.js"]', timeout=30_000)
        pg.wait_for_selector(".uplot canvas", timeout=30_000)
        settle(pg)
        yield pg


def states_after(service, version: int) -> list[TickState]:
    return [s for s in list(service.seen) if s.params_version >= version]


def test_page_shows_scene_plots_and_camera_and_is_screenshotted(page, service):
    ARTIFACTS.mkdir(exist_ok=True)
    wait_for(lambda: service.loop.last is not None and service.loop.last.phase == "tracking", 40.0,
             "the vision start-up to finish")
    time.sleep(3.0)  # let trails and plots fill
    assert service.loop.last.tracked.all()
    # the software-rendered page can lag the server by seconds on a loaded two-core machine
    page.get_by_text("poses from: vision, tracking").first.wait_for(timeout=30_000)
    img = page.locator("img[src^='blob:']").first  # viser sends GUI images as blobs (the logo is an SVG data URI)
    img.wait_for(timeout=10_000)
    box = img.bounding_box()
    assert box is not None and box["width"] > 150, "the camera panel shows the leader's frame"
    assert service.page.frames_sent > 10  # frames went to the page (the panel draws them: the blob above)
    page.screenshot(path=str(ARTIFACTS / "dashboard.png"))
    assert (ARTIFACTS / "dashboard.png").stat().st_size > 30_000
    assert page.locator(".uplot").count() >= 6
    assert service.loop.last is not None and service.loop.last.n == 3
    page.locator(".uplot .u-over").first.hover()  # the cursor shows the x value in every synced chart's legend
    legends = page.locator(".uplot .u-legend").all_inner_texts()
    assert legends and not any("1970" in text or "/70" in text for text in legends), legends  # seconds, not dates
    # one cursor for all: every legend shows the same x in seconds (uPlot prints a whole second as "8")
    assert all(re.search(r"t \(s\)\s*\d+(\.\d+)?[FV]", text) for text in legends), legends


def test_kf1_slider_reaches_the_controller_on_the_next_tick(page, service):
    before = service.store.get()
    assert before.gains.k_f1 == pytest.approx(0.10)
    thumb = page.locator(f'[id="{control_id(page, "k_f1 (m/s)")}"] [role=slider]')
    thumb.focus()
    thumb.press("ArrowRight")
    wait_for(lambda: service.store.get().gains.k_f1 == pytest.approx(0.11), what="k_f1 in the store")
    version = service.store.get().version
    wait_for(lambda: len(states_after(service, version)) > 0, what="a tick with the new parameters")
    first = states_after(service, version)[0]
    assert first.gains.k_f1 == pytest.approx(0.11)
    # The tick right before it still used the old value: it took effect on the next tick.
    earlier = [s for s in service.seen if s.tick == first.tick - 1]
    assert earlier and earlier[0].params_version < version


def test_typed_desired_position_moves_the_slot(page, service):
    ident = control_id(page, "Slot 1 x")
    box = page.locator(f'input[id="{ident}"], [id="{ident}"] input').first
    box.fill("-0.8")
    box.press("Enter")
    wait_for(lambda: service.store.get().slots[0, 0] == pytest.approx(-0.8), what="slot 1 x in the store")
    version = service.store.get().version
    wait_for(lambda: len(states_after(service, version)) > 0, what="a tick with the new slot")
    assert states_after(service, version)[0].slot_targets[0, 0] == pytest.approx(-0.8)
    # The follower assigned to slot 1 is driven towards it (ramped, not jumped).
    follower = int(np.flatnonzero(service.loop.last.assignment == 0)[0])
    wait_for(lambda: service.loop.last.p_d[follower, 0] < -0.7, timeout=15.0, what="the desired position to move")


def test_out_of_range_value_is_refused_and_the_box_shows_the_value_in_force(page, service):
    """7 typed into a box that ends at 2 m never reaches viser: the store keeps its value, the box
    is put back to it, and a notice says what is allowed."""
    before = float(service.store.get().slots[1, 1])
    ident = control_id(page, "Slot 2 y")
    box = page.locator(f'input[id="{ident}"], [id="{ident}"] input').first
    box.fill("7")
    box.press("Enter")
    page.get_by_text("must be a number in [-2, 2]").first.wait_for(timeout=10_000)  # the gate's notice
    wait_for(lambda: abs(float(box.input_value()) - before) < 1e-6, what="the box to show the value in force again")
    assert float(service.store.get().slots[1, 1]) == pytest.approx(before)
    assert service.loop.last is not None and service.loop.stopping is False


def test_the_safety_filter_is_on_and_the_page_switches_it(page, service):
    assert service.store.get().safety is True
    wait_for(lambda: service.loop.last is not None and service.loop.last.safety.startswith("on"), what="the filter's state")
    ident = control_id(page, "Safety filter")
    page.locator(f'[id="{ident}"] input, input[id="{ident}"]').first.click()
    wait_for(lambda: service.store.get().safety is False, what="the filter off in the store")
    version = service.store.get().version
    wait_for(lambda: len(states_after(service, version)) > 0, what="a tick without the filter")
    assert states_after(service, version)[0].safety == "off"
    wait_for(lambda: "safety filter: off" in page.inner_text("body"), timeout=15.0, what="the status line to say so")
    page.locator(f'[id="{ident}"] input, input[id="{ident}"]').first.click()
    wait_for(lambda: service.store.get().safety is True, what="the filter back on")


def test_stop_zeroes_every_command_on_the_next_tick(page, service):
    wait_for(lambda: np.abs(service.loop.last.commands).max() > 1e-3, what="followers moving")
    page.get_by_role("button", name="STOP", exact=True).click()
    wait_for(lambda: service.store.get().stop, what="STOP in the store")
    version = service.store.get().version
    wait_for(lambda: len(states_after(service, version)) >= 3, what="ticks after STOP")
    after = states_after(service, version)
    assert all(s.stopped for s in after)
    assert np.all(after[0].commands == 0.0)
    assert np.all(after[-1].commands == 0.0)
    assert after[-1].tick > after[0].tick  # the loop keeps observing
    page.get_by_role("button", name="Release STOP").click()
    wait_for(lambda: not service.store.get().stop, what="STOP released")


def test_shift_click_on_the_floor_gives_the_leader_a_goal(page, service):
    """Goal mode from the 3D view: a shift-click where the floor is sets the goal there (the
    click's ray meets z = 0), the leader mode becomes goal and the status line says how far."""
    canvas = page.locator('canvas[data-engine^="three.js"]').first
    box = canvas.bounding_box()
    assert box is not None
    before = service.store.get().version
    page.keyboard.down("Shift")
    try:
        page.mouse.click(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.75)  # below the horizon: floor
    finally:
        page.keyboard.up("Shift")
    wait_for(lambda: service.store.get().leader_mode == "goal" and service.store.get().goal is not None,
             timeout=20.0, what="the goal in the store")
    p = service.store.get()
    assert p.version > before and max(abs(p.goal[0]), abs(p.goal[1])) <= 10.0
    version = p.version
    wait_for(lambda: any(s.goal is not None for s in states_after(service, version)), what="a tick in goal mode")
    wait_for(lambda: "goal (" in page.inner_text("body"), timeout=15.0, what="the status line to show the goal")
    service.store.update("test", leader_mode="straight", goal=None)


def test_escape_on_the_page_is_stop(page, service):
    """The keyboard STOP the gate adds to the page: Escape presses the STOP button."""
    page.evaluate("document.activeElement && document.activeElement.blur()")  # no text field has the focus
    page.keyboard.press("Escape")
    wait_for(lambda: service.store.get().stop, timeout=15.0, what="STOP from the keyboard")
    version = service.store.get().version
    wait_for(lambda: len(states_after(service, version)) >= 2, what="ticks after STOP")
    assert all(np.all(s.commands == 0.0) for s in states_after(service, version))
    page.get_by_role("button", name="Release STOP").click()  # every follower tracked: no question asked
    wait_for(lambda: not service.store.get().stop, what="STOP released")


def test_plots_window_freeze_and_csv_export(page, service, tmp_path):
    """The Plots folder: a 10 s window, freeze (the charts hold still while the loop runs on),
    and the visible data exported as CSV to this browser."""
    wait_for(lambda: service.loop.tick_count > 30 * 12, timeout=60.0, what="more than 10 s of ticks")
    ident = control_id(page, "Window")
    page.locator(f'[id="{ident}"]').first.click()
    page.get_by_role("option", name="10 s").click()
    spans = """() => Object.values((window.__viserTestpoints || {}).uplots || {}).map(p => {
        const t = p.chart.data[0]; return t && t.length > 1 ? t[t.length - 1] - t[0] : -1; })"""
    wait_for(lambda: (lambda s: len(s) >= 6 and all(0 < x <= 10.001 for x in s))(page.evaluate(spans)), 30.0,
             "every chart drawn over the last 10 s")
    freeze = control_id(page, "Freeze")
    page.locator(f'[id="{freeze}"] input, input[id="{freeze}"]').first.click()

    def export(name: str) -> list[str]:
        with page.expect_download(timeout=30_000) as download:
            page.get_by_role("button", name="Export CSV").click()
        path = tmp_path / name
        download.value.save_as(path)
        return path.read_text().splitlines()

    frozen = export("plots.csv")  # a client's messages are taken in order: the window and freeze first
    ticks = service.loop.tick_count
    wait_for(lambda: service.loop.tick_count > ticks + 30, timeout=30.0, what="the loop to run on")
    assert export("again.csv") == frozen  # the charts held still
    assert frozen[0].startswith("t (s),F1 ex true (cm),")
    assert len(frozen[0].split(",")) == 6 * service.loop.last.n + 2  # t, V and six for each follower
    t = np.array([float(line.split(",")[0]) for line in frozen[1:]])
    assert len(t) > 100 and 9.0 <= t[-1] - t[0] <= 10.0 + 1e-3, (len(t), t[0], t[-1])  # the 10 s window
    page.locator(f'[id="{freeze}"] input, input[id="{freeze}"]').first.click()
    ticks = service.loop.tick_count
    wait_for(lambda: service.loop.tick_count > ticks + 30, timeout=30.0, what="the loop to run on")
    wait_for(lambda: export("moving.csv")[-1] != frozen[-1], 30.0, "the charts moving again once unfrozen")


# Where the browser's 3D camera is, as the browser draws it: its distance to the leader's origin
# (the same in any frame) and where the leader falls in the picture (-1..1 across, 0 in the middle).
CAMERA_TO_LEADER = """() => { const m = window.__viserMutable, o = m.nodeRefFromName['/leader'];
    const v = o.position.clone(), c = o.position.clone(); o.getWorldPosition(v); m.camera.getWorldPosition(c);
    const d = c.distanceTo(v); v.project(m.camera); return [d, v.x, v.y]; }"""
VISIBLE = """(names) => names.map(n => { const o = window.__viserMutable.nodeRefFromName[n];
    return o ? o.visible !== false : null; })"""


def test_the_view_folder_places_the_camera_and_hides_layers(page, service):
    """The 3D camera behind the leader (the default: 2.5 m behind, 2 m up, 3.2 m away) turns with
    it; above the leader it looks straight down on it from 6 m; each layer's box hides its layer;
    the key names what is drawn. All as the browser draws it."""
    import math

    key = page.get_by_text("3D key", exact=False).first
    key.wait_for(timeout=30_000)
    key.scroll_into_view_if_needed()
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "view-key.png"))  # the layers' boxes and the key beside the 3D view
    behind = math.hypot(2.5, 2.0)
    wait_for(lambda: abs(page.evaluate(CAMERA_TO_LEADER)[0] - behind) < 0.3, 30.0,
             "the camera 2.5 m behind the leader, 2 m up")
    page.locator(f'[id="{control_id(page, "3D camera")}"]').first.click()
    page.get_by_role("option", name="above the leader").click()

    def above() -> bool:
        d, x, y = page.evaluate(CAMERA_TO_LEADER)
        return abs(d - 6.0) < 0.3 and abs(x) < 0.1 and abs(y) < 0.1

    wait_for(above, 30.0, "the camera 6 m above the leader, looking at it")
    layers = ["/trails/0", "/trails/1", "/trails/2", "/leader/slots/0", "/leader/slots/1", "/leader/formation"]
    assert page.evaluate(VISIBLE, layers) == [True] * len(layers)
    for name in ("Trails", "Formation and slots"):
        page.locator(f'[id="{control_id(page, name)}"]').first.click()
    try:
        wait_for(lambda: not any(page.evaluate(VISIBLE, layers)), 30.0, "the layers hidden")  # (or not drawn)
    except AssertionError as exc:
        raise AssertionError(f"{exc}: {dict(zip(layers, page.evaluate(VISIBLE, layers)))}") from None
    for name in ("Trails", "Formation and slots"):
        page.locator(f'[id="{control_id(page, name)}"]').first.click()
    page.locator(f'[id="{control_id(page, "3D camera")}"]').first.click()
    page.get_by_role("option", name="behind the leader").click()
    wait_for(lambda: page.evaluate(VISIBLE, layers) == [True] * len(layers), 30.0, "the layers back")
    wait_for(lambda: abs(page.evaluate(CAMERA_TO_LEADER)[0] - behind) < 0.3, 30.0, "the camera behind again")


def test_wide_panel_enlarges_the_charts_and_the_camera(page, service):
    """The page's Wide panel button (this browser only): the charts and the camera at about half
    the window, the panel still in view; pressed again, back."""
    page.locator(".uplot").first.wait_for(state="attached", timeout=60_000)
    narrow = page.locator(".uplot").first.bounding_box()
    assert narrow is not None and narrow["width"] < 450
    page.locator("#omni-wide").click(timeout=60_000)
    wait_for(lambda: (page.locator(".uplot").first.bounding_box() or {"width": 0})["width"] > 550, 30.0,
             "the charts wide")
    img = page.locator("img[src^='blob:']").first
    wait_for(lambda: (img.bounding_box() or {"width": 0})["width"] > 550, 30.0, "the camera wide")
    box = page.locator(".uplot").first.bounding_box()
    assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= page.viewport_size["width"]
    # the wide charts' tick labels, as drawn: each whole (a negative one keeps its minus sign)
    page.evaluate("window.omniChartText = []")
    wait_for(lambda: page.evaluate("window.omniChartText.length") > 40, 30.0, "the wide charts redrawn")
    drawn = page.evaluate("window.omniChartText")
    assert {d["chart"] for d in drawn} >= set(range(6)), drawn
    cut = [d for d in drawn if d["left"] < 0]
    assert not cut, f"tick labels drawn past the chart's left edge: {cut[:5]}"
    assert any(d["text"][0] in "-\u2212" for d in drawn), "the errors and commands go both ways: negative ticks"
    y_labels = page.evaluate("""() => Object.values((window.__viserTestpoints || {}).uplots || {})
        .map(p => p.chart.axes[1].label)""")
    assert y_labels and all(label and "(" in label for label in y_labels), y_labels  # every y axis: quantity (unit)
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "wide-panel.png"))
    page.locator("#omni-wide").click(timeout=60_000)
    wait_for(lambda: (page.locator(".uplot").first.bounding_box() or {"width": 999})["width"] < 450, 30.0,
             "the charts narrow again")


def test_a_robot_named_on_the_panel_is_ringed_and_its_card_is_in_view_at_1600x1000(page, service):
    """Its name's button chooses it: the 3D view rings it and its card (estimated and true error,
    in cm) is in the window at once, whatever the panel's scroll; the time it took is printed."""
    page.set_viewport_size({"width": 1600, "height": 1000})
    try:
        page.get_by_role("button", name="F3", exact=True).wait_for(timeout=30_000)
        page.wait_for_timeout(1000)  # the 3D view redrawn at its new size (an operator does not click mid-resize)
        settle(page)
        light = page.locator(f'[id="{control_id(page, "Light mode")}"]').first.is_checked()
        print(f"\npage at 1600x1000: {page.evaluate('window.omniFps')} frames/s, main thread busy"
              f" {page.evaluate('window.omniBusy')}, light mode {light}")
        ringed = ["/followers/2/picked"]
        assert page.evaluate(VISIBLE, ringed) == [False], "F3 is not ringed before it is chosen"
        start_timer(page, "card_in_view", "^F3$")
        page.get_by_role("button", name="F3", exact=True).click()
        print(f"a robot's name clicked to its card in view (1600x1000): {timed_ms(page):.0f} ms")  # chosen
        wait_for(lambda: page.evaluate(VISIBLE, ringed) == [True], 10.0, "F3 ringed in the 3D view")
        card = page.evaluate("""() => { const s = Array.from(document.querySelectorAll('strong'))
            .find(e => e.textContent.trim() === 'F3' && /\\((tracked|not tracked)\\)/.test(e.parentNode.textContent));
            return s ? s.parentNode.parentNode.textContent : ''; }""")
        assert "estimated error" in card and "true error" in card, card
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "robot-card-1600x1000.png"))
    finally:
        page.set_viewport_size({"width": 1500, "height": 950})
