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
from matplotlib.axes import Axes  # noqa: E402
import numpy as np  # noqa: E402

from core.geometry import leader_to_world  # noqa: E402
from core.sim.run import SimulationLog  # noqa: E402

from core.camera.render.looks import follower_hex  # noqa: E402

colour = follower_hex  # each follower in its marker's colour, as on the page


def trajectory_panel(ax: Axes, t: np.ndarray, leader: np.ndarray, followers_world: np.ndarray,
                     p_d: np.ndarray, title: str, instants: int = 6) -> None:
    """The team's trajectory in the world (the paper's fig. 16 / 19): the leader, each
    follower and its desired path (dashed), and the formation drawn at a few instants from
    t = 0 on (a vision run starts with its start-up manoeuvres at t < 0). ``leader`` (T, 3)
    world pose, ``followers_world`` (T, n, >=2), ``p_d`` (T, n, 2) leader frame (NaN: none)."""
    ax.plot(leader[:, 0], leader[:, 1], color="tab:blue", lw=1.8, label="leader")
    for i in range(followers_world.shape[1]):
        ks = [k for k in range(0, len(t), 10) if np.all(np.isfinite(p_d[k, i]))]
        if ks:
            dw = np.array([leader_to_world(p_d[k, i], leader[k, :2], leader[k, 2])[0] for k in ks])
            ax.plot(dw[:, 0], dw[:, 1], "--", color=colour(i), lw=0.9)
        ax.plot(followers_world[:, i, 0], followers_world[:, i, 1], color=colour(i), lw=1.3,
                label=f"follower {i + 1}")
    start = int(np.searchsorted(t, 0.0))
    for k in np.linspace(min(start, len(t) - 1), len(t) - 1, instants).astype(int):
        pts = np.vstack([leader[k, :2], followers_world[k, :, :2]])
        if np.all(np.isfinite(pts)):
            ax.fill(pts[:, 0], pts[:, 1], facecolor="none", edgecolor="tab:red", lw=1.0)
            ax.annotate(f"{t[k]:.0f} s", (float(leader[k, 0]), float(leader[k, 1])), fontsize=7, color="tab:red",
                        xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x world (m)", ylabel="y world (m)", title=f"{title}: team trajectory (dashed: desired)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def plot_simulation(log: SimulationLog, path: Path, instants: int = 6) -> None:
    """Write the fig. 16-17 style figure of a run to ``path`` (PNG)."""
    n = log.n
    per_follower_rows = n <= 4
    rows = (n if per_follower_rows else 2) + 1
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
