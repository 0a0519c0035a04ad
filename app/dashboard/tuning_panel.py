"""The page's tuning bench: the Lyapunov monitor, step tests with their table of trials, and
sweeps in the simulator.

* **Lyapunov monitor** (live and replay): per follower eq. 21's V, its rate and whether it is
  falling, flat or rising, the saturations and limits active now, and a strip of the last
  10 s (one row per follower and limit, core.control.tuning.LIMIT_NAMES).
* **Step tests** (live): the operator picks a test and presses Run; app.live.tuning runs it on
  the loop and a row joins the table. Any row's gains can be applied again; the table is
  exported as CSV (and recorded with the session).
* **Sweeps** (live): the same test run by the simulator over a grid of one or two gains from
  the team's present state (app.live.sweep, in a worker process), shown as a heat map and a
  Pareto plot; a point, or the best, sets those gains.

Callbacks only write to the ParamsStore or start / cancel work; nothing here steps the world.
"""

from __future__ import annotations

import html
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import viser

from core.camera.render.looks import follower_rgb
from core.config import Scenario
from core.control.presets import FORMATION_PRESETS
from core.control.tuning import (LIMIT_NAMES, OFFSET_M, TURN_RPS, WINDOW_S, StepTest, flag_names,
                                 lyapunov_trend, parse_gain_range)
from core.types import GAIN_BOUNDS, Gains

from app.dashboard.widgets import assign
from app.params import ParamsStore
from app.live.sweep import SweepRunner
from core.sim.sweep import BEST_RULE, METRICS, SweepResult
from app.tick import TickState
from app.live.tuning import StepTests, Trial, trial_cells, trials_csv
from app.figures import excluded_points
from app.dashboard.controls import range_of
from core.bounds import PARAMETERS
from core.control.tuning import SETTLE_TOL_M, GainRange
from core.sim.sweep import STEADY_SLACK

STRIP_S = 10.0
STRIP_ROW_PX = 8
STRIP_WIDTH = 300
STRIP_GUTTER_PX = 28  # the followers' names
STRIP_AXIS_PX = 16  # the time axis
REDRAW_S = 0.25
LIMIT_RGB = ((230, 120, 20), (150, 60, 200), (200, 30, 30), (30, 110, 210), (20, 150, 90))
TREND_TEXT = {-1: ("falling", "#1a7f37"), 0: ("flat", "#57606a"), 1: ("rising", "#cf222e")}
SWEEP_GAINS = tuple(GAIN_BOUNDS)
PANEL_CELL_PT = 12.0  # the heat map's cell numbers in the panel: the page shows its 414 px figure ~0.78 x, 11.7 px


def on_slider(name: str, value: float) -> float:
    """``value`` on its gain slider's step (the parameter table's row, core.bounds.PARAMETERS),
    so the slider shows exactly what is applied; gains without a slider unchanged."""
    row = PARAMETERS.get(name)
    if row is None or row.step is None or row.bound is None:
        return value
    lo, _, step = range_of(name)
    return round(max(lo, lo + round((value - lo) / step) * step), 6)  # beyond the slider's top: on its steps still


def slider_range(r: GainRange) -> GainRange:
    """A sweep axis with its values on the gain's slider steps (repeats dropped)."""
    values = sorted({on_slider(r.name, float(v)) for v in r.values})
    return GainRange(r.name, np.array(values, dtype=np.float64))


def _legend() -> str:
    items = "".join(f'<span style="display:inline-block;width:9px;height:9px;background:rgb{c};margin:0 3px 0 8px">'
                    f"</span>{html.escape(name)}" for name, c in zip(LIMIT_NAMES, LIMIT_RGB))
    return f'<div style="font-size:11px">rows per follower:{items}</div>'


