"""Every control of the page reaches the loop, in both of `run`'s modes (issue 82, item 1).

`run` serves the page from a process of its own by default (the loop's process keeps the loop,
its store and its recorder; app.services.page_process); `run --one-process` serves it from the
loop's. In Chromium, one session a mode, the operator sets every control: the cases are made from
the parameter table (core.bounds.PARAMETERS: every row the page may set, found on the page by its
label and set as its widget is set) and from the page's own list of buttons (what the page sends
its clients); a button the table does not stand for must be one of BUTTONS (what it does to the
loop, checked) or of NOT_THE_LOOP (why it does nothing there). A row or a button added later is
tried, or named, without a new test.

What is checked is the loop's own state, never the page's widgets: its store (what the loop reads
each tick), the first tick made with the change (TickState), and at the end the recording's
parameter sets read back from its MCAP file."""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.params import FORMATION_PRESETS, PARAMETERS, Params, formation_preset
from core.bounds import OPERATOR, Parameter
from tests.helpers import RawPage, chromium_browser, keep_ticks, new_page, settle, start_timer, timed_ms, wait_for

playwright_api = pytest.importorskip("playwright.sync_api")
PAGE_MS = 30_000
LOOP_S = 20.0  # how long a change may take to reach the loop on a loaded machine (a hang fails, a slow run does not)
N = 2  # the team at the start

# Buttons the parameter table does not name, each with what it does to the loop (checked below).
BUTTONS = {
    "Release STOP": "stop = false",
    "Drive to goal": "the goal row's (goal and leader mode)",
    "Apply preset": "the slots row's",
    "Run test": "a step test in the loop: its row, measured on the loop's ticks",
    "Cancel test": "the running test ends, its row says cancelled, its step set back",
    "Apply trial's gains": "the gains that trial ran with",
    "Run sweep": "a sweep on the loop's side (its worker process)",
    "Cancel sweep": "the sweep running there stops",
    "Apply point's gains": "the chosen sweep point's gains",
    "Apply best": "the best sweep point's gains",
}
# Buttons that change nothing in the loop, and why.
NOT_THE_LOOP = {
    "Acknowledge alarms": "the page's own health banner: the alarms are judged and shown on the page",
    "Reset the 3D camera": "this browser's view of the 3D scene",
    "Export CSV": "a download of the charts' data the page holds",
    "Export trials CSV": "a download of the trials' table the page holds",
    "Enlarge heat map": "a larger figure in a window on this page",
    "Refresh list": "the Recordings panel's list of files",
    "Replay in a new tab": "a replay, served apart from the loop; it commands no robot",
}
# Rows of the table whose control is not a widget of their own label.
COMPOSITE = {
    "goal": "Goal x / Goal y and Drive to goal",
    "slots": "Preset and Apply preset",
    "slot": "Slot 1 x (each slot's coordinates)",
    "leader_hold": "set by STOP and cleared by the loop once the team is whole; the page's 'Release anyway'"
                   " only shows with a follower untracked, which truth feedback never has",
}


@dataclasses.dataclass
class Console:
    service: Any
    page: Any
    recording: Path
    mode: str
    done: list[tuple[str, Callable[[Params], bool]]] = dataclasses.field(default_factory=list)  # for the recording


def _service(tmp_path: Path, page_process: bool) -> Any:
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.services.recording import start_recording

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc: Any = Service(host="127.0.0.1", port=0, n_followers=N, rate_hz=30.0, seed=5, dynamics=config.dynamics,
                  recordings=tmp_path, page_process=page_process)
    keep_ticks(svc, 600)
    svc.recorder = start_recording(svc, config, None, None, None, 1.0, path=tmp_path / "controls.mcap")
    return svc


