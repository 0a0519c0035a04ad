"""`omniformation report FILE --out DIR`: a recording as the paper's figures and a summary.

Figures (PNG, paper style): trajectory.png (fig. 16/21/25/28: the team's path with the
formation triangle at a few instants), errors.png (fig. 17/19/23/26: x / y position error
per follower), headings.png (fig. 20/24/27: measured vs Kalman-filtered headings),
lyapunov_commands.png (V(t) and the commands), lyapunov.png (V per follower, where it rose or
fell, and which saturation or limit was active), safety.png. summary.md and summary.json: per follower
the settling time, steady-state error RMS and max, time not tracked (the session's, and each
segment's between resets); the STOPs and releases counted apart.

The numbers are app.recording.statistics' (re-exported here): one pass over the recording, a
block of ticks at a time, tallies them over every tick and keeps every k-th tick (at most
MAX_PLOTTED points per line) for the figures drawn here, so memory does not grow with the
recording's length.
"""

from __future__ import annotations

import json
from typing import Any
from pathlib import Path
from collections.abc import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.axes import Axes
import numpy as np

from app.figures import colour, trajectory_panel
from app.recording.reader import Recording
from app.recording.statistics import (BOUNDARY_M, COLLISION_M, DISTANCE_BLOCK, MAX_PLOTTED, NEAR_MISS_M,
                                      OBSTACLE_CLEARANCE_M, SETTLED_M, Scan, Series, Tally, obstacle_gap,
                                      is_release, recorded_obstacles, safety_summary, scan, step_tests, stop_intervals,
                                      summarise)

__all__ = ["DISTANCE_BLOCK", "FORMATS", "MAX_PLOTTED", "SETTLED_M", "Scan", "Series", "Tally", "safety_summary", "scan",
           "step_tests", "summarise", "write_report"]


def _summary_md(sm: dict[str, Any]) -> str:
    lines = [f"# Session report: {sm['recording']}", "",
             f"- duration {sm['duration_s']} s; errors from {sm['errors_from']}; settled = {sm['settled_means']}",
             f"- file complete: {'yes' if sm['complete'] else 'no (cut off; read up to its last complete chunk)'}",
             f"- {sm['events']} events", f"- STOPs: {sm['stops']}", f"- releases: {sm['releases']}"]
    lines += [f"  - {ev['t']} s: {ev['detail']}" for ev in sm["stop_events"]]
    sf = sm["safety"]
    lines.append(f"- safety ({sf['distances_from']}): closest two robots {sf['min_distance_cm']} cm; {sf['collisions']}"
                 f" collisions (< {COLLISION_M * 100:.0f} cm), {sf['near_misses']} near misses (< {NEAR_MISS_M * 100:.0f}"
                 f" cm, {sf['time_under_min_distance_s']} s); {sf['actuator_limit_hits']} actuator-limit hits;"
                 f" {sf['boundary_exits']} exits from the camera's ring (> {BOUNDARY_M:g} m); safety"
                 f" filter acting {sf['filter_acting_s'] if sf['filter_acting_s'] is not None else 'not recorded'} s")
    if "obstacle_clearance_cm" in sf:
        lines.append(f"- obstacles: closest follower body {sf['obstacle_clearance_cm']} cm from a surface;"
                     f" {sf['obstacle_hits']} hits, {sf['obstacle_near_misses']} near misses"
                     f" (< {OBSTACLE_CLEARANCE_M * 100:.0f} cm)")
    if sm["loss"]:
        lines.append(f"- not in the file: {sm['lost_ticks']} ticks ({sm['lost_s']} s); {sm['loss']}")
    lines += ["", "| follower | settling time (s) | steady error RMS (cm) | steady error max (cm) | not tracked (s) |",
              "|---|---|---|---|---|"]
    for f in sm["followers"]:
        lines.append(f"| {f['follower']} | {f['settling_time_s'] if f['settling_time_s'] is not None else 'not settled'}"
                     f" | {f['steady_error_rms_cm']} | {f['steady_error_max_cm']} | {f['time_not_tracked_s']} |")
    if len(sm["segments"]) > 1:  # a reset started the loop's clock again: each stretch on its own
        lines += ["", "## Segments (between resets)", "",
                  "Each segment's times from its own start (the reset); settled as above.", "",
                  "| segment | from (s) | to (s) | follower | settling time (s) | steady error RMS (cm) |"
                  " steady error max (cm) | not tracked (s) |",
                  "|---|---|---|---|---|---|---|---|"]
        for k, g in enumerate(sm["segments"], 1):
            for f in g["followers"]:
                lines.append(f"| {k} | {g['from_s']} | {g['to_s']} | {f['follower']} |"
                             f" {f['settling_time_s'] if f['settling_time_s'] is not None else 'not settled'} |"
                             f" {f['steady_error_rms_cm']} | {f['steady_error_max_cm']} | {f['time_not_tracked_s']} |")
    if sm["step_tests"]:
        lines += ["", "## Step tests", "",
                  f"Settling to {SETTLED_M * 100:.0f} cm, overshoot past the target, steady error RMS over the last 2 s and effort"
                  " (∫ mean squared wheel speed dt): as the page measured them / as computed here from the"
                  " recorded ticks.", "",
                  "| # | test | status | settling (s) | overshoot (cm) | steady RMS (cm) | effort (m²/s) |",
                  "|---|---|---|---|---|---|---|"]
        for tr in sm["step_tests"]:
            page, here = tr.get("page") or {}, tr.get("report") or {}

            def pair(key: str, scale: float = 1.0, digits: int = 2, page: dict[str, Any] = page,
                     here: dict[str, Any] = here) -> str:
                def one(d: dict[str, Any]) -> str:
                    v = d.get(key)
                    return "not settled" if v is None and d else "" if v is None else f"{v * scale:.{digits}f}"
                return f"{one(page)} / {one(here)}"

            lines.append(f"| {tr['number']} | {tr['label']} | {tr['status']} | {pair('settling_s')} |"
                         f" {pair('overshoot_m', 100)} | {pair('steady_rms_m', 100, 3)} | {pair('effort', 1, 4)} |")
    return "\n".join(lines) + "\n"


