"""The operator's console's numbers (issue 82), measured on this machine, printed, never asserted:

1. alarms in a session with one Chromium page on the same machine: the loop's own ticks (the
   vision team `make run` serves, the page in its own process, the page's 3D view drawn) judged by
   the health rules as they are (3 of the last 30 ticks) and, on the same ticks, as they were
   (every late or skipped tick its own alarm once its streak began: HOLD = WINDOW = 1);
2. the loop with a replay tab playing at 8x beside the live page, against the same time without:
   ticks a second, ticks skipped, frame-to-command p50/p99.

    .venv/bin/python scripts/console-numbers.py [SECONDS]   (default 60: each of the three windows)
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


LOG: list[tuple[object, int]] = []  # every tick of the loop, with the loop's count of skipped ticks then


def window(svc, seconds: float) -> dict[str, object]:
    """The loop over ``seconds``: ticks a second, ticks skipped, frame-to-command p50 and p99 (ms)."""
    i0, t0, k0, d0 = len(LOG), time.monotonic(), svc.loop.tick_count, svc.loop.ticks_dropped
    time.sleep(seconds)
    i1, t1, k1, d1 = len(LOG), time.monotonic(), svc.loop.tick_count, svc.loop.ticks_dropped
    part = LOG[i0:i1]
    lat = sorted(s.latency_ms for s, _ in part if s.latency_ms == s.latency_ms)
    return {"hz": (k1 - k0) / (t1 - t0), "skipped": d1 - d0,
            "p50": statistics.median(lat) if lat else float("nan"),
            "p99": lat[int(0.99 * (len(lat) - 1))] if lat else float("nan"),
            "ticks": [s for s, _ in part], "dropped": [d for _, d in part]}


def alarms(ticks, dropped_at, hold: int, width: int, target_hz: float) -> list[str]:
    import app.dashboard.health as health

    saved = health.HOLD, health.WINDOW
    health.HOLD, health.WINDOW = hold, width
    try:
        heard: list[str] = []
        k = [0]
        h = health.Health(target_hz, dropped=lambda: dropped_at[k[0]])
        h.listeners.append(lambda _t, text: heard.append(text))
        for k[0], s in enumerate(ticks):
            h.check(s)
        return heard
    finally:
        health.HOLD, health.WINDOW = saved


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 60.0
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from tests.helpers import SAMPLES, chromium_browser

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics, recordings=SAMPLES, page_process=True)
    svc.loop.subscribe(lambda s: LOG.append((s, svc.loop.ticks_dropped)))
    svc.start()
    try:
        with chromium_browser() as browser:
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.goto(svc.url)
            page.get_by_role("button", name="STOP", exact=True).first.wait_for(timeout=120_000)
            time.sleep(5.0)  # past the page's loading
            base = window(svc, seconds)
            ticks, at = base.pop("ticks"), base.pop("dropped")
            before = alarms(ticks, at, 1, 1, 30.0)
            after = alarms(ticks, at, 3, 30, 30.0)
            print(f"alarms in {seconds:g} s with one page on this machine: {len(before)} as the rules were"
                  f" (every late or skipped tick), {len(after)} with 3 of the last 30 ticks")
            page.get_by_text("Recordings", exact=True).first.click(timeout=60_000)
            page.get_by_role("button", name="Replay in a new tab").click(timeout=60_000)
            link = page.locator("a[href^='http://127.0.0.1:']").first
            link.wait_for(timeout=300_000)  # the replay's link, once its process reads the file and serves
            tab = browser.new_page(viewport={"width": 1280, "height": 720})
            tab.goto(str(link.get_attribute("href")))
            tab.get_by_role("button", name="Play replay").wait_for(timeout=120_000)
            ident = tab.locator("label", has_text="Speed").first.get_attribute("for")
            tab.locator(f'input[id="{ident}"]').click()
            tab.get_by_role("option", name="8", exact=True).click()
            tab.get_by_role("button", name="Play replay").click()
            time.sleep(3.0)
            replay = window(svc, seconds)
            replay.pop("ticks"), replay.pop("dropped")
            for name, w in (("without a replay", base), ("with a replay tab at 8x", replay)):
                print(f"loop {name}: {w['hz']:.2f} ticks/s, {w['skipped']} skipped, frame to command"
                      f" p50 {w['p50']:.1f} ms, p99 {w['p99']:.1f} ms")
            print(f"loop rate with the replay at 8x: {100 * replay['hz'] / base['hz']:.1f} % of without")
    finally:
        svc.close()


if __name__ == "__main__":
    main()
