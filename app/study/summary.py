"""A study's ``summary.md`` and ``plots/``, from its files alone (``report DIR`` draws them again).

* summary.md: the study (file, runs, failures, where the formation holds), then per point the
  convergence rate and, for each metric, the median and the 5-95 % range over its replicates;
* plots/: per pair of grid axes, a heat map of the convergence rate and of the median settling
  time (over every other axis and the replicates); one grid axis: the same as lines; a sampled
  axis: the convergence rate in bins along it; with ``start.*`` axes, the region of attraction
  (the convergence rate by where the followers start relative to their slots); with
  ``[optimize]``, the objective by trial and the best so far.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from app.study.store import PLOTS, SUMMARY, StudyFolder, _write_atomic
from core.study.point import METRICS
from core.study.spec import SCENARIO_AXIS, START_BEARING, START_DEFAULTS, START_OFFSET, StudySpec

FLOAT_METRICS = tuple(k for k, (kind, _) in METRICS.items() if kind != "bool")


def _groups(table: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    keys = np.asarray(table.column("point").to_pylist(), dtype=object)
    uniq, inverse = np.unique(keys.astype(str), return_inverse=True)
    return uniq, inverse


def _col(table: pa.Table, name: str) -> np.ndarray:
    return np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=np.float64)


def per_point(table: pa.Table, axes: tuple[str, ...]) -> list[dict[str, Any]]:
    """One dict per point: its axis values, runs, convergence rate, and per metric (median, p5, p95)."""
    if table.num_rows == 0:
        return []
    uniq, inverse = _groups(table)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
    conv = np.asarray(table.column("converged").to_numpy(zero_copy_only=False), dtype=bool)
    cols = {m: _col(table, m) for m in FLOAT_METRICS}
    axis_cols = {a: table.column(a).to_pylist() for a in axes}
    out = []
    for g in range(len(uniq)):
        rows = order[bounds[g]:bounds[g + 1]]
        first = int(rows[0])
        entry: dict[str, Any] = {"point": str(uniq[g]), **{a: axis_cols[a][first] for a in axes},
                                 "runs": int(rows.size), "converged": float(conv[rows].mean())}
        for m in FLOAT_METRICS:
            v = cols[m][rows]
            v = v[np.isfinite(v)]
            entry[m] = (float(np.median(v)), float(np.percentile(v, 5)), float(np.percentile(v, 95))) if v.size \
                else (math.nan, math.nan, math.nan)
            entry[f"{m}_finite"] = int(v.size)
        out.append(entry)

    def by_axes(p: dict[str, Any]) -> tuple[Any, ...]:
        return tuple((0, v, "") if isinstance(v, (int, float)) else (1, 0.0, str(v)) for v in (p[a] for a in axes))

    return sorted(out, key=by_axes)


def _fmt(x: Any) -> str:
    if isinstance(x, str):
        return x
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    return "–" if not math.isfinite(x) else f"{x:.4g}"


def write_summary(spec: StudySpec, folder: StudyFolder, seconds: float | None = None, workers: int | None = None,
                  best: dict[str, Any] | None = None) -> Path:
    table = folder.table()
    failures = folder.failures()
    points = per_point(table, spec.axis_names) if table.num_rows else []
    runs = table.num_rows
    lines = [f"# Study: {folder.manifest().get('study_file', '?')}", ""]
    scen = ", ".join(s.name for s in spec.scenarios)
    lines.append(f"- {scen}, {spec.feedback} feedback"
                 + (f", {spec.test.label()} from the team settled on its slots" if spec.test else "")
                 + f"; {spec.replicates} replicate{'s' if spec.replicates != 1 else ''} per point, seed {spec.seed}")
    lines.append(f"- {runs} of {spec.runs} runs in results/ ({len(points)} points), {len(failures)} failed"
                 " (failures.parquet)" + (f"; this session {seconds:.1f} s on {workers} worker"
                                          f"{'s' if workers != 1 else ''}" if seconds is not None else ""))
    if runs:
        conv = np.asarray(table.column("converged").to_numpy(zero_copy_only=False), dtype=bool)
        held = [p for p in points if p["converged"] >= 0.95]
        lines.append(f"- the formation held (error RMS ≤ 2 cm over the last 2 s) in {conv.mean() * 100:.1f} % of the"
                     f" runs; {len(held)} of {len(points)} points held in at least 95 % of their replicates")
        failing = [p for p in points if p["converged"] < 0.95]
        if failing and len(failing) <= 30:
            lines.append("- it held in fewer than 95 % of the replicates at: " + "; ".join(
                ", ".join(f"{a} = {_fmt(p[a])}" for a in spec.axis_names) + f" ({p['converged'] * 100:.0f} %)"
                for p in failing))
        elif failing:
            lines.append(f"- it held in fewer than 95 % of the replicates at {len(failing)} points (the table below)")
    if best is not None:
        lines.append(f"- best point ({best['trial']} of {best['trials']} trials): "
                     + ", ".join(f"{k} = {_fmt(v)}" for k, v in best["values"].items())
                     + f"; objective {spec.optimize.objective if spec.optimize else ''} = {_fmt(best['value'])}")
    lines += ["", "Per point: the convergence rate over its replicates, then each metric's median [5 %, 95 %]"
              " over the replicates that have it (settling_s: those that settled).", ""]
    heads = [*spec.axis_names, "runs", "converged", *FLOAT_METRICS]
    lines.append("| " + " | ".join(heads) + " |")
    lines.append("|" + "---|" * len(heads))
    for p in points:
        cells = [_fmt(p[a]) for a in spec.axis_names] + [str(p["runs"]), f"{p['converged'] * 100:.0f} %"]
        for m in FLOAT_METRICS:
            med, lo, hi = p[m]
            cells.append("–" if not math.isfinite(med) else f"{med:.4g} [{lo:.4g}, {hi:.4g}]")
        lines.append("| " + " | ".join(cells) + " |")
    path = folder.out / SUMMARY
    _write_atomic(path, ("\n".join(lines) + "\n").encode())
    return path


# ------------------------------------------------------------------------------ plots

def _axis_values(table: pa.Table, name: str) -> np.ndarray:
    if name == SCENARIO_AXIS:
        return np.asarray(table.column(name).to_pylist(), dtype=object)
    return _col(table, name)


def _label(name: str) -> str:
    return {"measurement.position_noise_m": "position noise (m)", "latency.camera_ms": "camera latency (ms)",
            "measurement.vision_position_noise_m": "noise on the vision estimates (m)",
            START_OFFSET: "start offset (m)", START_BEARING: "start bearing (deg)"}.get(name, name)


def draw_plots(spec: StudySpec, folder: StudyFolder, fmt: str = "png") -> list[Path]:
    """Every plot the study's axes call for, into DIR/plots; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = folder.table()
    out = folder.out / PLOTS
    out.mkdir(exist_ok=True)
    written: list[Path] = []
    if table.num_rows == 0:
        return written
    conv = np.asarray(table.column("converged").to_numpy(zero_copy_only=False), dtype=np.float64)
    settle = _col(table, "settling_s")
    grid = [a.name for a in spec.grid_axes]
    if spec.optimize is None and len(grid) >= 2:
        for a, b in itertools.combinations(grid, 2):
            written.append(_heatmap(plt, table, a, b, conv, settle, out, fmt))
    elif spec.optimize is None and len(grid) == 1:
        written.append(_lines(plt, table, grid[0], conv, settle, out, fmt))
    for axis in spec.sample_axes:
        written.append(_binned(plt, table, axis.name, conv, out, fmt))
    names = spec.axis_names
    if START_OFFSET in names or START_BEARING in names:
        written.append(_roa(plt, table, names, conv, out, fmt))
    if spec.optimize is not None:
        path = _history(plt, folder, spec, out, fmt)
        if path is not None:
            written.append(path)
    return written


