"""Static figures in the paper's style (matplotlib, headless Agg backend): the report's and
simulate's, and the page's tuning and calibration panels' (below both, so neither imports the other).

The simulation figure reproduces the layout of fig. 16-17: the team's world
trajectories with formation triangles at a few instants, the x / y position
errors per follower over time, and the followers' headings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from core.geometry import leader_to_world
from core.sim.run import SimulationLog

from core.camera.render.looks import follower_hex

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from core.sim.sweep import SweepResult

colour = follower_hex  # each follower in its marker's colour, as on the page


def pyplot() -> Any:
    """matplotlib's pyplot on the headless Agg backend, imported when a figure is first drawn: a
    process that never draws one (the live loop's, each CLI start) does not pay its import."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def trajectory_panel(ax: Axes, t: np.ndarray, leader: np.ndarray, followers_world: np.ndarray,
                     p_d: np.ndarray, title: str, instants: int = 6, boxes: np.ndarray | None = None,
                     marks: Sequence[tuple[float, str, str]] = ()) -> None:
    """The team's trajectory in the world (the paper's fig. 16 / 19): the leader, each
    follower and its desired path (dashed), and the formation drawn at a few instants from
    t = 0 on (a vision run starts with its start-up manoeuvres at t < 0). ``leader`` (T, 3)
    world pose, ``followers_world`` (T, n, >=2), ``p_d`` (T, n, 2) leader frame (NaN: none).
    ``boxes``: obstacles (core.obstacles.as_array rows), drawn grey; ``marks``: (t, label,
    matplotlib marker) drawn where the leader was then (STOPs, resets)."""
    ax.plot(leader[:, 0], leader[:, 1], color="tab:blue", lw=1.8, label="leader")
    for i in range(followers_world.shape[1]):
        ks = [k for k in range(0, len(t), 10) if np.all(np.isfinite(p_d[k, i]))]
        if ks:
            dw = np.array([leader_to_world(p_d[k, i], leader[k, :2], leader[k, 2])[0] for k in ks])
            ax.plot(dw[:, 0], dw[:, 1], "--", color=colour(i), lw=0.9)
        ax.plot(followers_world[:, i, 0], followers_world[:, i, 1], color=colour(i), lw=1.3,
                label=f"follower {i + 1}")
    labels: list[tuple[float, float, str, str]] = []  # (x, y, text, colour): drawn last, near ones merged
    start = int(np.argmax(np.nan_to_num(t, nan=-np.inf) >= 0.0))  # rows of NaN break the lines at a reset
    for k in np.linspace(min(start, len(t) - 1), len(t) - 1, instants).astype(int):
        pts = np.vstack([leader[k, :2], followers_world[k, :, :2]])
        if np.all(np.isfinite(pts)):
            ax.fill(pts[:, 0], pts[:, 1], facecolor="none", edgecolor="tab:red", lw=1.0)
            labels.append((float(leader[k, 0]), float(leader[k, 1]), f"{t[k]:.0f} s", "tab:red"))
    for (x, y, heading, half_l, half_w) in (np.zeros((0, 5)) if boxes is None else np.asarray(boxes, float).reshape(-1, 5)):
        c, s_ = math.cos(heading), math.sin(heading)
        corners = np.array([[x + c * u - s_ * v, y + s_ * u + c * v]
                            for u, v in ((half_l, half_w), (-half_l, half_w), (-half_l, -half_w), (half_l, -half_w))])
        ax.fill(corners[:, 0], corners[:, 1], color="0.55", alpha=0.6, lw=0, label=None)
    for when, what, mark in marks:  # STOPs and resets, where the leader was
        k = int(np.argmin(np.abs(np.nan_to_num(t, nan=np.inf) - when)))
        if np.all(np.isfinite(leader[k, :2])):
            ax.plot(leader[k, 0], leader[k, 1], mark, color="black", ms=8, mfc="none")
            labels.append((float(leader[k, 0]), float(leader[k, 1]), f"{what} {when:.0f} s", "black"))
    pts = np.concatenate([leader[:, :2], followers_world[..., :2].reshape(-1, 2)])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts):  # fitted to where the robots were (a desired path far off, or a reset's jump, does not widen it)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = 0.08 * max(float(np.max(hi - lo)), 0.5)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    _place_labels(ax, labels, pad if len(pts) else 0.1)
    ax.set_aspect("equal", adjustable="box" if len(pts) else "datalim")
    ax.set(xlabel="x world (m)", ylabel="y world (m)", title=f"{title}: team trajectory (dashed: desired)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def plot_simulation(log: SimulationLog, path: Path, instants: int = 6) -> None:
    """Write the fig. 16-17 style figure of a run to ``path`` (PNG)."""
    n = log.n
    per_follower_rows = n <= 4
    rows = (n if per_follower_rows else 2) + 1
    plt = pyplot()
    fig = plt.figure(figsize=(13, 2.3 * rows + 1.0), constrained_layout=True)
    grid = fig.add_gridspec(rows, 2, width_ratios=[1.15, 1.0])
    ax_traj = fig.add_subplot(grid[:, 0])

    trajectory_panel(ax_traj, log.t, log.leader, log.followers_world, log.p_d, log.scenario.name, instants)

    err = log.error
    if per_follower_rows:
        for i in range(n):
            ax = fig.add_subplot(grid[i, 1])
            ax.plot(log.t, err[:, i, 0], color="tab:blue", lw=1.0, label="x error")
            ax.plot(log.t, err[:, i, 1], color="tab:red", lw=1.0, label="y error")
            ax.set_ylabel("m")
            ax.set_title(f"follower {i + 1}: position error", fontsize=9)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
    else:
        for axis, name in ((0, "x"), (1, "y")):
            ax = fig.add_subplot(grid[axis, 1])
            for i in range(n):
                ax.plot(log.t, err[:, i, axis], color=colour(i), lw=0.9, label=f"f{i + 1}")
            ax.set_ylabel("m")
            ax.set_title(f"{name} position error", fontsize=9)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6, ncol=3, loc="upper right")
    ax_head = fig.add_subplot(grid[rows - 1, 1])
    for i in range(n):
        ax_head.plot(log.t, np.degrees(log.a[:, i]), color=colour(i), lw=1.0, label=f"follower {i + 1}")
    ax_head.axhline(90.0, color="k", lw=0.6, ls=":")
    ax_head.set_xlabel("t (s)")
    ax_head.set_ylabel("heading a (deg)")
    ax_head.set_title("headings in the leader frame (90° = aligned)", fontsize=9)
    ax_head.grid(alpha=0.3)
    ax_head.legend(fontsize=7, loc="upper right")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _place_labels(ax: Axes, labels: list[tuple[float, float, str, str]], near: float) -> None:
    """The trajectory's labels without overlaps: labels closer than ``near`` (m) to one already
    placed join it, one line each, in one box (a STOP and its release where the leader stood)."""
    groups: list[tuple[float, float, list[tuple[str, str]]]] = []
    for x, y, text, ink in labels:
        for gx, gy, members in groups:
            if math.hypot(x - gx, y - gy) < near:
                members.append((text, ink))
                break
        else:
            groups.append((x, y, [(text, ink)]))
    for x, y, members in groups:
        for row, (text, ink) in enumerate(members):
            ax.annotate(text, (x, y), fontsize=7, color=ink, xytext=(5, 4 - 9 * row), textcoords="offset points",
                        bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})


