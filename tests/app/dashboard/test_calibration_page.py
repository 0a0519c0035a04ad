"""The calibration page in real Chromium, from an empty table to a saved camera file, on the
synthetic rig standing in for a real camera (its mirror tilted 2 deg and 12 px off-centre);
the saved file places markers it never saw within the numbers the page promises."""

from __future__ import annotations

from pathlib import Path

import dataclasses
import math

import numpy as np
import pytest

from app.backends.camera import SyntheticMarkerRig
from app.dashboard.calibration_panel import CalibrationService
from app.files import SYNTHETIC_CAMERA, load_camera
from core.camera.config import WorkingArea, parse_camera
from core.camera.guide import find_marker
from core.camera.model import bearing_range_to_xy

from tests.helpers import ARTIFACTS, chromium_browser, main_cli, new_page, settle, view_on_screen, wait_for

# viser's page sends a control's messages at most once every 50 ms, the newest winning: two clicks of
# one button closer together than that reach the server as one. A browser driven as fast as it goes
# clicks every 20-40 ms on a fast machine, and the page test then counted 24-27 captures of 32 clicks.
# 70 ms apart is still faster than a person clicks.
CLICK_GAP_S = 0.07

playwright_api = pytest.importorskip("playwright.sync_api")


@pytest.fixture(scope="module")
def rig():
    cam = load_camera(SYNTHETIC_CAMERA)
    assert cam.model is not None
    flawed = dataclasses.replace(cam, model=cam.model.replace(tilt_deg=2.0, cx=cam.model.cx + 12.0))
    return flawed, SyntheticMarkerRig(flawed, seed=3)


@pytest.fixture(scope="module")
def service(rig, tmp_path_factory):
    cam, source = rig
    out = tmp_path_factory.mktemp("cal") / "rig.toml"
    svc = CalibrationService(source, cam.detect, out, host="127.0.0.1", port=0)
    yield svc
    svc.close()


