"""Live uPlot charts: x / y error per follower (fig. 19 style), headings, team V, commands.

Every chart names its quantity, its source (true pose in simulation, else the estimate) and its
unit on its title and its y axis: errors in cm (as the status and the robot card), V in cm², as
the Lyapunov monitor. The y axis is wide enough for its longest tick label ("-0.015" lost its
minus sign at uPlot's default 50 px when the Wide panel gave the axis more ticks).

The loop appends every tick to ring buffers (the last 5 minutes); the charts show the last
10 s, 60 s or 5 min (the operator's choice) and are redrawn at about 10 Hz from a decimated
copy, so the page stays smooth at any loop rate. "Freeze" holds the charts still while the
loop runs on; "Export CSV" sends the data the charts show (every tick of the window, not
the decimated copy) to the browser that asked.
"""

from __future__ import annotations

import io
import itertools
import time
from collections import deque
from typing import Any

import numpy as np
import viser
import viser.uplot as uplot

from core.camera.render.looks import follower_rgb
from app.tick import TickState

WINDOWS_S = {"10 s": 10.0, "60 s": 60.0, "5 min": 300.0}
WINDOW_S = WINDOWS_S["60 s"]  # what the charts show at first
KEPT_S = max(WINDOWS_S.values())
REDRAW_S = 0.1
MAX_POINTS = 400
Y_AXIS_PX = 64  # room for a y tick label such as "-12.5" or "-0.015" and the axis label beside it


def axes(y_label: str) -> tuple[uplot.Axis, uplot.Axis]:
    """The x axis (seconds of the session) and a y axis named ``y_label`` (quantity and unit)."""
    return ({"label": "t (s)", "labelSize": 20}, {"label": y_label, "labelSize": 20, "size": Y_AXIS_PX})


def _rgb(i: int) -> str:
    r, g, b = follower_rgb(i)
    return f"rgb({r},{g},{b})"


