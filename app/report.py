"""`omniformation report FILE --out DIR`: a recording as the paper's figures and a summary.

Figures (PNG, paper style): trajectory.png (fig. 16/21/25/28: the team's path with the
formation triangle at a few instants), errors.png (fig. 17/19/23/26: x / y position error
per follower), headings.png (fig. 20/24/27: measured vs Kalman-filtered headings),
lyapunov_commands.png (V(t) and the commands). summary.md and summary.json: per follower
the settling time, steady-state error RMS and max, time not tracked; the STOP events.

Errors use the true pose when the recording has one (simulation), else the estimate.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from app.figures import FOLLOWER_COLOURS  # noqa: E402
from app.recorder import Recording, json_floats  # noqa: E402
from core.geometry import leader_to_world  # noqa: E402

SETTLED_M = 0.03  # settled: the error stays under 3 cm to the end


@dataclass(frozen=True)
class Series:
    """A recording as arrays (T rows)."""

    t: np.ndarray  # s, 0 = the scenario's start (start-up manoeuvres before it)
    leader: np.ndarray  # (T, 3)
    followers_world: np.ndarray  # (T, n, 3)
    p: np.ndarray  # (T, n, 2) true if recorded, else estimated
    p_d: np.ndarray
    a_est: np.ndarray
    a_raw: np.ndarray
    tracked: np.ndarray
    v_lyap: np.ndarray  # (T,)
    commands: np.ndarray  # (T, n, 2)
    truth: bool


def series(rec: Recording) -> Series:
    ticks = rec.ticks
    start = float(rec.metadata.get("scenario_start_s", "0") or 0)
    t = np.array([tk["t"] for tk in ticks]) - start
    p_true = np.array([json_floats(tk["p_true"]) for tk in ticks])
    truth = bool(np.isfinite(p_true).any())
    p = p_true if truth else np.array([json_floats(tk["p_est"]) for tk in ticks])
    a_est = np.array([json_floats(tk["a_est"]) for tk in ticks])
    a_raw = np.array([json_floats(tk["a_raw"]) if tk.get("a_raw") is not None else json_floats(tk["a_est"]) for tk in ticks])
    return Series(
        t=t, leader=np.array([json_floats(tk["leader"]) for tk in ticks]),
        followers_world=np.array([json_floats(tk["followers_world"]) for tk in ticks]),
        p=p, p_d=np.array([json_floats(tk["p_d"]) for tk in ticks]), a_est=a_est, a_raw=a_raw,
        tracked=np.array([tk["tracked"] for tk in ticks], dtype=bool),
        v_lyap=np.array([np.nansum(json_floats(tk["v_lyap"])) for tk in ticks]),
        commands=np.array([json_floats(tk["commands"]) for tk in ticks]), truth=truth,
    )


def _colour(i: int) -> str:
    return FOLLOWER_COLOURS[i % len(FOLLOWER_COLOURS)]


def summarise(rec: Recording, s: Series) -> dict[str, object]:
    err = np.linalg.norm(s.p_d - s.p, axis=-1)  # (T, n)
    dt = float(np.median(np.diff(s.t))) if len(s.t) > 1 else 0.0
    followers = []
    for i in range(err.shape[1]):
        e = err[:, i]
        ok = np.isfinite(e) & (s.t >= 0)
        above = np.flatnonzero(ok & (e >= SETTLED_M))
        valid = np.flatnonzero(ok)
        if valid.size == 0:
            settle = None
        elif above.size == 0:
            settle = float(s.t[valid[0]])
        elif above[-1] == valid[-1]:
            settle = None  # not settled by the end
        else:
            settle = float(s.t[above[-1] + 1])
        steady = ok & (s.t >= (settle if settle is not None else s.t[-1] * 0.75))
        es = e[steady]
        followers.append({
            "follower": i + 1,
            "settling_time_s": None if settle is None else round(settle, 2),
            "steady_error_rms_cm": round(float(np.sqrt(np.mean(es**2))) * 100, 3) if es.size else None,
            "steady_error_max_cm": round(float(es.max()) * 100, 3) if es.size else None,
            "time_not_tracked_s": round(float((~s.tracked[s.t >= 0, i]).sum() * dt), 2),
        })
    stops = [e for e in rec.events if e.get("kind") == "stop"]
    return {
        "recording": rec.path.name,
        "complete": rec.complete,
        "duration_s": round(float(s.t[-1] - s.t[0]), 2),
        "errors_from": "true poses" if s.truth else "estimated poses (no ground truth recorded)",
        "settled_means": f"error stays under {SETTLED_M * 100:.0f} cm to the end",
        "followers": followers,
        "stop_events": [{"t": round(float(e["t"]), 2), "detail": e["detail"]} for e in stops],
        "events": len(rec.events),
    }


def _summary_md(sm: dict[str, object]) -> str:
    lines = [f"# Session report: {sm['recording']}", "",
             f"- duration {sm['duration_s']} s; errors from {sm['errors_from']}; settled = {sm['settled_means']}",
             f"- file complete: {'yes' if sm['complete'] else 'no (cut off; read up to its last complete chunk)'}",
             f"- {sm['events']} events, {len(sm['stop_events'])} STOP events"]  # type: ignore[arg-type]
    for ev in sm["stop_events"]:  # type: ignore[attr-defined]
        lines.append(f"  - {ev['t']} s: {ev['detail']}")
    lines += ["", "| follower | settling time (s) | steady error RMS (cm) | steady error max (cm) | not tracked (s) |",
              "|---|---|---|---|---|"]
    for f in sm["followers"]:  # type: ignore[attr-defined]
        lines.append(f"| {f['follower']} | {f['settling_time_s'] if f['settling_time_s'] is not None else 'not settled'}"
                     f" | {f['steady_error_rms_cm']} | {f['steady_error_max_cm']} | {f['time_not_tracked_s']} |")
    return "\n".join(lines) + "\n"


def _trajectory(s: Series, title: str, path: Path, instants: int = 6) -> None:
    n = s.p.shape[1]
    fig, ax = plt.subplots(figsize=(7.5, 7), constrained_layout=True)
    ax.plot(s.leader[:, 0], s.leader[:, 1], color="tab:blue", lw=1.8, label="leader")
    for i in range(n):
        ax.plot(s.followers_world[:, i, 0], s.followers_world[:, i, 1], color=_colour(i), lw=1.2,
                label=f"follower {i + 1}")
        ks = [k for k in range(0, len(s.t), 10) if np.all(np.isfinite(s.p_d[k, i]))]
        if ks:
            dw = np.array([leader_to_world(s.p_d[k, i], s.leader[k, :2], s.leader[k, 2])[0] for k in ks])
            ax.plot(dw[:, 0], dw[:, 1], "--", color=_colour(i), lw=0.8)
    start = int(np.searchsorted(s.t, 0.0))
    for k in np.linspace(min(start, len(s.t) - 1), len(s.t) - 1, instants).astype(int):
        pts = np.vstack([s.leader[k, :2], s.followers_world[k, :, :2]])
        if np.all(np.isfinite(pts)):
            ax.fill(pts[:, 0], pts[:, 1], facecolor="none", edgecolor="tab:red", lw=1.0)
            ax.annotate(f"{s.t[k]:.0f} s", s.leader[k, :2], fontsize=7, color="tab:red", xytext=(3, 3),
                        textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x world (m)", ylabel="y world (m)", title=f"{title}: team trajectory (dashed: desired)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _per_follower(s: Series, path: Path, ylabel: str, title: str,
                  draw: Callable[[plt.Axes, int], None]) -> None:
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


def _errors(s: Series, path: Path) -> None:
    err = s.p_d - s.p

    def draw(ax: plt.Axes, i: int) -> None:
        ax.plot(s.t, err[:, i, 0], color="tab:blue", lw=1.0, label="x error")
        ax.plot(s.t, err[:, i, 1], color="tab:red", lw=1.0, label="y error")

    _per_follower(s, path, "m", "position error", draw)


def _headings(s: Series, path: Path) -> None:
    def draw(ax: plt.Axes, i: int) -> None:
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
        axes[1].plot(s.t, s.commands[:, i, 0], color=_colour(i), lw=0.9, label=f"follower {i + 1}")
        axes[2].plot(s.t, s.commands[:, i, 1], color=_colour(i), lw=0.9)
    axes[1].set(ylabel="m/s", title="command v")
    axes[2].set(ylabel="rad/s", title="command ω", xlabel="t (s)")
    axes[1].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(rec: Recording, out: Path, progress: Callable[[int, int, str], None] | None = None) -> list[Path]:
    s = series(rec)
    title = rec.metadata.get("scenario", rec.path.stem)
    steps: list[tuple[str, Callable[[Path], None]]] = [
        ("trajectory.png", lambda p: _trajectory(s, title, p)),
        ("errors.png", lambda p: _errors(s, p)),
        ("headings.png", lambda p: _headings(s, p)),
        ("lyapunov_commands.png", lambda p: _lyapunov_commands(s, p)),
    ]
    written = []
    total = len(steps) + 1
    for k, (name, fn) in enumerate(steps, 1):
        fn(out / name)
        written.append(out / name)
        if progress:
            progress(k, total, name)
    sm = summarise(rec, s)
    (out / "summary.json").write_text(json.dumps(sm, indent=2) + "\n", encoding="utf-8")
    (out / "summary.md").write_text(_summary_md(sm), encoding="utf-8")
    written += [out / "summary.json", out / "summary.md"]
    if progress:
        progress(total, total, "summary.md, summary.json")
    return written
