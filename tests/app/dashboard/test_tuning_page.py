"""The tuning bench in real Chromium: a step test and a 2 x 3 sweep run from the page, the best
point applied and used on the next tick; the Lyapunov monitor shows each follower's V trend;
what cannot run says why.

The page runs in a process of its own, as `run` serves it: the tests read the page as its clients
do (the browser; a second client that reads what the page holds now, as a new tab would get it),
and the loop's side here (its store, its step tests and sweeps)."""

from __future__ import annotations


import pytest

from app.services.live import Service

from tests.helpers import ARTIFACTS, RawPage, chromium_browser, control_id, keep_ticks, new_page, settle, wait_for

playwright_api = pytest.importorskip("playwright.sync_api")


@pytest.fixture(scope="module")
def service():
    """The built-in simulated team with truth feedback (the tuning bench is the same with vision)."""
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, seed=7, page_process=True)
    keep_ticks(svc, 3000)
    svc.start()
    yield svc
    svc.close()


@pytest.fixture(scope="module")
def page(service):
    with chromium_browser() as browser:
        pg = new_page(browser, 1500, 1400, scene=False)  # the panels are tested here, not the 3D view
        pg.goto(service.url)
        pg.wait_for_selector(".uplot canvas", timeout=30_000)
        settle(pg)
        pg.get_by_text("Tuning", exact=True).first.click(timeout=30_000)
        pg.get_by_text("Lyapunov monitor", exact=True).first.click(timeout=30_000)
        yield pg


def _held(service, label: str) -> object:
    """The value the page holds now for the control ``label``, as a client that opens the page gets it."""
    client = RawPage(service.page.port)
    try:
        return client.held(label)
    finally:
        client.close()


def _type(page, label: str, text: str) -> None:
    ident = control_id(page, label)
    box = page.locator(f'input[id="{ident}"], [id="{ident}"] input').first
    if not box.count():  # a text field: its input has an id of its own, in the label's row
        box = page.locator("label", has_text=label).first.locator("xpath=ancestor::div[3]//input").first
    box.fill(text)
    box.press("Enter")


def test_a_step_test_from_the_page_adds_a_scored_row(page, service):
    wait_for(lambda: service.loop.last is not None and service.loop.last.t > 6.0, 60.0, "the team to settle")
    _type(page, "Measure for (s)", "6")
    wait_for(lambda: _held(service, "Measure for (s)") == 6.0, what="the window on the page's server")
    page.get_by_role("button", name="Run test").click()
    wait_for(lambda: len(service.tests.trials) == 1, 60.0, "the trial's row")
    trial = service.tests.trials[0]
    assert trial.status == "done" and trial.score is not None, trial.status
    assert trial.test.kind == "offset" and trial.test.size == pytest.approx(0.10) and trial.test.window_s == 6.0
    page.locator("tr[data-trial='1']").get_by_text("done").wait_for(timeout=30_000)
    assert page.get_by_text("effort (m²/s)", exact=True).count() >= 1  # the effort column's unit
    assert "%" not in trial.disturbed or "0 %" not in trial.disturbed, trial.disturbed  # never "changed 0 %"
    # the monitor: one row per follower, each saying whether its V falls, is flat or rises
    page.locator("td[data-trend]").nth(2).wait_for(timeout=30_000)
    assert page.locator("td[data-trend]").count() == 3


