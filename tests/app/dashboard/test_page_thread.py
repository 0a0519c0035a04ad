"""The page is drawn on viser's own thread (app.dashboard.widgets.on_page_thread says why)."""

from __future__ import annotations

import threading

import pytest
import viser

from app.dashboard.widgets import on_page_thread
from app.services.live import Service


def loop_thread_ident(server: viser.ViserServer) -> int:
    seen: list[int] = []
    ran = threading.Event()

    def note() -> None:
        seen.append(threading.get_ident())
        ran.set()

    server.get_event_loop().call_soon_threadsafe(note)
    assert ran.wait(30.0)
    return seen[0]


@pytest.fixture
def server():
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


def test_the_live_dashboard_draws_every_state_on_viser_thread():
    svc = Service(host="127.0.0.1", port=0, n_followers=2, rate_hz=30.0)
    drawn_on: list[int] = []
    enough = threading.Event()

    def note() -> None:  # an extra panel's redraw happens inside the dashboard's drawing
        drawn_on.append(threading.get_ident())
        if len(drawn_on) >= 3:
            enough.set()

    svc.dashboard.extra.append(note)
    svc.start()
    try:
        assert enough.wait(120.0), "the dashboard drew nothing"
        loop_ident = loop_thread_ident(svc.server)
    finally:
        svc.close()
    assert set(drawn_on) == {loop_ident}
    assert svc.publisher.published >= 3


def test_a_page_call_runs_on_viser_thread_and_hands_back_its_error(server):
    loop_ident = loop_thread_ident(server)
    ran_on: list[int] = []
    assert on_page_thread(server, lambda: ran_on.append(threading.get_ident()))
    assert ran_on == [loop_ident]

    def fails() -> None:
        raise ValueError("a view that cannot be drawn")

    with pytest.raises(ValueError, match="cannot be drawn"):
        on_page_thread(server, fails)

    def nested() -> None:  # already on viser's thread: runs at once, no waiting on itself
        assert on_page_thread(server, lambda: ran_on.append(threading.get_ident()))

    assert on_page_thread(server, nested)
    assert ran_on == [loop_ident, loop_ident]


def test_a_page_call_that_cannot_run_in_time_never_runs_late(server):
    release, blocking = threading.Event(), threading.Event()

    def hold() -> None:
        blocking.set()
        release.wait(60.0)

    holder = threading.Thread(target=on_page_thread, args=(server, hold, 120.0))
    holder.start()
    assert blocking.wait(30.0)
    late: list[str] = []
    assert on_page_thread(server, lambda: late.append("drawn"), timeout_s=0.2) is False
    release.set()
    holder.join(30.0)
    assert on_page_thread(server, lambda: late.append("next"))  # viser's thread is free again
    assert late == ["next"]  # the one given up on was never drawn, not even after


def test_a_stopped_server_draws_nothing_and_does_not_hang():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    server.stop()
    drawn: list[int] = []
    assert on_page_thread(server, lambda: drawn.append(1), timeout_s=1.0) is False
    assert drawn == []


def test_light_mode_draws_what_the_operator_asked_for_on_the_next_tick(tmp_path):
    """Light mode draws the 3D view once a second, but a robot chosen (its name's button runs
    ``select``) is ringed and carded on the very next tick, with its errors named and in cm; the
    status says STOPPED on the tick STOP takes effect; light mode turns the shadows off."""
    svc = Service(port=0, n_followers=3, recordings=tmp_path)
    try:
        svc.publisher.close()  # the page drawn here only, tick by tick
        dash = svc.dashboard
        dash.controls.light.value = True
        lights: list[object] = []
        queue = svc.server.scene._websock_interface.queue_message
        svc.server.scene._websock_interface.queue_message = lambda m: (lights.append(m), queue(m))[1]
        assert dash.publish(svc.loop.tick())  # the view drawn: its once-a-second turn starts now
        assert any(type(m).__name__ == "EnableLightsMessage" and m.cast_shadow is False for m in lights)
        dash.scene.select(2)
        assert dash.publish(svc.loop.tick())
        assert dash.scene.picked[2].visible and not dash.scene.picked[0].visible
        card = dash.controls.selected.content
        assert card.startswith("**F3**") and "estimated error" in card and "true error" in card and " cm" in card
        assert "true error to the slot (cm): F1 " in dash.controls.status.content
        svc.store.update("test", stop=True)
        assert dash.publish(svc.loop.tick())
        assert dash.controls.status.content.startswith("**STOPPED"), dash.controls.status.content
    finally:
        svc.close()


def test_a_page_nobody_watches_draws_nothing_and_keeps_what_it_must(server):
    """With ``watched`` saying nobody is there (the page in its own process sets it from the gate's
    open connections), a tick draws nothing but the health rules still judge it (their alarms go to
    the recording) and the charts' history keeps it; the first tick watched draws the page whole."""
    from app.dashboard import Dashboard
    from app.params import Params, ParamsStore, default_slots
    from tests.app.dashboard.test_health import tick

    store = ParamsStore(Params(n_followers=2, slots=default_slots(2)))
    dashboard = Dashboard(server, store)
    dashboard.controls.health.target_hz = 30.0
    heard: list[str] = []
    dashboard.controls.health.listeners.append(lambda _t, text: heard.append(text))
    watching = [False]
    dashboard.watched = lambda: watching[0]
    status = dashboard.controls.status.content
    for k in range(90):  # 3 s at 28 Hz: below 95 % of 30 for more than 2 s
        assert dashboard.publish(tick(k / 30, rate_hz=28.0))
    assert len(heard) == 1 and "28.0 Hz" in heard[0]  # judged though nobody watched
    assert dashboard.controls.status.content == status  # and nothing drawn
    assert dashboard.plots.charts and all(max(chart.data[0]) == 0.0 for chart in dashboard.plots.charts.values())
    assert not dashboard.controls.alarm.visible
    watching[0] = True
    assert dashboard.publish(tick(3.0, rate_hz=28.0))
    assert "t = 3.0 s" in dashboard.controls.status.content and dashboard.controls.alarm.visible
    t = dashboard.plots.charts["ex"].data[0]
    assert t[0] == 0.0 and t[-1] == 3.0  # the ticks nobody watched are on the charts
    assert dashboard.monitor._hist[0][0] == 0.0  # and in the monitor's strip