def _cells(x: np.ndarray, y: np.ndarray, v: np.ndarray, how: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs = np.unique(x)
    ys = np.unique(y)
    grid = np.full((len(ys), len(xs)), math.nan)
    xi = np.searchsorted(xs, x) if x.dtype != object else np.array([list(xs).index(e) for e in x])
    yi = np.searchsorted(ys, y) if y.dtype != object else np.array([list(ys).index(e) for e in y])
    for j in range(len(ys)):
        for i in range(len(xs)):
            sel = (xi == i) & (yi == j)
            vals = v[sel]
            vals = vals[np.isfinite(vals)]
            if vals.size:
                grid[j, i] = float(np.mean(vals) if how == "mean" else np.median(vals))
    return xs, ys, grid


def _heatmap(plt: Any, table: pa.Table, a: str, b: str, conv: np.ndarray, settle: np.ndarray, out: Path,
             fmt: str) -> Path:
    x, y = _axis_values(table, a), _axis_values(table, b)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), constrained_layout=True)
    for ax, (vals, how, title, cmap) in zip(axes, ((conv * 100, "mean", "convergence rate (%)", "RdYlGn"),
                                                   (settle, "median", "median settling time (s)", "viridis_r"))):
        xs, ys, grid = _cells(x, y, vals, how)
        im = ax.imshow(grid, origin="lower", aspect="auto", cmap=cmap,
                       vmin=0 if how == "mean" else None, vmax=100 if how == "mean" else None)
        ax.set_xticks(range(len(xs)), [_fmt(v) for v in xs], rotation=45 if len(xs) > 6 else 0)
        ax.set_yticks(range(len(ys)), [_fmt(v) for v in ys])
        ax.set_xlabel(_label(a))
        ax.set_ylabel(_label(b))
        ax.set_title(title + (" (grey: none settled)" if how == "median" else ""))
        for j in range(grid.shape[0]):
            for i in range(grid.shape[1]):
                if math.isfinite(grid[j, i]) and grid.size <= 400:
                    ax.text(i, j, f"{grid[j, i]:.0f}" if how == "mean" else f"{grid[j, i]:.1f}", ha="center",
                            va="center", fontsize=7)
        fig.colorbar(im, ax=ax)
    fig.suptitle(f"{a} × {b}: over every other axis and the replicates")
    path = out / f"heatmap-{_safe(a)}-{_safe(b)}.{fmt}"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _lines(plt: Any, table: pa.Table, a: str, conv: np.ndarray, settle: np.ndarray, out: Path, fmt: str) -> Path:
    x = _axis_values(table, a)
    xs = np.unique(x)
    rate = [float(np.mean(conv[x == v])) * 100 for v in xs]
    med = []
    for v in xs:
        s = settle[(x == v) & np.isfinite(settle)]
        med.append(float(np.median(s)) if s.size else math.nan)
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    pos = range(len(xs)) if x.dtype == object else xs
    ax.plot(pos, rate, "o-", color="tab:green", label="convergence rate (%)")
    ax.set_ylim(-3, 103)
    ax.set_xlabel(_label(a))
    ax.set_ylabel("convergence rate (%)")
    ax2 = ax.twinx()
    ax2.plot(pos, med, "s--", color="tab:blue", label="median settling time (s)")
    ax2.set_ylabel("median settling time (s)")
    fig.legend(loc="lower right")
    path = out / f"line-{_safe(a)}.{fmt}"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _binned(plt: Any, table: pa.Table, a: str, conv: np.ndarray, out: Path, fmt: str) -> Path:
    x = _col(table, a)
    edges = np.linspace(np.nanmin(x), np.nanmax(x), 11)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, 9)
    rate = [float(np.mean(conv[idx == k])) * 100 if np.any(idx == k) else math.nan for k in range(10)]
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    ax.bar(0.5 * (edges[1:] + edges[:-1]), rate, width=np.diff(edges) * 0.9, color="tab:green")
    ax.set_ylim(0, 100)
    ax.set_xlabel(_label(a) + " (sampled)")
    ax.set_ylabel("convergence rate (%)")
    path = out / f"sample-{_safe(a)}.{fmt}"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _roa(plt: Any, table: pa.Table, names: tuple[str, ...], conv: np.ndarray, out: Path, fmt: str) -> Path:
    n = table.num_rows
    off = _col(table, START_OFFSET) if START_OFFSET in names else np.full(n, START_DEFAULTS[START_OFFSET])
    bear = _col(table, START_BEARING) if START_BEARING in names else np.full(n, START_DEFAULTS[START_BEARING])
    keys = np.round(off, 9) * 1e4 + np.round(bear, 6)
    uniq, inv = np.unique(keys, return_inverse=True)
    rate = np.array([conv[inv == k].mean() for k in range(len(uniq))]) * 100
    first = np.array([np.flatnonzero(inv == k)[0] for k in range(len(uniq))])
    fig = plt.figure(figsize=(6.4, 6), constrained_layout=True)
    ax = fig.add_subplot(projection="polar")
    sc = ax.scatter(np.radians(bear[first]), off[first], c=rate, cmap="RdYlGn", vmin=0, vmax=100, s=60,
                    edgecolors="k", linewidths=0.3)
    ax.set_title("region of attraction: convergence rate (%) by where each follower starts\n"
                 "(bearing from its slot in the leader frame, 90° = ahead; radius: offset in m)")
    fig.colorbar(sc, ax=ax, shrink=0.7)
    path = out / f"region_of_attraction.{fmt}"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _history(plt: Any, folder: StudyFolder, spec: StudySpec, out: Path, fmt: str) -> Path | None:
    from app.study.optimize import history

    trials = history(folder)
    if not trials:
        return None
    num = np.array([t[0] for t in trials], dtype=np.float64)
    val = np.array([t[1] for t in trials], dtype=np.float64)
    best = np.minimum.accumulate(np.where(np.isfinite(val), val, np.inf))
    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    ax.plot(num, val, "o", ms=3, color="tab:gray", label="trial")
    ax.plot(num, np.where(np.isfinite(best), best, np.nan), "-", color="tab:red", label="best so far")
    k = int(np.nanargmin(np.where(np.isfinite(val), val, np.nan))) if np.isfinite(val).any() else None
    if k is not None:
        ax.plot([num[k]], [val[k]], "*", ms=14, color="tab:red", label=f"best: trial {int(num[k])}")
    ax.set_xlabel("trial")
    ax.set_ylabel(spec.optimize.objective if spec.optimize else "objective")
    ax.set_title("optimisation history (Optuna TPE)")
    ax.legend()
    path = out / f"optimize_history.{fmt}"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _safe(name: str) -> str:
    return name.replace(".", "_").replace("/", "_")