class Plots:
    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self.folder = server.gui.add_folder("Plots")
        with self.folder:
            self.window = server.gui.add_dropdown("Window", options=tuple(WINDOWS_S), initial_value="60 s",
                                                  hint="how much of the session the charts show")
            self.freeze = server.gui.add_checkbox("Freeze", initial_value=False,
                                                  hint="hold the charts still; the loop and the recording go on")
            self.export = server.gui.add_button("Export CSV", hint="the data the charts show, every tick, as CSV")
        self.charts: dict[str, viser.GuiUplotHandle] = {}
        self._names: list[str] = []
        self._n = -1
        self._truth = True
        self._last_draw = 0.0
        self._rows: deque[np.ndarray] = deque()
        self._t: deque[float] = deque()
        self._shown: tuple[np.ndarray, np.ndarray] | None = None  # (t, rows) the charts show now

        @self.export.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            if event.client is not None:
                event.client.send_file_download("omniformation-plots.csv", self.csv(), save_immediately=True)

    def _build(self, n: int, truth: bool) -> None:
        """Charts for ``n`` followers; ``truth``: the errors are the true poses' (simulation)."""
        for h in self.charts.values():
            h.remove()
        self.charts = {}
        empty = np.zeros(2)

        def chart(key: str, title: str, y_label: str, names: list[str], colours: list[str], dashed: int = 0) -> None:
            """``y_label``: the y axis's quantity and unit; ``dashed``: the last this-many series thin and dashed."""
            first_dashed = len(names) - dashed
            series = (uplot.Series(label="t (s)"),) + tuple(
                uplot.Series(label=nm, stroke=c, width=1.0, dash=(4.0, 3.0)) if k >= first_dashed
                else uplot.Series(label=nm, stroke=c, width=1.5)
                for k, (nm, c) in enumerate(zip(names, colours))
            )
            with self.folder:
                self.charts[key] = self.server.gui.add_uplot(
                    data=(empty,) + tuple(empty for _ in names), series=series, title=title, aspect=2.2,
                    axes=axes(y_label),
                    # x is seconds of the session, not a date (uPlot's default reads it as UNIX time);
                    # one cursor key: hovering one chart shows the same instant on all of them
                    scales={"x": {"time": False}}, cursor={"sync": {"key": "omniformation"}},
                )

        follower_names = [f"F{i + 1}" for i in range(n)]
        colours = [_rgb(i) for i in range(n)]
        which = "true" if truth else "estimated"
        chart("ex", f"{which} x error to the slot (cm)", f"{which} x error (cm)", follower_names, colours)
        chart("ey", f"{which} y error to the slot (cm)", f"{which} y error (cm)", follower_names, colours)
        chart("a", "heading a (deg): Kalman-filtered (solid), measured eq. 34-37 (dashed)", "heading a (deg)",
              follower_names + [f"{nm} raw" for nm in follower_names], colours + colours, dashed=n)
        chart("V", "team V = Σ ½‖ρ̃‖² of the estimates (cm², as the Lyapunov monitor)", "V (cm²)", ["V"],
              ["rgb(40,70,140)"])
        chart("v", "command v (m/s)", "v (m/s)", follower_names, colours)
        chart("w", "command ω (rad/s)", "ω (rad/s)", follower_names, colours)
        self._names = ([f"F{i + 1} ex {which} (cm)" for i in range(n)] + [f"F{i + 1} ey {which} (cm)" for i in range(n)]
                       + [f"F{i + 1} a (deg)" for i in range(n)] + [f"F{i + 1} a raw (deg)" for i in range(n)]
                       + ["V (cm2)"] + [f"F{i + 1} v (m/s)" for i in range(n)] + [f"F{i + 1} w (rad/s)" for i in range(n)])
        self._n, self._truth = n, truth
        self.reset()

    def reset(self) -> None:
        """Forget the history (replay: after a jump on the timeline)."""
        self._rows, self._t = deque(), deque()
        self._shown = None
        self._last_draw = 0.0

    def visible(self) -> tuple[np.ndarray, np.ndarray]:
        """(t (k,), rows (k, columns)) of every tick in the window the charts show (frozen: as frozen)."""
        if self.freeze.value and self._shown is not None:
            return self._shown
        if not self._t:
            return np.zeros(0), np.zeros((0, len(self._names)))
        t = np.fromiter(self._t, dtype=np.float64, count=len(self._t))
        first = int(np.searchsorted(t, t[-1] - WINDOWS_S.get(str(self.window.value), WINDOW_S)))
        return t[first:], np.array(list(itertools.islice(self._rows, first, None)))

    def csv(self) -> bytes:
        """The visible data as CSV: t (s of the session), then every series of every chart."""
        t, rows = self.visible()
        out = io.StringIO()
        out.write(",".join(["t (s)", *self._names]) + "\n")
        for ti, row in zip(t, rows):
            out.write(f"{ti:.4f}," + ",".join(f"{v:.6g}" for v in row) + "\n")
        return out.getvalue().encode()

    def add(self, s: TickState) -> None:
        """Append one tick to the 60 s window, without drawing."""
        n = s.n
        truth = bool(np.all(np.isfinite(s.p_true)))  # simulation: the true pose; real robots: the estimate
        if n != self._n or truth != self._truth:
            self._build(n, truth)
        err = (s.p_d - (s.p_true if truth else s.p_est)) * 100  # cm
        self._t.append(s.t)
        a_raw = s.a_raw if s.a_raw is not None else s.a_est
        # uPlot has no use for NaN: a heading not known yet is drawn at 90 deg (aligned)
        heads = np.degrees(np.nan_to_num(np.concatenate([s.a_est, a_raw]), nan=np.pi / 2))
        self._rows.append(np.concatenate([np.nan_to_num(err[:, 0]), np.nan_to_num(err[:, 1]), heads,
                                          [float(np.nansum(s.v_lyap)) * 1e4], s.commands[:, 0], s.commands[:, 1]]))
        while self._t and self._t[0] < s.t - KEPT_S:
            self._t.popleft()
            self._rows.popleft()

    def update(self, s: TickState, redraw_s: float | None = None) -> None:
        """Append one tick and redraw at most every ``redraw_s`` (REDRAW_S; longer in light mode)."""
        self.add(s)
        n = s.n
        now = time.monotonic()
        if now - self._last_draw < (REDRAW_S if redraw_s is None else redraw_s) or len(self._t) < 2 or (self.freeze.value and self._shown is not None):
            return
        self._last_draw = now
        self._shown = self.visible()
        t_all, rows_all = self._shown
        step = max(1, len(t_all) // MAX_POINTS)
        t, rows = t_all[::step], rows_all[::step]
        cols = {"ex": rows[:, :n], "ey": rows[:, n:2 * n], "a": rows[:, 2 * n:4 * n], "V": rows[:, 4 * n:4 * n + 1],
                "v": rows[:, 4 * n + 1:5 * n + 1], "w": rows[:, 5 * n + 1:6 * n + 1]}
        with self.server.atomic():
            for key, data in cols.items():
                self.charts[key].data = (t,) + tuple(data[:, i].copy() for i in range(data.shape[1]))
