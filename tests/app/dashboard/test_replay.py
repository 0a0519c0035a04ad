"""Replay in real Chromium: a sample recording, the timeline slider, the scene and plots at that
time; and the live dashboard opening a recording from recordings/ in a new tab."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from app.recording.reader import read_recording
from app.services.replay import ReplayService
from core.geometry import leader_to_world
from tests.helpers import ARTIFACTS, chromium_browser, control_id, new_page, settle, view_on_screen, wait_for

from tests.helpers import ROOT
SAMPLE = ROOT / "recordings" / "samples" / "experiment2-vision.mcap"
# A software-WebGL page on a loaded 2-core machine can block its main thread for tens of
# seconds: the page's steps and the waits on the server get long limits (a passing run
# does not wait for them).
PAGE_MS = 90_000
WAIT_S = 60.0


@pytest.fixture(scope="module")
def browser():
    with chromium_browser() as b:
        yield b


def _replay_page(browser, svc: ReplayService, scene: bool = True):
    """A 1400 x 900 page on the replay, its charts drawn (``scene``: as new_page)."""
    page = new_page(browser, 1400, 900, scene)
    page.goto(svc.url)
    page.wait_for_selector(".uplot canvas", timeout=PAGE_MS)
    settle(page)
    return page


def test_timeline_slider_shows_the_recorded_state_of_that_time(browser):
    rec = read_recording(SAMPLE)
    svc = ReplayService(rec, port=0)
    svc.start()
    try:
        page = _replay_page(browser, svc)
        page.wait_for_selector('canvas[data-engine^="three.js"]', timeout=PAGE_MS)
        page.get_by_text("replaying experiment2-vision.mcap").first.wait_for(timeout=PAGE_MS)
        # robot-commanding controls are disabled in replay, and say why
        assert page.get_by_role("button", name="STOP", exact=True).is_disabled(timeout=PAGE_MS)

        target = 61.1  # not a multiple of the live status's 6-tick refresh
        box = page.locator(f'[id="{control_id(page, "Time (s)")}"] + div input').first
        box.fill(f"{target:g}", timeout=PAGE_MS)
        box.press("Enter", timeout=PAGE_MS)
        wait_for(lambda: abs(float(svc.t[svc.index]) - target) < 0.05, WAIT_S, "the replay to jump to 61.1 s")
        k = svc.index
        tick = rec.ticks[k]
        # the 3D scene: each follower where the recording had its estimate at that time
        leader = np.array(tick["leader"], dtype=float)
        est = leader_to_world(np.array(tick["p_est"], dtype=float), leader[:2], float(leader[2]))
        for i, handle in enumerate(svc.dashboard.scene.followers):
            assert np.allclose(handle.position[:2], est[i], atol=1e-4), (i, handle.position, est[i])
        assert np.allclose(svc.dashboard.scene.leader.position[:2], leader[:2], atol=1e-4)
        # the plots: the last 60 s up to that time
        t_plot = np.asarray(svc.dashboard.plots.charts["ex"].data[0])
        assert t_plot[-1] <= float(svc.t[k]) + 1e-6 and t_plot[-1] > float(svc.t[k]) - 0.5
        assert t_plot[0] >= float(svc.t[k]) - 60.5 and len(t_plot) > 50
        ex = np.asarray(svc.dashboard.plots.charts["ex"].data[1])
        p_d, p_true = np.array(tick["p_d"], dtype=float), np.array(tick["p_true"], dtype=float)
        assert math.isclose(ex[-1], (p_d - p_true)[0, 0] * 100, abs_tol=0.2) or math.isclose(  # cm
            ex[-1], (p_d - np.array(tick["p_est"], dtype=float))[0, 0] * 100, abs_tol=0.2)
        # and the page itself shows that moment
        shown = f"t = {float(svc.t[k]):.1f} s"
        page.get_by_text(shown).first.wait_for(timeout=PAGE_MS)
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "replay.png"), timeout=PAGE_MS)
        view_on_screen(page, False)  # the rest is the bar's and the panel's: the 3D view is not drawn
        # a replay never looks live: at a moment that was not stopped, STOP stays disabled (panel and
        # bar), the bar has no STOP to press and says what this page is
        assert not svc.store.get().stop, "the moment shown was not stopped (else this proves nothing)"
        assert page.get_by_role("button", name="STOP", exact=True).is_disabled(timeout=PAGE_MS)
        assert svc.dashboard.controls.stop_button.disabled and svc.dashboard.controls.release_button.disabled
        bar = page.locator("#omni-stopbar")
        wait_for(lambda: "REPLAY — no robot is controlled" in bar.inner_text(), WAIT_S, "the replay's bar")
        assert not page.locator("#omni-stopbar > button").first.is_visible()
        page.keyboard.press("Space")  # no key stops (or does) anything on a replay
        page.keyboard.press("Escape")
        assert not svc.store.get().stop

        # play at 8x, then pause: time moved on by about 8x the wall time
        page.get_by_role("button", name="Play replay").click(timeout=PAGE_MS)
        page.get_by_role("button", name="Pause replay").wait_for(timeout=PAGE_MS)
        start = float(svc.t[svc.index])
        wait_for(lambda: float(svc.t[svc.index]) > start + 1.0, WAIT_S, "playback to advance")
        page.get_by_role("button", name="Pause replay").click(timeout=PAGE_MS)
        wait_for(lambda: not svc.playing, WAIT_S, "playback to pause")
        # next event: experiment 2's follower 2 gets stuck at 58-62 s; events include the start-up phases
        before = float(svc.t[svc.index])
        page.get_by_role("button", name="Previous event").click(timeout=PAGE_MS)
        wait_for(lambda: float(svc.t[svc.index]) < before, WAIT_S, "a jump to the previous event")
        assert any(abs(float(e["t"]) - float(svc.t[svc.index])) < 0.05 for e in rec.events)
    finally:
        svc.close()


def test_the_live_dashboard_opens_a_recording_in_a_new_tab(browser, tmp_path):
    from app.services.live import Service

    svc = Service(port=0, n_followers=2)  # truth feedback: light, this test is about the panel
    svc.start()
    try:
        page = new_page(browser, 1400, 900, scene=False)  # the panel is tested here, not the 3D view
        page.goto(svc.url)
        page.wait_for_selector(".uplot", state="attached", timeout=PAGE_MS)
        settle(page)
        # the folder, collapsed by default; a software-WebGL page on a loaded machine can block
        # its main thread for tens of seconds, hence the long timeouts
        page.get_by_text("Recordings", exact=True).first.click(timeout=PAGE_MS)
        options = svc.recordings.menu.options
        assert "recordings/samples/experiment2-vision.mcap" in options
        svc.recordings.menu.value = "recordings/samples/experiment2-vision.mcap"
        with page.context.expect_page(timeout=PAGE_MS) as opened:  # a tab of its own, opened at the click
            page.get_by_role("button", name="Replay in a new tab").click(timeout=PAGE_MS)
        link = page.locator("a", has_text="experiment2-vision.mcap").first
        link.wait_for(timeout=PAGE_MS)
        url = link.get_attribute("href")
        assert url and re.match(r"http://127\.0\.0\.1:\d+", url) and url != svc.url
        tab = opened.value
        tab.wait_for_url(url, wait_until="commit", timeout=PAGE_MS)  # the new tab goes to the replay
        tab.close()  # (a second software-rendered 3D page would only measure this machine's CPU)
        assert page.url == svc.url  # and the live page stays where it was
        with page.context.expect_page(timeout=PAGE_MS) as again:  # the link too opens a tab, not in place
            link.click(timeout=PAGE_MS)
        again.value.wait_for_url(url, wait_until="commit", timeout=PAGE_MS)
        again.value.close()
        assert page.url == svc.url
        # the replay is served there (its page is the same dashboard, exercised by the test above;
        # a second software-rendered 3D page beside this one would only measure this machine's CPU)
        import urllib.request

        with urllib.request.urlopen(url, timeout=10) as response:
            assert response.status == 200 and b"<html" in response.read(2000).lower()
        (replay,) = svc.recordings.replays
        assert replay.url == url and replay.dashboard.controls.replay
        assert replay.rec.path.name == "experiment2-vision.mcap" and len(replay.rec.ticks) > 3000
        assert svc.loop.tick_count > 0 and not svc.loop.stopping  # the live run went on
    finally:
        svc.close()
    assert svc.recordings.replays == []


def test_the_replayed_page_shows_the_settings_in_force_at_the_moment_shown(browser, tmp_path):
    """A session where k_f1 went from 0.1 to 0.15 at tick 30 and the team was reset at tick 60:
    the replay's page shows 0.1 before the change and 0.15 after it, and the timeline reaches
    the ticks after the reset (the session's clock, which the reset does not set back)."""
    from tests.app.recording.test_session_truth import session_with_a_reset

    session_with_a_reset(tmp_path / "s.mcap")
    rec = read_recording(tmp_path / "s.mcap")
    svc = ReplayService(rec, port=0)
    svc.start()
    try:
        page = _replay_page(browser, svc, scene=False)  # the settings panel is tested here, not the 3D view
        box = page.locator(f'[id="{control_id(page, "Time (s)")}"] + div input').first
        k_f1 = page.locator(f'[id="{control_id(page, "k_f1 (m/s)")}"] + div input').first
        for k, expected in ((10, "0.1"), (40, "0.15"), (120, "0.15"), (20, "0.1")):
            target = round(float(rec.t[k]), 3)
            box.fill(f"{target:g}", timeout=PAGE_MS)
            box.press("Enter", timeout=PAGE_MS)
            wait_for(lambda k=k: abs(svc.index - k) <= 1, WAIT_S, f"the replay at tick {k}")  # (the slider's step)
            wait_for(lambda expected=expected: k_f1.input_value(timeout=PAGE_MS) == expected, WAIT_S,
                     f"k_f1 {expected} on the page at tick {k}")
    finally:
        svc.close()