def _trajectory(s: Series, title: str, path: Path, boxes: np.ndarray, marks: list[tuple[float, str, str]],
                instants: int = 6) -> None:
    fig, ax = plt.subplots(figsize=(7.5, 7), constrained_layout=True)
    trajectory_panel(ax, s.t, s.leader, s.followers_world, s.p_d, title, instants, boxes, marks)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _per_follower(s: Series, path: Path, ylabel: str, title: str,
                  draw: Callable[[Axes, int], None]) -> None:
    """One panel per follower, stacked over a shared time axis (the paper's fig. 17/20 layout)."""
    n = s.p.shape[1]
    fig, axes = plt.subplots(n, 1, figsize=(9, 2.2 * n + 0.6), sharex=True, constrained_layout=True, squeeze=False)
    for i in range(n):
        ax = axes[i, 0]
        draw(ax, i)
        ax.set(ylabel=ylabel, title=f"follower {i + 1}: {title}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("t (s)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def error_limit_cm(err_cm: np.ndarray) -> float:
    """The errors figure's half-range (cm): the 99th percentile of |error| with a margin, at least
    1 cm, so a start-up transient or one outlier does not flatten the rest (what lies beyond is
    drawn at the edge and said in the title)."""
    finite = np.abs(err_cm[np.isfinite(err_cm)])
    if not finite.size:
        return 1.0
    return float(max(1.0, 1.15 * np.percentile(finite, 99)))


def _errors(s: Series, path: Path, stops: list[tuple[float, float]], resets: list[float]) -> None:
    """x / y position error per follower in cm, on a scale that fits the data; STOPs shaded
    red, resets as grey lines."""
    err = (s.p_d - s.p) * 100
    lim = error_limit_cm(err)
    beyond = int(np.sum(np.abs(np.nan_to_num(err)) > lim))

    def draw(ax: Axes, i: int) -> None:
        ax.plot(s.t, np.clip(err[:, i, 0], -lim, lim), color="tab:blue", lw=1.0, label="x error")
        ax.plot(s.t, np.clip(err[:, i, 1], -lim, lim), color="tab:red", lw=1.0, label="y error")
        ax.set_ylim(-lim * 1.05, lim * 1.05)
        for k, (a, b) in enumerate(stops):
            ax.axvspan(a, b, color="tab:red", alpha=0.12, lw=0, label="STOP" if k == 0 else None)
        for k, r in enumerate(resets):
            ax.axvline(r, color="0.4", lw=1.0, ls="--", label="reset" if k == 0 else None)

    note = f" ({beyond} points beyond ±{lim:.1f} cm drawn at the edge)" if beyond else ""
    _per_follower(s, path, "cm", f"position error{note}", draw)


def _headings(s: Series, path: Path) -> None:
    def draw(ax: Axes, i: int) -> None:
        ax.plot(s.t, np.degrees(s.a_raw[:, i]), color="tab:blue", lw=0.8, label="measured (eq. 34-37)")
        ax.plot(s.t, np.degrees(s.a_est[:, i]), color="tab:red", lw=1.2, label="Kalman-filtered")
        ax.axhline(90.0, color="k", lw=0.5, ls=":")

    _per_follower(s, path, "deg", "heading in the leader frame", draw)


def _lyapunov_commands(s: Series, path: Path) -> None:
    n = s.p.shape[1]
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True, constrained_layout=True)
    axes[0].plot(s.t, s.v_lyap, color="tab:blue")
    axes[0].set(ylabel="m²", title="team V = Σ ½‖ρ̃‖² (eq. 21)")
    axes[0].set_yscale("symlog", linthresh=1e-5)
    for i in range(n):
        axes[1].plot(s.t, s.commands[:, i, 0], color=colour(i), lw=0.9, label=f"follower {i + 1}")
        axes[2].plot(s.t, s.commands[:, i, 1], color=colour(i), lw=0.9)
    axes[1].set(ylabel="m/s", title="command v")
    axes[2].set(ylabel="rad/s", title="command ω", xlabel="t (s)")
    axes[1].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _lyapunov_monitor(s: Series, path: Path) -> None:
    """Per follower: eq. 21's V (where it rose, shaded red; fell, green), and the strip of the
    saturations and limits that were active (core.control.tuning)."""
    from app.figures import limits_strip
    from core.control.tuning import lyapunov_trend

    v = s.v_each if s.v_each is not None else s.v_lyap[:, None]
    n = v.shape[1]
    rate = s.v_rate if s.v_rate is not None and np.isfinite(s.v_rate).any() else \
        np.gradient(v, s.t, axis=0) if len(s.t) > 1 else np.zeros_like(v)
    fig, axes = plt.subplots(n + 1, 1, figsize=(9, 1.9 * n + 2.2), sharex=True, constrained_layout=True,
                             squeeze=False, gridspec_kw={"height_ratios": [2] * n + [max(1.5, 0.35 * n * 5 / 2)]})
    for i in range(n):
        ax = axes[i, 0]
        ax.plot(s.t, v[:, i], color=colour(i), lw=1.0)
        trend = lyapunov_trend(rate[:, i], v[:, i])
        top = float(np.nanmax(v[:, i])) if np.isfinite(v[:, i]).any() else 1.0
        ax.fill_between(s.t, 0, top, where=trend > 0, color="tab:red", alpha=0.15, lw=0, step="mid", label="rising")
        ax.fill_between(s.t, 0, top, where=trend < 0, color="tab:green", alpha=0.10, lw=0, step="mid", label="falling")
        ax.set_yscale("symlog", linthresh=1e-5)
        ax.set(ylabel="V (m²)", title=f"follower {i + 1}: V = ½‖ρ̃‖² (eq. 21)")
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3)
    ax = axes[n, 0]
    if s.limits is not None and np.isfinite(s.limits).any():
        limits_strip(s.t, np.nan_to_num(s.limits).astype(np.int64), ax)
        ax.set_title("active saturations and limits (eq. 4, eq. 12, v / ω limits, safety filter)")
    else:
        ax.text(0.5, 0.5, "saturations not recorded (a recording older than the monitor)", ha="center",
                va="center", transform=ax.transAxes)
    ax.set_xlabel("t (s)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _safety(s: Series, gap: np.ndarray | None, path: Path) -> None:
    """The minimum distance over time (robots, and obstacles where the scenario has them) and
    where the safety filter acted."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True, constrained_layout=True,
                             gridspec_kw={"height_ratios": [3, 1]})
    axes[0].plot(s.t, s.min_distance() * 100, color="tab:blue", lw=0.9, label="closest two robots (centres)")
    if gap is not None:
        axes[0].plot(s.t, gap * 100, color="tab:brown", lw=0.9, label="closest follower body to an obstacle")
    axes[0].axhline(NEAR_MISS_M * 100, color="tab:red", ls="--", lw=0.8, label=f"minimum distance {NEAR_MISS_M * 100:.0f} cm")
    axes[0].axhline(OBSTACLE_CLEARANCE_M * 100, color="tab:orange", ls=":", lw=0.8,
                    label=f"obstacle clearance {OBSTACLE_CLEARANCE_M * 100:.0f} cm")
    axes[0].set(ylabel="cm", title="minimum distance over time")
    axes[0].set_ylim(bottom=0)
    axes[0].legend(fontsize=7, loc="upper right")
    if s.filter_acting is not None:
        axes[1].fill_between(s.t, s.filter_acting.astype(float), step="mid", color="tab:red", alpha=0.5, lw=0)
    axes[1].set(ylabel="acting", xlabel="t (s)", title="safety filter changed a command", yticks=[0, 1])
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


FORMATS = ("png", "svg", "pdf")


def write_report(rec: Recording, out: Path, progress: Callable[[int, int, str], None] | None = None,
                 fmt: str = "png") -> list[Path]:
    """The figures (as ``fmt``: png, svg or pdf) and summary.json / summary.md in ``out``."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: one of {', '.join(FORMATS)}")
    sc = scan(rec)  # one pass: every tick into the summary, every k-th into the figures
    shown = sc.shown
    title = rec.metadata.get("scenario", rec.path.stem)
    boxes = recorded_obstacles(rec)
    start = float(rec.metadata.get("scenario_start_s", "0") or 0)
    marks = [(float(e["t"]) - start, "release" if is_release(e) else "STOP", "s")
             for e in rec.events if e.get("kind") == "stop"] + \
            [(g.start_s, "reset", "D") for g in sc.segments[1:]]
    steps: list[tuple[str, Callable[[Path], None]]] = [
        (f"trajectory.{fmt}", lambda p: _trajectory(shown, title, p, boxes, marks)),
        (f"errors.{fmt}", lambda p: _errors(shown, p, stop_intervals(rec, start), [g.start_s for g in sc.segments[1:]])),
        (f"headings.{fmt}", lambda p: _headings(shown, p)),
        (f"lyapunov_commands.{fmt}", lambda p: _lyapunov_commands(shown, p)),
        (f"safety.{fmt}", lambda p: _safety(shown, obstacle_gap(boxes, shown), p)),
        (f"lyapunov.{fmt}", lambda p: _lyapunov_monitor(shown, p)),
    ]
    written = []
    total = len(steps) + 1
    for k, (name, fn) in enumerate(steps, 1):
        fn(out / name)
        written.append(out / name)
        if progress:
            progress(k, total, name)
    sm = summarise(rec, sc)
    (out / "summary.json").write_text(json.dumps(sm, indent=2) + "\n", encoding="utf-8")
    (out / "summary.md").write_text(_summary_md(sm), encoding="utf-8")
    written += [out / "summary.json", out / "summary.md"]
    if progress:
        progress(total, total, "summary.md, summary.json")
    return written