@pytest.fixture(scope="module", params=[True, False], ids=["default", "one-process"])
def console(request: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    """One session a mode: the built-in team on truth feedback, recording, and one Chromium page."""
    tmp = tmp_path_factory.mktemp("controls")
    svc = _service(tmp, request.param)
    svc.start()
    try:
        with chromium_browser() as browser:
            page = new_page(browser, 1500, 1400, scene=False)  # the panel's controls, not the 3D view
            page.goto(svc.url)
            page.wait_for_selector(".uplot canvas", timeout=PAGE_MS)
            settle(page)
            page.get_by_text("Tuning", exact=True).first.click(timeout=PAGE_MS)  # its folder opens
            yield Console(svc, page, tmp / "controls.mcap", "default" if request.param else "one-process")
    finally:
        svc.close()
        svc.recorder.close()


# -- the page, as an operator uses it ---------------------------------------------------------

def _ident(page: Any, label: str) -> str:
    loc = page.locator("label").filter(has_text=re.compile(f"^{re.escape(label)}$")).first
    loc.wait_for(timeout=PAGE_MS)
    ident = loc.get_attribute("for")
    assert ident, f"label {label!r} has no control"
    return str(ident)


def _widget(page: Any, label: str) -> tuple[str, str]:
    """(the kind of widget labelled ``label``: slider, checkbox, dropdown, number or text; its id)."""
    ident = _ident(page, label)
    kind = page.evaluate("""(id) => { const el = document.getElementById(id);
        if (!el) return 'text';
        if (el.querySelector('[role=slider]')) return 'slider';
        if (el.type === 'checkbox') return 'checkbox';
        if (el.getAttribute('role') === 'combobox') return 'dropdown';
        return 'number'; }""", ident)
    return str(kind), ident


def _type(page: Any, label: str, text: str) -> None:
    """Type into the number box of a slider or a number input, or a text field; Enter."""
    kind, ident = _widget(page, label)
    if kind == "slider":
        box = page.locator(f'[id="{ident}"] + div input').first
    elif kind == "text":
        box = page.locator("label").filter(has_text=re.compile(f"^{re.escape(label)}$")).first \
            .locator("xpath=ancestor::div[3]//input").first
    else:
        box = page.locator(f'input[id="{ident}"]').first
    box.fill(text)
    box.press("Enter")


def _choose(page: Any, label: str, option: str) -> None:
    _, ident = _widget(page, label)
    page.locator(f'input[id="{ident}"]').click()
    page.get_by_role("option", name=option, exact=True).click()


def _press(page: Any, name: str) -> None:
    button = page.get_by_role("button", name=name, exact=True).first
    wait_for(lambda: button.is_enabled(), LOOP_S, f"{name!r} enabled")
    button.click()


# -- the loop's state -------------------------------------------------------------------------

def _in_force(c: Console, what: str, holds: Callable[[Params], bool]) -> Any:
    """Wait until the loop's store holds ``holds``; the first tick the loop made with it."""
    store = c.service.store
    wait_for(lambda: holds(store.get()), LOOP_S, f"[{c.mode}] {what}: in the loop's store")
    version = store.get().version
    seen = c.service.seen
    wait_for(lambda: any(s.params_version >= version for s in list(seen)), LOOP_S,
             f"[{c.mode}] {what}: a tick of the loop made with it")
    c.done.append((what, holds))
    return next(s for s in list(seen) if s.params_version >= version)


def _grid_value(row: Parameter, now: float) -> float:
    """A value on the control's grid, inside its range, other than ``now``."""
    lo, hi = row.control_range()
    step = float(row.step or 1.0)
    value = lo + round((hi - lo) * 0.37 / step) * step
    if math.isclose(value, now, abs_tol=step / 2):
        value += step
    return float(round(value, 6))


def _value(params: Params, name: str) -> Any:
    return getattr(params.gains, name) if PARAMETERS[name].kind == "gain" else getattr(params, name)


def _set_row(c: Console, row: Parameter) -> str:
    """Set one row of the table as the operator does; the check of the loop's state. Returns how it was set."""
    page, name = c.page, row.name
    now = c.service.store.get()
    if row.kind in ("gain", "number", "count"):
        target = _grid_value(row, float(_value(now, name)))
        kind, _ = _widget(page, row.label)
        assert kind == "slider", (name, kind)
        _type(page, row.label, f"{target:g}")
        tick = _in_force(c, f"{name} = {target:g}", lambda p: math.isclose(float(_value(p, name)), target, abs_tol=1e-9))
        if row.kind == "gain":
            assert math.isclose(getattr(tick.gains, name), target, abs_tol=1e-9), (name, tick.gains)
        if name == "n_followers":
            assert tick.n == target, tick.n
        return "its slider's number box"
    if row.kind == "choice":
        option = next(o for o in row.choices if o not in (now.leader_mode, "goal", "stop"))
        _choose(page, row.label, option)
        _in_force(c, f"{name} = {option}", lambda p: getattr(p, name) == option)
        return "its dropdown"
    if row.kind == "flag" and name == "paused":
        start_timer(page, "text", ["#omni-stopstate", "^PAUSED"])  # the figure issue 82 asks for, printed (-s)
        _press(page, row.label)
        tick = _in_force(c, "paused", lambda p: p.paused)
        print(f"\n[{c.mode}] Pause click to PAUSED on the bar: {timed_ms(page):.0f} ms")
        wait_for(lambda: c.service.loop.last.paused, LOOP_S, f"[{c.mode}] the loop's ticks paused")
        frozen = c.service.loop.last
        wait_for(lambda: c.service.loop.last.tick > frozen.tick + 5, LOOP_S, "ticks while paused")
        assert np.array_equal(c.service.loop.last.followers_world, frozen.followers_world)  # the world stood still
        return "Pause"
    if row.kind == "flag" and name == "stop":
        _press(page, row.label)
        tick = _in_force(c, "stop", lambda p: p.stop)
        assert tick.stopped and not tick.commands.any(), "STOP: every follower at zero"
        assert not any(tick.leader_twist), tick.leader_twist  # the leader too
        return "STOP"
    if row.kind == "flag" and name == "leader_hold":
        assert c.service.store.get().stop and c.service.store.get().leader_hold, "STOP sets the leader's wait"
        _press(page, "Release STOP")  # (BUTTONS) every follower tracked: released at once, no question
        tick = _in_force(c, "stop released", lambda p: not p.stop)
        wait_for(lambda: not c.service.store.get().leader_hold, LOOP_S, "the loop clears the leader's wait")
        assert not tick.stopped
        return "STOP, then Release STOP (the loop clears the wait)"
    if row.kind == "flag":  # a checkbox labelled as its row
        kind, ident = _widget(page, row.label)
        assert kind == "checkbox", (name, kind)
        before = bool(getattr(now, name))
        page.locator(f'[id="{ident}"]').first.click()
        tick = _in_force(c, f"{name} = {not before}", lambda p: bool(getattr(p, name)) == (not before))
        if name == "safety":
            assert tick.safety.startswith("off" if before else "on"), tick.safety
        return "its checkbox"
    if row.kind == "request":
        count = int(getattr(now, name))
        if name == "step_requests":
            assert now.paused, "Single step is for a paused loop (the paused row comes first in the table)"
        _press(page, row.label)
        tick = _in_force(c, f"{name} + 1", lambda p: getattr(p, name) == count + 1)
        if name == "step_requests":
            assert not tick.paused, "the stepped tick advanced the world"
        if name == "reset_requests":
            assert math.hypot(*tick.leader[:2]) < 0.05, tick.leader  # the team back where it starts
        return row.label
    if row.kind == "point":  # the goal: its two coordinates, then Drive to goal
        goal = (0.4, 1.6)
        _type(page, "Goal x (m, odometry frame)", f"{goal[0]:g}")
        _type(page, "Goal y (m, odometry frame)", f"{goal[1]:g}")
        _press(page, "Drive to goal")
        tick = _in_force(c, f"goal {goal}", lambda p: p.goal == goal and p.leader_mode == "goal")
        assert tick.goal == goal, tick.goal
        return COMPOSITE[name]
    if row.kind == "slots":
        preset = next(p for p in FORMATION_PRESETS[1:])
        _choose(page, "Preset", preset)
        _press(page, "Apply preset")
        want = formation_preset(preset, now.n_followers)
        tick = _in_force(c, f"preset {preset}", lambda p: np.allclose(p.slots, want))
        assert np.allclose(tick.slot_targets, want)
        return COMPOSITE[name]
    if row.kind == "slot":
        x = round(float(now.slots[0, 0]) - 0.13, 2)
        _type(page, "Slot 1 x", f"{x:g}")
        tick = _in_force(c, f"slot 1 x = {x:g}", lambda p: math.isclose(float(p.slots[0, 0]), x, abs_tol=1e-9))
        assert math.isclose(float(tick.slot_targets[0, 0]), x, abs_tol=1e-9)
        return COMPOSITE[name]
    raise AssertionError(f"{name}: a row of kind {row.kind!r} the page may set, and this test does not know how"
                         " to set it: teach _set_row its widget")


def _tuning(c: Console) -> list[str]:
    """The Tuning panel's actions: each runs on the loop's side (its step tests and sweeps)."""
    page, svc = c.page, c.service
    tests, sweeps = svc.tests, svc.bench.sweeps
    wait_for(lambda: svc.loop.last is not None and svc.loop.last.t > 3.0, LOOP_S, "the team to settle")
    _type(page, "Measure for (s)", "3")
    before = len(tests.trials)
    slots = svc.store.get().slots.copy()
    _press(page, "Run test")
    _in_force(c, "the step test's step", lambda p: not np.array_equal(p.slots, slots))
    _press(page, "Cancel test")
    wait_for(lambda: len(tests.trials) == before + 1, LOOP_S, f"[{c.mode}] the cancelled test's row")
    assert tests.trials[-1].status.startswith("aborted: cancelled"), tests.trials[-1].status
    _in_force(c, "the step set back", lambda p: np.array_equal(p.slots, slots))
    _press(page, "Run test")
    wait_for(lambda: len(tests.trials) == before + 2, 60.0, f"[{c.mode}] the step test's row")
    trial = tests.trials[-1]
    assert trial.status == "done", trial.status
    _type(page, "k_w2", f"{trial.gains.k_w2 + 0.5:g}")  # off the trial's gains, then back by its row
    _in_force(c, "k_w2 off the trial's", lambda p: p.gains != trial.gains)
    _type(page, "Trial #", str(trial.number))
    _press(page, "Apply trial's gains")
    _in_force(c, "the trial's gains", lambda p: p.gains == trial.gains)
    _type(page, "Range 1", "2:3:2")  # the smallest sweep: k_w2 at 2 and 3, nothing else
    _choose(page, "Gain 2", "none")
    _press(page, "Run sweep")
    wait_for(lambda: sweeps.busy or sweeps.last is not None, LOOP_S, f"[{c.mode}] the sweep running in the loop's process")
    wait_for(lambda: sweeps.last is not None, 120.0, f"[{c.mode}] the sweep's result")
    result = sweeps.last
    best = result.best()
    assert best is not None
    _press(page, "Apply best")
    k = result.values(best)[0]
    _in_force(c, f"the best point's k_w2 = {k:g}", lambda p: math.isclose(p.gains.k_w2, k, abs_tol=1e-9))
    ranked = [k for k in result.order() if result.scores[k] is not None]
    assert len(ranked) == 2, result.scores
    other = ranked[1]  # the second of the Sweep point menu (its first is the best)
    _choose(page, "Sweep point", f"2. {result.point_label(other)}")
    _press(page, "Apply point's gains")
    k = result.values(other)[0]
    _in_force(c, f"the other point's k_w2 = {k:g}", lambda p: math.isclose(p.gains.k_w2, k, abs_tol=1e-9))
    _type(page, "Range 1", "1:4:4")
    _press(page, "Run sweep")
    wait_for(lambda: sweeps.busy, LOOP_S, f"[{c.mode}] a second sweep running")
    last = sweeps.last
    _press(page, "Cancel sweep")
    wait_for(lambda: not sweeps.busy, 60.0, f"[{c.mode}] the sweep cancelled in the loop's process")
    assert sweeps.last is not last and sweeps.last.cancelled, "the sweep's result says it was cancelled"
    return ["Run test", "Cancel test", "Apply trial's gains", "Run sweep", "Apply best", "Apply point's gains",
            "Cancel sweep"]


def test_every_control_reaches_the_loop(console: Console) -> None:
    c = console
    svc = c.service
    port = svc.page.port if svc.page is not None else svc.gate.port
    client = RawPage(port)  # the page's buttons, as it sends them to its clients
    try:
        client.uuids({"Replay in a new tab"}, timeout=60.0)  # the page's last button: every one before it is in
        buttons = set(client.buttons)
    finally:
        client.close()
    rows = [row for row in PARAMETERS.values() if OPERATOR in row.setters]
    by_row = {row.label for row in rows}
    unknown = sorted(b for b in buttons if b not in by_row and b not in BUTTONS and b not in NOT_THE_LOOP)
    assert not unknown, f"buttons this test does not know: {unknown}: add each to BUTTONS (and check it) or NOT_THE_LOOP"
    wait_for(lambda: svc.loop.last is not None and svc.loop.last.t > 1.0, LOOP_S, "the loop running")
    how: dict[str, str] = {}
    order = sorted(rows, key=lambda r: (r.name == "n_followers", r.kind == "request", r.name == "paused"))
    # the team's size last but the requests (it rebuilds the team), Pause before Single step and Reset
    order = [r for r in order if r.kind != "request" and r.name != "paused"] + \
        [r for r in order if r.name == "paused"] + [r for r in order if r.kind == "request"]
    for row in order:
        how[row.name] = _set_row(c, row)
    _press(c.page, "Resume")  # the Pause button, now saying Resume
    _in_force(c, "resumed", lambda p: not p.paused)
    wait_for(lambda: not svc.loop.last.paused, LOOP_S, f"[{c.mode}] the loop's ticks running again")
    pressed = set(_tuning(c)) | {"Release STOP", "Drive to goal", "Apply preset"}
    assert set(BUTTONS) <= pressed, set(BUTTONS) - pressed
    assert {r.name for r in rows} <= set(how), {r.name for r in rows} - set(how)
    # the recording: every change above is in one of its parameter sets, as the loop put it in force
    svc.close()
    svc.recorder.close()
    from app.recording.reader import params_from_payload, read_recording

    recorded = [params_from_payload(p) for _, p in read_recording(c.recording).params]
    missing = [what for what, holds in c.done if not any(holds(p) for p in recorded)
               and not any(s in what for s in ("step_requests", "reset_requests"))]  # requests are not recorded
    assert not missing, f"[{c.mode}] not in the recording's parameter sets: {missing}"
    assert not any(PARAMETERS[n].recorded for n in ("step_requests", "reset_requests"))