class LyapunovMonitor:
    """V per follower, its trend and the active limits, redrawn at most every REDRAW_S."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        with server.gui.add_folder("Lyapunov monitor", expand_by_default=False):
            self.table = server.gui.add_html("<i>waiting for the loop</i>")
            self.strip = server.gui.add_image(np.full((STRIP_ROW_PX, STRIP_GUTTER_PX + STRIP_WIDTH, 3), 255, np.uint8),
                                              label="limits, last 10 s",
                                              format="png")
            server.gui.add_html(_legend())
        self._hist: deque[tuple[float, np.ndarray]] = deque()
        self._last = 0.0
        self.text = ""

    def reset(self) -> None:
        self._hist.clear()

    def add(self, s: TickState) -> None:
        """One tick into the strip's history, without drawing."""
        limits = s.limits if s.limits is not None else np.zeros(s.n, dtype=np.int64)
        if self._hist and (s.t < self._hist[-1][0] or len(self._hist[-1][1]) != s.n):
            self._hist.clear()
        self._hist.append((s.t, np.asarray(limits, dtype=np.int64)))
        while self._hist and self._hist[0][0] < s.t - STRIP_S:
            self._hist.popleft()

    def update(self, s: TickState) -> None:
        self.add(s)
        now = time.monotonic()
        if now - self._last < REDRAW_S:
            return
        self._last = now
        self.text = self.render_table(s)
        self.table.content = self.text
        self.strip.image = self.render_strip(s.n)

    @staticmethod
    def render_table(s: TickState) -> str:
        rate = s.v_rate if s.v_rate is not None else np.zeros(s.n)
        trend = lyapunov_trend(rate, s.v_lyap)
        limits = s.limits if s.limits is not None else np.zeros(s.n, dtype=np.int64)
        rows = []
        for i in range(s.n):
            word, color = TREND_TEXT[int(trend[i])]
            r, g, b = follower_rgb(i)
            names = ", ".join(flag_names(int(limits[i]))) or "none"
            v = float(s.v_lyap[i]) if np.isfinite(s.v_lyap[i]) else math.nan
            rows.append(f'<tr><td style="color:rgb({r},{g},{b})"><b>F{i + 1}</b></td><td>{v * 1e4:.3f}</td>'
                        f"<td>{float(rate[i]) * 1e4:+.3f}</td>"
                        f'<td style="color:{color}" data-trend="{word}">{word}</td><td>{html.escape(names)}</td></tr>')
        return ('<table style="font-size:12px;width:100%"><tr><th></th><th>V (cm²)</th><th>dV/dt (cm²/s)</th>'
                "<th>V is</th><th>limits now</th></tr>" + "".join(rows) + "</table>")

    def render_strip(self, n: int) -> np.ndarray:
        """Per follower one row per limit (LIMIT_RGB) over the last STRIP_S, the follower named in
        its colour on the left, the time axis below (seconds before now)."""
        import cv2

        k = len(LIMIT_NAMES)
        rows_px = max(1, n * k) * STRIP_ROW_PX
        img = np.full((rows_px + STRIP_AXIS_PX, STRIP_GUTTER_PX + STRIP_WIDTH, 3), 255, np.uint8)
        plot = img[:rows_px, STRIP_GUTTER_PX:]
        for i in range(n):
            r, g, b = follower_rgb(i)
            cv2.putText(img, f"F{i + 1}", (3, i * k * STRIP_ROW_PX + (k * STRIP_ROW_PX) // 2 + 5),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.42, (r, g, b), 1, cv2.LINE_AA)
            if i:
                img[i * k * STRIP_ROW_PX - 1, :] = (r, g, b)
        for frac, text in ((0.0, f"-{STRIP_S:g} s"), (0.5, f"-{STRIP_S / 2:g} s"), (1.0, "now")):
            x = STRIP_GUTTER_PX + int(frac * (STRIP_WIDTH - 1))
            img[rows_px:rows_px + 3, x] = 90
            size = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)[0][0]
            cv2.putText(img, text, (min(max(x - size // 2, 0), img.shape[1] - size), rows_px + 13),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
        if not self._hist:
            return img
        t = np.array([h[0] for h in self._hist])
        flags = np.array([h[1] for h in self._hist]).reshape(len(t), -1)
        if flags.shape[1] != n:
            return img
        col = np.clip(((t - (t[-1] - STRIP_S)) / STRIP_S * (STRIP_WIDTH - 1)).astype(int), 0, STRIP_WIDTH - 1)
        for i in range(n):
            for bit in range(k):
                on = col[((flags[:, i] >> bit) & 1).astype(bool)]
                if on.size:
                    y0 = (i * k + bit) * STRIP_ROW_PX
                    plot[y0:y0 + STRIP_ROW_PX - 1, on] = LIMIT_RGB[bit]
        return img


@dataclass(frozen=True)
class SweepAsk:
    """A sweep as the panel's widgets describe it, in plain values (what a page in a process of its
    own sends the loop's side, which checks it as the panel would)."""

    gain1: str
    range1: str
    gain2: str  # "none": one gain
    range2: str
    feedback: str  # "truth" or "vision"


class Bench(Protocol):
    """What the panel asks of the loop's side: its step tests (``tests``: trials, status, listeners,
    request, cancel) and sweeps (``sweeps``: on_progress, on_done, cancel), and a sweep started."""

    tests: Any
    sweeps: Any
    vision_offered: bool

    def start_sweep(self, ask: SweepAsk, test: StepTest) -> str | None: ...


class LiveBench:
    """The bench in the loop's process: step tests on the loop, sweeps in a worker from the team now."""

    def __init__(self, store: ParamsStore, tests: StepTests, sweeps: SweepRunner,
                 base: Callable[[], tuple[Scenario, tuple[float, float]] | str],
                 vision: Callable[[], Any] | None) -> None:
        """``base()``: the team now as a scenario (app.live.tuning.live_base) or why not;
        ``vision()``: the rig and Γ for sweeps with vision in the loop (None: not offered)."""
        self.store = store
        self.tests = tests
        self.sweeps = sweeps
        self._base = base
        self._vision = vision
        self.vision_offered = vision is not None

    def start_sweep(self, ask: SweepAsk, test: StepTest) -> str | None:
        """Start the sweep ``ask`` describes; why not, or None. Each grid value is taken to its gain
        slider's step, so the point applied is the point measured and the slider shows it exactly."""
        try:
            if ask.gain1 not in SWEEP_GAINS or ask.gain2 not in ("none", *SWEEP_GAINS):
                raise ValueError(f"gains {ask.gain1!r}, {ask.gain2!r}: must be among {', '.join(SWEEP_GAINS)}")
            ranges = [slider_range(parse_gain_range(f"{ask.gain1}={ask.range1}"))]
            if ask.gain2 != "none":
                ranges.append(slider_range(parse_gain_range(f"{ask.gain2}={ask.range2}")))
        except ValueError as exc:
            return str(exc)
        base = self._base()
        if isinstance(base, str):
            return base
        scenario, twist = base
        from core.control.tuning import check_step_test

        why = check_step_test(test, scenario.n)
        if why:
            return why
        vision = None
        if ask.feedback == "vision":
            if self._vision is None:
                return "vision sweeps need the synthetic rig (run with the simulated camera)"
            vision = self._vision()
        elif ask.feedback != "truth":
            return f"feedback {ask.feedback!r}: must be truth or vision"
        return self.sweeps.start(scenario, test, twist, ranges, self.store.get().gains, vision)


class TuningPanel:
    """Step tests and sweeps on the live team."""

    def __init__(self, server: viser.ViserServer, store: ParamsStore, bench: Bench) -> None:
        """``bench``: the loop's side (LiveBench in one process; a proxy over the pipe when the page
        runs in a process of its own, app.services.page_tuning)."""
        self.server = server
        self.store = store
        self.bench = bench
        self.tests = bench.tests
        self.sweeps = bench.sweeps
        vision = bench.vision_offered
        self.message = ""
        self.sweep_message = ""
        self.result: SweepResult | None = None
        self._point_index: dict[str, int] = {}
        self._status_shown = ""
        gui = server.gui
        n = store.get().n_followers
        with gui.add_folder("Tuning", expand_by_default=False):
            self.kind = gui.add_dropdown("Step test", options=("offset", "switch", "turn"), initial_value="offset",
                                         hint="offset: one follower's slot moves sideways; switch: to the formation"
                                              " below; turn: the leader's turn rate steps")
            self.follower = gui.add_dropdown("Which follower", options=tuple(f"F{i + 1}" for i in range(n)), initial_value="F1")
            self.size = gui.add_number("Step size (cm)", initial_value=10.0, step=1.0,
                                       hint=f"offset: cm ({OFFSET_M[0] * 100:g} to {OFFSET_M[1] * 100:g}, either way);"
                                            f" turn: deg/s ({math.degrees(TURN_RPS[0]):g} to"
                                            f" {math.degrees(TURN_RPS[1]):g}, either way)")
            self.formation = gui.add_dropdown("Switch to", options=FORMATION_PRESETS, initial_value="line abreast",
                                              visible=False)
            self.window = gui.add_number("Measure for (s)", initial_value=10.0, min=WINDOW_S[0], max=WINDOW_S[1], step=1.0,
                                         hint="how long each follower's response is measured")
            self.run_button = gui.add_button("Run test", hint="apply the test and measure: settling to 2 cm,"
                                                              " overshoot, steady RMS, effort")
            self.cancel_button = gui.add_button("Cancel test", color="gray")
            self.status = gui.add_markdown("step test: idle")
            self.table = gui.add_html("<i>no trials yet</i>")
            self.row = gui.add_number("Trial #", initial_value=1, min=1, step=1)
            self.reapply = gui.add_button("Apply trial's gains", hint="set the gains that trial ran with", disabled=True)
            self.export = gui.add_button("Export trials CSV")
            with gui.add_folder("Sweep in the simulator"):
                self.gain1 = gui.add_dropdown("Gain 1", options=SWEEP_GAINS, initial_value="k_w2")
                self.range1 = gui.add_text("Range 1", initial_value="1:4:5", hint="LO:HI:COUNT, both ends included")
                self.gain2 = gui.add_dropdown("Gain 2", options=("none", *SWEEP_GAINS), initial_value="k_f1")
                self.range2 = gui.add_text("Range 2", initial_value="0.05:0.2:5")
                self.feedback = gui.add_dropdown("Feedback", options=("truth", "vision") if vision else ("truth",),
                                                 initial_value="truth",
                                                 hint="truth: simulated poses plus noise; vision: the pipeline on"
                                                      " rendered frames (slower)")
                self.sweep_button = gui.add_button("Run sweep", hint="the test above, in the simulator, from the"
                                                                     " team's present state, for every grid point")
                self.progress = gui.add_progress_bar(0.0, animated=False)
                self.cancel_sweep = gui.add_button("Cancel sweep", color="gray", disabled=True)
                self.sweep_status = gui.add_markdown("sweep: none yet")
                self.metric = gui.add_dropdown("Heat map shows", options=tuple(METRICS), initial_value="settling",
                                               hint="the colour and the number in each cell: one figure, with its unit")
                self.figure = gui.add_image(np.full((8, 8, 3), 255, np.uint8), format="png", visible=False)
                self.excluded = gui.add_markdown("")
                self.enlarge = gui.add_button("Enlarge heat map", disabled=True, hint="the same figure, large, in a window")
                self.point = gui.add_dropdown("Sweep point", options=("none",), initial_value="none", disabled=True,
                                              hint="best first: settled, then fastest, then least overshoot")
                self.apply_point = gui.add_button("Apply point's gains", disabled=True)
                self.apply_best = gui.add_button("Apply best", disabled=True)
        self.tests.listeners.append(self._on_trial)
        self.sweeps.on_progress.append(self._on_progress)
        self.sweeps.on_done.append(self._on_sweep)
        self._wire()

    # -- what the operator asked ----------------------------------------------------------
    def test_from_widgets(self) -> StepTest:
        kind = str(self.kind.value)
        size = float(self.size.value)
        scaled = size / 100.0 if kind == "offset" else math.radians(size)
        follower = int(str(self.follower.value)[1:]) - 1
        return StepTest(kind, follower, scaled, str(self.formation.value), float(self.window.value))

    def run_test(self) -> str:
        why = self.tests.request(self.test_from_widgets())
        self.message = f"refused: {why}" if why else "requested"
        self.status.content = f"step test: {self.message}"
        return self.message

    def start_sweep(self, feedback: str | None = None) -> str | None:
        """Start the sweep the widgets describe (``feedback``: instead of the widget's); why not, or None."""
        ask = SweepAsk(str(self.gain1.value), str(self.range1.value), str(self.gain2.value), str(self.range2.value),
                       str(feedback or self.feedback.value))
        return self.bench.start_sweep(ask, self.test_from_widgets())

    def _show_fields(self) -> None:
        """Only the fields the chosen test uses, the step size labelled with its unit."""
        kind = str(self.kind.value)
        self.follower.visible = kind == "offset"
        self.size.visible = kind in ("offset", "turn")
        self.size.label = "Step size (cm)" if kind == "offset" else "Step size (deg/s)"
        self.formation.visible = kind == "switch"

    def _wire(self) -> None:
        @self.kind.on_update
        def _(event: viser.GuiEvent[Any]) -> None:
            self._show_fields()

        @self.metric.on_update
        def _(event: viser.GuiEvent[Any]) -> None:
            self._draw_sweep()

        @self.run_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            self.run_test()

        @self.cancel_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            self.tests.cancel()

        @self.reapply.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            k = int(self.row.value) - 1
            trials = list(self.tests.trials)
            if not 0 <= k < len(trials):
                self.status.content = f"step test: trial {k + 1} does not exist (1..{len(trials)})"
                return
            self._set_gains(trials[k].gains.as_dict(), f"trial {k + 1}")

        @self.export.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            if event.client is not None:
                event.client.send_file_download("omniformation-trials.csv", trials_csv(list(self.tests.trials)),
                                                save_immediately=True)

        @self.sweep_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            why = self.start_sweep()
            if why:
                self.sweep_message = f"refused: {why}"
            else:
                self.sweep_message = "running"
                assign(self.progress, 0.0)
                self.cancel_sweep.disabled = False
                self.sweep_button.disabled = True
            self.sweep_status.content = f"sweep: {self.sweep_message}"

        @self.cancel_sweep.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            if self.sweeps.cancel():
                self.sweep_status.content = "sweep: cancelling (the point running finishes)"

        @self.apply_point.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            if self.result is None or self.point.value not in self._point_index:
                return
            k = self._point_index[str(self.point.value)]
            self._set_gains({r.name: v for r, v in zip(self.result.ranges, self.result.values(k))}, "sweep point")

        @self.apply_best.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            self.apply_best_point()

        @self.enlarge.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            if event.client is not None and self.result is not None:
                self.show_enlarged(event.client)

    def show_enlarged(self, client: viser.ClientHandle) -> None:
        """The heat map and Pareto plot, wide, in a window over the page (every cell numbered)."""
        from app.figures import figure_rgb, sweep_figure

        assert self.result is not None
        image = figure_rgb(sweep_figure(self.result, width_in=12.0, metric=str(self.metric.value), cell_pt=12.0))
        with client.gui.add_modal("Sweep: heat map and Pareto plot") as modal:
            client.gui.add_image(image, format="png")
            client.gui.add_markdown(self.excluded.content)
            client.gui.add_button("Close").on_click(lambda _: modal.close())

    def apply_best_point(self) -> dict[str, float] | None:
        """Set the best point's gains; which were set (None: no result)."""
        if self.result is None or self.result.best() is None:
            return None
        k = self.result.best()
        assert k is not None
        values = {r.name: v for r, v in zip(self.result.ranges, self.result.values(k))}
        self._set_gains(values, "best sweep point")
        return values

    def _set_gains(self, values: dict[str, float], what: str) -> None:
        asked = {k: float(f"{v:.4g}") for k, v in values.items()}  # a sweep's grid: 0.0875, not 0.08750000000000001
        values = {k: on_slider(k, v) for k, v in asked.items()}  # what the gain's slider shows, exactly
        _, notices = self.store.update("tuning", **values)
        shown = ", ".join(f"{k}={v:g}" for k, v in values.items())
        snapped = [f"{k} {asked[k]:g} -> {v:g}" for k, v in values.items() if v != asked[k]]
        notes = [n.message for n in notices] + ([f"to the sliders' steps: {', '.join(snapped)}"] if snapped else [])
        extra = f" ({'; '.join(notes)})" if notes else ""
        self.sweep_status.content = f"sweep: applied {what}: {shown}{extra}"

    # -- what came back -------------------------------------------------------------------
    def _on_trial(self, trial: Trial) -> None:
        trials = list(self.tests.trials)
        head = ("<tr><th>#</th><th>test</th><th>status</th><th>settle (s)</th><th>overshoot (cm)</th>"
                "<th>steady RMS (cm)</th><th title='∫ mean squared wheel speed dt'>effort (m²/s)</th>"
                "<th>gains changed</th></tr>")
        default = Gains().as_dict()  # the controller's defaults (README): what each trial changed from them
        body = []
        for t in trials[-12:]:
            cells = trial_cells(t)
            changed = ", ".join(f"{k}={v:g}" for k, v in t.gains.as_dict().items() if default.get(k) != v) or "defaults"
            body.append(f"<tr data-trial='{t.number}'><td>{cells[0]}</td><td>{html.escape(cells[1])}</td>"
                        f"<td>{html.escape(cells[2])}</td><td>{cells[-4]}</td><td>{cells[-3]}</td><td>{cells[-2]}</td>"
                        f"<td>{cells[-1]}</td><td>{html.escape(changed)}</td></tr>")
        self.table.content = f'<table style="font-size:11px;width:100%">{head}{"".join(body)}</table>'
        assign(self.row, trial.number)
        self.reapply.disabled = not trials
        self.status.content = f"step test: trial {trial.number} {trial.status}" + (
            f"  \n**warning: {html.escape(trial.disturbed)}: the scores are not the controller's alone**"
            if trial.disturbed else "")

    def _on_progress(self, done: int, total: int) -> None:
        assign(self.progress, 100.0 * done / max(1, total))
        self.sweep_status.content = f"sweep: {done} of {total} points"

    def _on_sweep(self, result: SweepResult) -> None:
        self.result = result
        ran = sum(s is not None for s in result.scores)
        self._draw_sweep()
        order = [k for k in result.order() if result.scores[k] is not None]
        labels = [f"{rank + 1}. {result.point_label(k)}" for rank, k in enumerate(order)] or ["none"]
        self._point_index = {label: k for label, k in zip(labels, order)}
        self.point.options = tuple(labels)
        assign(self.point, labels[0])
        self.point.disabled = self.apply_point.disabled = self.apply_best.disabled = not order
        self.cancel_sweep.disabled = True
        self.sweep_button.disabled = False
        state = "cancelled" if result.cancelled else "done"
        errors = f"; {len(result.errors)} points failed: {result.errors[0]}" if result.errors else ""
        self.sweep_status.content = (f"sweep: {state}, {ran} of {len(result.gains)} points in {result.seconds:.1f} s"
                                     f" ({result.feedback} feedback){errors}  \n{BEST_RULE}")

    def _draw_sweep(self) -> None:
        from app.figures import figure_rgb, sweep_figure

        if self.result is None:
            return
        fig = sweep_figure(self.result, width_in=4.6, stacked=True, metric=str(self.metric.value), cell_pt=PANEL_CELL_PT)
        self.figure.image = figure_rgb(fig)
        self.figure.visible = True
        self.enlarge.disabled = False
        slack, unsettled, limit = excluded_points(self.result)
        lines = []
        if slack:
            lines.append(f"**hatched grey: {len(slack)} of the points that settled, left out by the best rule**: their steady"
                         f" error is above {STEADY_SLACK[0]:g} × the smallest + {STEADY_SLACK[1] * 100:g} cm"
                         f" = {limit * 100:.2f} cm")
        if unsettled:
            lines.append(f"**grey \"no\": {len(unsettled)} did not settle** (within {SETTLE_TOL_M * 100:g} cm by the"
                         " window's end)")
        self.excluded.content = "  \n".join(lines)

    def set_followers(self, n: int) -> None:
        options = tuple(f"F{i + 1}" for i in range(n))
        if tuple(self.follower.options) != options:
            value = self.follower.value if self.follower.value in options else "F1"
            self.follower.options = options
            assign(self.follower, value)

    def update(self, s: TickState) -> None:
        self.set_followers(s.n)
        status = self.tests.status
        if status != "idle" and status != self._status_shown:
            self.status.content = f"step test: {status}"
        self._status_shown = status