def test_from_an_empty_table_to_a_saved_calibration_in_the_browser(service, rig):
    cam, source = rig
    panel = service.panel
    with chromium_browser() as browser:
        page = new_page(browser, 1400, 1300)
        page.goto(service.url)
        page.get_by_role("button", name="Capture", exact=True).wait_for(timeout=30_000)
        settle(page)
        steps = page.locator("ol").filter(has_text="Find the mirror").first  # numbered steps, in order
        steps.wait_for(timeout=30_000)
        items = [t.strip() for t in steps.locator("li").all_inner_texts()]
        assert [t.split()[0] for t in items] == ["Find", "Put", "Capture.", "Save"], items
        # the camera's picture is the page's main view: more than half the window wide, and not blank
        canvas = page.locator('canvas[data-engine^="three.js"]').first
        wait_for(lambda: canvas.bounding_box() is not None, 30.0, "the main view")
        box = canvas.bounding_box()
        assert box["width"] >= 0.5 * 1400, box
        import cv2

        def shown_std() -> float:
            shot = cv2.imdecode(np.frombuffer(page.screenshot(clip=box), np.uint8), cv2.IMREAD_COLOR)
            return float(shot.std())

        wait_for(lambda: shown_std() > 20.0, 30.0, "the camera's picture in the main view")
        wait_for(lambda: abs(service.aspect - box["width"] / box["height"]) < 0.01, 30.0, "the view's shape")
        from app.dashboard.calibration_panel import letterbox

        frame = source.latest()[0]
        shown_w = box["width"] * frame.shape[1] / letterbox(frame, service.aspect).shape[1]  # not stretched
        print(f"main view {box['width']:.0f} x {box['height']:.0f} px, the picture {shown_w:.0f} px wide")
        assert shown_w >= 0.5 * 1400, shown_w
        view_on_screen(page, False)  # the rest is the panel's: the picture is not drawn until the screenshot
        page.get_by_role("button", name="Propose from image").click()
        wait_for(lambda: abs(panel.cx.value - (cam.model.cx)) < 2.0 and abs(panel.cy.value - cam.model.cy) < 2.0,
                 30.0, "the mirror's centre proposed from the picture")
        page.get_by_text("mirror circle: centre").first.wait_for(timeout=30_000)
        # captures that cannot be taken say why and add nothing
        for markers, words in (([], "no marker in the picture"), ([(0.0, 0.6), (90.0, 0.8)], "2 markers")):
            source.place(markers)
            page.get_by_role("button", name="Capture", exact=True).click()
            page.get_by_text(words, exact=False).first.wait_for(timeout=30_000)
            assert panel.rows == []
        # a marker beyond the working area (its outer radius pulled in to 150 px; 2 m is at about 180 px)
        outer = panel.outer.value
        panel.outer.value = 150.0
        source.place([(0.0, 2.0)])
        page.get_by_role("button", name="Capture", exact=True).click()
        page.get_by_text("outside the working area", exact=False).first.wait_for(timeout=30_000)
        assert panel.rows == []
        panel.outer.value = outer
        panel.show_next()  # the helper puts the marker back where the guide asked
        # the guide's plan, clicked faster than a person clicks (CLICK_GAP_S): every click is a capture,
        # none dropped
        plan = len(panel.targets)
        assert min(d for _, d in panel.targets) == 0.3  # from the working ring's inner edge, where followers drive
        button = page.get_by_role("button", name="Capture", exact=True)
        clicks = panel.clicks
        # the first capture held up (as a slow camera would) so that the clicks must queue behind it: on a
        # quiet machine each capture can end before the next click, and the busy note would never show
        panel._busy.acquire()
        try:
            for _ in range(plan):
                button.click(no_wait_after=True)
                page.wait_for_timeout(CLICK_GAP_S * 1e3)
            page.get_by_text("clicks waiting", exact=False).first.wait_for(timeout=30_000)  # it shows it is busy
        finally:
            panel._busy.release()
        wait_for(lambda: len(panel.rows) == plan, 120.0, f"all {plan} captures")
        assert panel.clicks - clicks == plan
        wait_for(lambda: panel.busy.content == "", 60.0, "the busy note cleared after the last click")
        wait_for(lambda: panel.fitted == plan, 60.0, f"the fit of all {plan} markers")
        print(f"calibration page: {plan} quick clicks, {len(panel.rows)} captures")
        page.get_by_text("held-out error: median", exact=False).first.wait_for(timeout=30_000)
        assert panel.held is not None and panel.held.median_cm <= 1.5, panel.held
        # a verdict, the p95 in it; bearings named 0-360 (no negative bearing anywhere in the fit's words)
        verdict = page.locator("[data-verdict]").first
        verdict.wait_for(timeout=30_000)
        said = verdict.inner_text()
        assert f"p95 {panel.held.p95_cm:.1f} cm" in said and ("good, Save" in said or "capture more" in said
                                                               or "usable" in said), said
        import re

        assert not re.search(r"-\d+(\.\d+)? ?(°|deg)", panel.quality.content), panel.quality.content
        ARTIFACTS.mkdir(exist_ok=True)
        view_on_screen(page, True)
        page.screenshot(path=str(ARTIFACTS / "calibration.png"), full_page=True)
        view_on_screen(page, False)
        page.get_by_role("button", name="Save camera file and table").click()
        page.get_by_text("saved", exact=False).first.wait_for(timeout=30_000)
        saved = panel.save_as.value
        text = Path(saved).read_text(encoding="utf-8")
        before = text
        page.get_by_role("button", name="Save camera file and table").click()  # again: never over it unasked
        page.get_by_text("tick Overwrite", exact=False).first.wait_for(timeout=30_000)
        assert Path(saved).read_text(encoding="utf-8") == before
    # the saved file, as locate and run load it, on 80 markers the page never saw
    gamma = parse_camera(text, "rig.toml").gamma
    assert gamma is not None
    area = parse_camera(text, "rig.toml").working_area
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(80):
        b, d = float(rng.uniform(0, 360)), float(rng.uniform(0.3, 1.75))
        source.place([(b, d)])
        blob = find_marker(source.latest()[0], (gamma.cx, gamma.cy), WorkingArea(area.inner_px, area.outer_px),
                           cam.detect)
        assert not isinstance(blob, str), blob
        xy = bearing_range_to_xy(np.array(math.radians(b)), np.array(d))
        errors.append(float(np.linalg.norm(gamma.pixel_to_leader(np.array(blob.u), np.array(blob.v)) - xy)) * 100)
    print(f"calibration page, {len(panel.rows)} captures: 80 fresh markers median {np.median(errors):.2f} cm,"
          f" p95 {np.percentile(errors, 95):.2f} cm; the page's held-out estimate {panel.held}")
    assert np.median(errors) <= 1.5 and np.percentile(errors, 95) <= 3.0, (np.median(errors), np.percentile(errors, 95))
    # what the page said it would be: never more than 1 cm better than the fresh markers show, and cautious by
    # at most 1.5 cm (docs/calibration.md: the plan's first distance, left out, is extrapolated)
    held = panel.held
    assert -1.0 <= held.median_cm - np.median(errors) <= 1.5, (held, np.median(errors))
    assert -1.0 <= held.p95_cm - np.percentile(errors, 95) <= 1.5, (held, np.percentile(errors, 95))


@pytest.mark.parametrize("args, words", [
    (["--page"], "either --camera SOURCE"),
    (["--page", "t.csv", "--synthetic", str(SYNTHETIC_CAMERA)], "builds the table in the browser"),
    (["--page", "--camera", "/nonexistent/video.mp4"], "/nonexistent/video.mp4"),
    (["--page", "--camera", "0", "--tilt", "2"], "shape the synthetic rig"),
    (["t.csv", "--out", "c.toml", "--tilt", "2"], "go with --page"),
])
def test_calibrate_page_bad_input_is_one_line(args, words):
    r = main_cli("calibrate", *args)
    assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