def _gain_label(name: str) -> str:
    from core.types import GAIN_BOUNDS

    unit = GAIN_BOUNDS[name].unit if name in GAIN_BOUNDS else ""
    return f"{name} ({unit})" if unit else name


def excluded_points(result: "SweepResult") -> tuple[list[int], list[int], float]:
    """(points that settled but the best rule leaves out, points that did not settle, the steady
    error limit in m): core.sim.sweep.BEST_RULE's first cut, so the page can grey them and say why."""
    from core.sim.sweep import STEADY_SLACK

    done = [(k, s.worst) for k, s in enumerate(result.scores) if s is not None]
    settled = [w["steady_rms_m"] for _, w in done if math.isfinite(w["settling_s"]) and math.isfinite(w["steady_rms_m"])]
    limit = min(settled) * STEADY_SLACK[0] + STEADY_SLACK[1] if settled else math.inf
    slack = [k for k, w in done if math.isfinite(w["settling_s"]) and not w["steady_rms_m"] <= limit]
    unsettled = [k for k, w in done if not math.isfinite(w["settling_s"])]
    return slack, unsettled, limit


CELL_PT = 10.0  # the heat map's cell numbers: 12.5 px at the page's 90 dpi


def sweep_figure(result: "SweepResult", width_in: float = 7.5, stacked: bool = False,
                 metric: str = "settling", cell_pt: float = CELL_PT) -> "Figure":
    """A sweep's result: for two gains a heat map of one ``metric`` (METRICS: its colour and the
    number in each cell are the same figure, with its unit; the colour scale spans the 5th to
    95th percentile so one slow row does not flatten the rest; not settled: grey, "no"), for one
    gain the settling time and overshoot against it; beside it the Pareto plot (settling time vs.
    overshoot, the front joined, the best point ringed). Points the best rule leaves out (settled,
    but their steady error above its limit) are hatched grey, their numbers kept; ``cell_pt``: the
    cell numbers' size (points), omitted where a cell is too narrow for them (the enlarged figure has them)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from core.sim.sweep import METRICS

    key, scale, label, decimals = METRICS[metric]
    if stacked:  # one above the other: the page's narrow panel
        fig = Figure(figsize=(width_in, width_in * 1.3), constrained_layout=True)
        ax, axp = fig.subplots(2, 1, gridspec_kw={"height_ratios": [1.15, 1]})
    else:
        fig = Figure(figsize=(width_in, width_in * 0.42), constrained_layout=True)
        ax, axp = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.15, 1]})
    settle = result.grid("settling_s")
    over = result.grid("overshoot_m") * 100
    r0 = result.ranges[0]
    best = result.best()
    if len(result.ranges) == 2:
        r1 = result.ranges[1]
        shown = result.grid(key) * scale
        if key != "settling_s":
            shown = np.where(np.isfinite(settle), shown, np.nan)  # a point that did not settle shows "no"
        finite = shown[np.isfinite(shown)]
        lo, hi = (np.percentile(finite, [5, 95]) if finite.size else (0.0, 1.0))
        hi = hi if hi > lo else lo + 1e-9
        ax.set_facecolor("0.85")
        mesh = ax.imshow(np.ma.masked_invalid(shown).T, origin="lower", aspect="auto", cmap="viridis_r",
                         vmin=lo, vmax=hi, extent=(-0.5, len(r0.values) - 0.5, -0.5, len(r1.values) - 0.5))
        fig.colorbar(mesh, ax=ax, label=label, extend="both")
        slack, _, _ = excluded_points(result)
        cell_in = 0.62 * width_in / len(r0.values)  # about the heat map's share of the width, per column
        numbers = cell_in * 72 >= cell_pt * (decimals + 3) * 0.62  # the widest number fits its cell
        for i in range(len(r0.values)):
            for j in range(len(r1.values)):
                v = shown[i, j]
                if np.ravel_multi_index((i, j), settle.shape) in slack:
                    ax.add_patch(Rectangle((i - 0.5, j - 0.5), 1, 1, facecolor=(0.6, 0.6, 0.6, 0.75), hatch="///",
                                           edgecolor="0.35", lw=0))
                if not numbers:
                    continue
                if np.isfinite(v):
                    r, g, b, _ = mesh.cmap(mesh.norm(v))
                    ink = "k" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "w"  # readable on every colour
                    if np.ravel_multi_index((i, j), settle.shape) in slack:
                        ink = "k"
                    ax.text(i, j, f"{v:.{decimals}f}", ha="center", va="center", fontsize=cell_pt, color=ink)
                else:
                    ax.text(i, j, "no", ha="center", va="center", fontsize=cell_pt, color="k")
        ax.set_xticks(range(len(r0.values)), [f"{v:g}" for v in r0.values], fontsize=9)
        ax.set_yticks(range(len(r1.values)), [f"{v:g}" for v in r1.values], fontsize=9)
        ax.set(xlabel=_gain_label(r0.name), ylabel=_gain_label(r1.name), title=f"{result.test.label()}: {label}")
        if best is not None:
            bi, bj = np.unravel_index(best, settle.shape)
            ax.add_patch(Rectangle((bi - 0.5, bj - 0.5), 1, 1, fill=False, edgecolor="red", lw=2))
    else:
        x = r0.values
        ax.plot(x, settle[:, 0], "o-", color="tab:blue", label="settling time (s)")
        ax.set(xlabel=_gain_label(r0.name), ylabel="settling time (s)", title=result.test.label())
        ax2 = ax.twinx()
        ax2.plot(x, over[:, 0], "s--", color="tab:red", label="overshoot (cm)")
        ax2.set_ylabel("overshoot (cm)", color="tab:red")
        ax.grid(alpha=0.3)
        if best is not None:
            ax.axvline(x[best], color="red", lw=0.8, ls=":")
    pts = [(k, s.worst) for k, s in enumerate(result.scores) if s is not None and np.isfinite(s.worst["settling_s"])]
    if pts:
        axp.scatter([w["settling_s"] for _, w in pts], [w["overshoot_m"] * 100 for _, w in pts], s=14, color="0.5")
        front = result.pareto()
        axp.plot([result.scores[k].worst["settling_s"] for k in front],  # type: ignore[union-attr]  # settled
                 [result.scores[k].worst["overshoot_m"] * 100 for k in front], "o-", color="tab:orange", ms=4,  # type: ignore[union-attr]
                 label="Pareto front")
        if best is not None and result.scores[best] is not None:
            w = result.scores[best].worst  # type: ignore[union-attr]  # checked
            axp.scatter([w["settling_s"]], [w["overshoot_m"] * 100], s=80, facecolors="none", edgecolors="red",
                        label="best")
        axp.legend(fontsize=7)
    else:
        axp.text(0.5, 0.5, "no point settled", ha="center", va="center", transform=axp.transAxes)
    axp.set(xlabel="settling time (s)", ylabel="overshoot (cm)", title=f"{result.feedback} feedback")
    axp.grid(alpha=0.3)
    return fig


def figure_rgb(fig: "Figure", dpi: int = 90) -> np.ndarray:
    """A matplotlib Figure as an (h, w, 3) uint8 image (for the page)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    canvas.draw()  # type: ignore[no-untyped-call]  # matplotlib's Agg canvas has no annotations here
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()  # type: ignore[no-untyped-call]


def limits_strip(t: np.ndarray, limits: np.ndarray, ax: Axes) -> None:
    """Which saturation or limit each follower is in over time (core.control.tuning): one row
    per follower and limit, filled where it is active."""
    from core.control.tuning import LIMIT_NAMES

    n = limits.shape[1]
    k = len(LIMIT_NAMES)
    img = np.zeros((n * k, len(t)))
    for i in range(n):
        for b in range(k):
            img[i * k + b] = (limits[:, i].astype(np.int64) >> b) & 1
    if len(t) >= 2:
        ax.imshow(img, aspect="auto", interpolation="nearest", cmap="Greys", vmin=0, vmax=1,
                  extent=(float(t[0]), float(t[-1]), n * k - 0.5, -0.5))
    ax.set_yticks(range(n * k), [f"F{i + 1} {name}" for i in range(n) for name in LIMIT_NAMES], fontsize=6)
    for i in range(1, n):
        ax.axhline(i * k - 0.5, color=colour(i), lw=0.8)
