"""Static figures in the paper's style (matplotlib, headless Agg backend).

The simulation figure reproduces the layout of fig. 16-17: the team's world
trajectories with formation triangles at a few instants, the x / y position
errors per follower over time, and the followers' headings.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from core.geometry import leader_to_world  # noqa: E402
from core.sim.run import SimulationLog  # noqa: E402

FOLLOWER_COLOURS = ["tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray"]


def _colour(i: int) -> str:
    return FOLLOWER_COLOURS[i % len(FOLLOWER_COLOURS)]


def plot_simulation(log: SimulationLog, path: Path, instants: int = 6) -> None:
    """Write the fig. 16-17 style figure of a run to ``path`` (PNG)."""
    n = log.n
    per_follower_rows = n <= 4
    rows = (n if per_follower_rows else 2) + 1
    fig = plt.figure(figsize=(13, 2.3 * rows + 1.0), constrained_layout=True)
    grid = fig.add_gridspec(rows, 2, width_ratios=[1.15, 1.0])
    ax_traj = fig.add_subplot(grid[:, 0])

    lx, ly = log.leader[:, 0], log.leader[:, 1]
    ax_traj.plot(lx, ly, color="tab:blue", lw=1.8, label="leader")
    for i in range(n):
        desired_world = np.array(
            [leader_to_world(log.p_d[k, i], log.leader[k, :2], log.leader[k, 2])[0] for k in range(0, len(log.t), 10)]
        )
        ax_traj.plot(desired_world[:, 0], desired_world[:, 1], "--", color=_colour(i), lw=0.9)
        ax_traj.plot(log.followers_world[:, i, 0], log.followers_world[:, i, 1], color=_colour(i), lw=1.3,
                     label=f"follower {i + 1}")
    start = int(np.searchsorted(log.t, 0.0))  # a vision run starts with its start-up manoeuvres (t < 0)
    for k in np.linspace(start, len(log.t) - 1, instants).astype(int):
        pts = np.vstack([log.leader[k, :2], log.followers_world[k, :, :2]])
        ax_traj.fill(pts[:, 0], pts[:, 1], facecolor="none", edgecolor="tab:red", lw=1.0)
        ax_traj.annotate(f"{log.t[k]:.0f} s", log.leader[k, :2], fontsize=7, color="tab:red",
                         xytext=(3, 3), textcoords="offset points")
    ax_traj.set_aspect("equal", adjustable="datalim")
    ax_traj.set_xlabel("x world (m)")
    ax_traj.set_ylabel("y world (m)")
    ax_traj.set_title(f"{log.scenario.name}: team trajectory (dashed: desired)")
    ax_traj.grid(alpha=0.3)
    ax_traj.legend(loc="best", fontsize=8)

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
                ax.plot(log.t, err[:, i, axis], color=_colour(i), lw=0.9, label=f"f{i + 1}")
            ax.set_ylabel("m")
            ax.set_title(f"{name} position error", fontsize=9)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6, ncol=3, loc="upper right")
    ax_head = fig.add_subplot(grid[rows - 1, 1])
    for i in range(n):
        ax_head.plot(log.t, np.degrees(log.a[:, i]), color=_colour(i), lw=1.0, label=f"follower {i + 1}")
    ax_head.axhline(90.0, color="k", lw=0.6, ls=":")
    ax_head.set_xlabel("t (s)")
    ax_head.set_ylabel("heading a (deg)")
    ax_head.set_title("headings in the leader frame (90° = aligned)", fontsize=9)
    ax_head.grid(alpha=0.3)
    ax_head.legend(fontsize=7, loc="upper right")
    fig.savefig(path, dpi=110)
    plt.close(fig)