def test_a_sweep_from_the_page_applies_its_best_point_on_the_next_tick(page, service):
    _type(page, "Range 1", "1:4:2")  # 2 x 3 points: the sweep's worker is the test's slowest part on a loaded machine
    _type(page, "Range 2", "0.05:0.2:3")
    wait_for(lambda: _held(service, "Range 1") == "1:4:2" and _held(service, "Range 2") == "0.05:0.2:3",
             what="the ranges")
    page.get_by_role("button", name="Run sweep").click()
    sweeps = service.bench.sweeps
    wait_for(lambda: sweeps.last is not None, 240.0, "the sweep's result")
    result = sweeps.last
    assert result is not None and len(result.gains) == 6 and all(s is not None for s in result.scores)
    page.get_by_text("sweep: done, 6 of 6 points").first.wait_for(timeout=30_000)
    # every grid value is one the gain's slider shows exactly (0.125 would show as 0.13): 0.05, 0.13, 0.2
    assert list(result.ranges[1].values) == [0.05, 0.13, 0.2] and list(result.ranges[0].values) == [1.0, 4.0]
    # the heat map's numbers: at least 11 px as shown (the figure is scaled to the panel's width)
    from app.dashboard.tuning_panel import PANEL_CELL_PT
    from app.figures import excluded_points, figure_rgb, sweep_figure

    page.get_by_role("button", name="Enlarge heat map").wait_for(timeout=30_000)
    # the panel's figure, made here as the page makes it (its shape finds its image on the page)
    shape = figure_rgb(sweep_figure(result, width_in=4.6, stacked=True, metric="settling", cell_pt=PANEL_CELL_PT)).shape
    sizes = page.evaluate("""([w, h]) => [...document.querySelectorAll('img')]
        .filter(i => i.naturalWidth === w && i.naturalHeight === h).map(i => i.getBoundingClientRect().width)""",
                          [shape[1], shape[0]])
    assert sizes, "the heat map's image on the page"
    cell_px = PANEL_CELL_PT * 90 / 72 * sizes[0] / shape[1]
    print(f"heat map cell numbers {cell_px:.1f} px as shown")
    assert cell_px >= 11.0, cell_px
    slack, unsettled, _ = excluded_points(result)  # greyed, and the reason said
    if slack:
        page.get_by_text(f"{len(slack)} of the points that settled, left out by the best rule", exact=False).first.wait_for(
            timeout=30_000)
    if unsettled:
        page.get_by_text(f"{len(unsettled)} did not settle", exact=False).first.wait_for(timeout=30_000)
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "tuning.png"), full_page=True)
    page.get_by_role("button", name="Enlarge heat map").click()  # enlargeable: the same figure, wide, in a window
    dialog = page.get_by_role("dialog")
    dialog.wait_for(timeout=30_000)
    big = dialog.locator("img").first
    big.wait_for(timeout=30_000)
    assert big.evaluate("i => i.naturalWidth") >= 1000 and big.bounding_box()["width"] > sizes[0]
    page.screenshot(path=str(ARTIFACTS / "tuning-heatmap.png"))
    dialog.get_by_role("button", name="Close").click()
    dialog.wait_for(state="hidden", timeout=30_000)
    best = result.best()
    assert best is not None
    k_w2, k_f1 = result.values(best)
    page.get_by_role("button", name="Apply best").click()
    wait_for(lambda: service.store.get().gains.k_w2 == pytest.approx(k_w2)
             and service.store.get().gains.k_f1 == pytest.approx(k_f1), what="the best point's gains in the store")
    # the gain sliders show exactly the applied values
    import re

    for label, value in (("k_f1 (m/s)", k_f1), ("k_w2", k_w2)):  # the Gains folder is open by default
        ident = page.locator("label:visible").filter(has_text=re.compile(f"^{re.escape(label)}$")).first.get_attribute("for")
        box = page.locator(f'[id="{ident}"] + div input').first
        wait_for(lambda box=box, value=value: float(box.input_value() or "nan") == value, 30.0, f"{label} shows {value}")
    version = service.store.get().version
    wait_for(lambda: any(s.params_version >= version for s in list(service.seen)), what="a tick with them")
    first = next(s for s in list(service.seen) if s.params_version >= version)
    assert first.gains.k_w2 == pytest.approx(k_w2) and first.gains.k_f1 == pytest.approx(k_f1)
    # trial 1 ran with the defaults: applying its row sets them back
    trial_gains = service.tests.trials[0].gains
    page.get_by_role("button", name="Apply trial's gains").click()
    wait_for(lambda: service.store.get().gains == trial_gains, what="trial 1's gains in the store")


def test_what_cannot_run_says_why_and_runs_nothing(page, service):
    _type(page, "Range 1", "4:1:3")
    wait_for(lambda: _held(service, "Range 1") == "4:1:3", what="the reversed range")
    page.get_by_role("button", name="Run sweep").click()
    page.get_by_text("reversed", exact=False).first.wait_for(timeout=30_000)
    _type(page, "Range 1", "1:40:3")
    wait_for(lambda: _held(service, "Range 1") == "1:40:3", what="the range beyond the bound")
    page.get_by_role("button", name="Run sweep").click()
    page.get_by_text("(0, 20]", exact=False).first.wait_for(timeout=30_000)
    trials = len(service.tests.trials)
    page.get_by_role("button", name="STOP", exact=True).click()
    wait_for(lambda: service.store.get().stop, what="STOP")
    page.get_by_role("button", name="Run test").click()
    page.get_by_text("STOP is engaged", exact=False).first.wait_for(timeout=30_000)
    assert len(service.tests.trials) == trials and service.tests.status == "idle"
    page.get_by_role("button", name="Release STOP").click()
    wait_for(lambda: not service.store.get().stop, what="STOP released")
