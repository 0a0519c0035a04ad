"""Sweeps: one step test run by the simulator over a grid of one or two gains, in a worker
process, so the live loop keeps its rate.

The worker is one process started for the sweep (``spawn``: a fresh interpreter, never a
fork of the threads serving the page and the robots), at a lower CPU priority than the loop;
the grid's points go to it one by one, so progress is counted point by point and a cancel
drops every point not started (the one running finishes in well under a second with truth
feedback, a few seconds with vision). The same code serves ``omniformation tune``, which
runs the points in its own process.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.control.tuning import GainRange, StepScore, StepTest, sweep_grid
from core.sim.sweep import run_step_test
from core.types import Gains

WORKER_NICE = 19  # the lowest priority: the robots' loop comes first


@dataclass(frozen=True)
class SweepResult:
    """Every point of a sweep in grid order (the first gain varies slowest); a point not run
    (cancelled) or failed has no score."""

    ranges: tuple[GainRange, ...]
    test: StepTest
    feedback: str  # "truth" or "vision"
    gains: tuple[Gains, ...]
    scores: tuple[StepScore | None, ...]
    seconds: float
    cancelled: bool = False
    errors: tuple[str, ...] = ()

    def values(self, k: int) -> tuple[float, ...]:
        """The swept gains' values at point k."""
        return tuple(float(getattr(self.gains[k], r.name)) for r in self.ranges)

    def point_label(self, k: int) -> str:
        s = self.scores[k]
        where = ", ".join(f"{r.name}={v:g}" for r, v in zip(self.ranges, self.values(k)))
        if s is None:
            return f"{where}: not run"
        w = s.worst
        settle = f"{w['settling_s']:.2f} s" if math.isfinite(w["settling_s"]) else "not settled"
        return f"{where}: settles {settle}, overshoot {w['overshoot_m'] * 100:.1f} cm, effort {w['effort']:.3f}"

    def order(self) -> list[int]:
        """Points from best to worst: settled before not, then shorter settling, then less overshoot."""
        def key(k: int) -> tuple[float, float, float]:
            s = self.scores[k]
            if s is None:
                return (2.0, math.inf, math.inf)
            w = s.worst
            settled = math.isfinite(w["settling_s"])
            return (0.0 if settled else 1.0, w["settling_s"] if settled else w["steady_rms_m"], w["overshoot_m"])
        return sorted(range(len(self.gains)), key=key)

    def best(self) -> int | None:
        ranked = [k for k in self.order() if self.scores[k] is not None]
        return ranked[0] if ranked else None

    def pareto(self) -> list[int]:
        """The points no other point beats on both settling time and overshoot (settled ones)."""
        pts = [(k, s.worst) for k, s in enumerate(self.scores) if s is not None and math.isfinite(s.worst["settling_s"])]
        front = []
        for k, w in pts:
            if not any(o["settling_s"] <= w["settling_s"] and o["overshoot_m"] <= w["overshoot_m"]
                       and (o["settling_s"] < w["settling_s"] or o["overshoot_m"] < w["overshoot_m"]) for _, o in pts):
                front.append(k)
        return sorted(front, key=lambda k: self.scores[k].worst["settling_s"])  # type: ignore[union-attr]  # settled ones

    def table(self) -> list[dict[str, object]]:
        """One row per point: the swept values and the team's figures."""
        rows: list[dict[str, object]] = []
        for k in range(len(self.gains)):
            row: dict[str, object] = {r.name: v for r, v in zip(self.ranges, self.values(k))}
            s = self.scores[k]
            w = s.worst if s is not None else {}
            row.update({"settling_s": w.get("settling_s"), "overshoot_cm": w.get("overshoot_m", math.nan) * 100,
                        "steady_rms_cm": w.get("steady_rms_m", math.nan) * 100, "effort": w.get("effort")})
            rows.append(row)
        return rows

    def csv(self) -> str:
        rows = self.table()
        cols = [r.name for r in self.ranges] + ["settling_s", "overshoot_cm", "steady_rms_cm", "effort_m2_per_s"]
        lines = [",".join(cols)]
        for row in rows:
            vals = list(row.values())
            lines.append(",".join("" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.6g}"
                                  for v in vals))
        return "\n".join(lines) + "\n"

    def grid(self, key: str = "settling_s") -> np.ndarray:
        """The team's ``key`` over the grid, shape (len(values of gain 1), len(values of gain 2) or 1)."""
        shape = tuple(len(r.values) for r in self.ranges) + ((1,) if len(self.ranges) == 1 else ())
        vals = [s.worst[key] if s is not None else math.nan for s in self.scores]
        return np.array(vals, dtype=np.float64).reshape(shape)


def _lower_priority() -> None:
    try:
        os.nice(WORKER_NICE)
    except OSError:
        pass


def run_point(base: Scenario, test: StepTest, twist: tuple[float, float], gains: Gains,
              vision: tuple[CameraConfig, Gamma] | None) -> StepScore:
    """One point of a sweep (the worker's task)."""
    rig, gamma = vision if vision is not None else (None, None)
    return run_step_test(base, test, twist, gains, rig, gamma).score


def run_sweep(base: Scenario, test: StepTest, twist: tuple[float, float], ranges: list[GainRange], base_gains: Gains,
              vision: tuple[CameraConfig, Gamma] | None = None,
              progress: Callable[[int, int], None] | None = None) -> SweepResult:
    """Every point here, one after the other (``omniformation tune``)."""
    grid = sweep_grid(ranges, base_gains)
    start = time.perf_counter()
    scores: list[StepScore | None] = []
    for k, g in enumerate(grid):
        scores.append(run_point(base, test, twist, g, vision))
        if progress:
            progress(k + 1, len(grid))
    return SweepResult(tuple(ranges), test, "vision" if vision else "truth", tuple(grid), tuple(scores),
                       time.perf_counter() - start)


class SweepRunner:
    """One sweep at a time in a worker process; ``on_progress(done, total)`` and
    ``on_done(result)`` are called from the runner's thread."""

    def __init__(self) -> None:
        self.on_progress: list[Callable[[int, int], None]] = []
        self.on_done: list[Callable[[SweepResult], None]] = []
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()
        self.last: SweepResult | None = None

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, base: Scenario, test: StepTest, twist: tuple[float, float], ranges: list[GainRange],
              base_gains: Gains, vision: tuple[CameraConfig, Gamma] | None = None) -> str | None:
        """Start a sweep; the reason it cannot, or None."""
        try:
            grid = sweep_grid(ranges, base_gains)
        except ValueError as exc:
            return str(exc)
        with self._lock:
            if self.busy:
                return "a sweep is running: wait for it or cancel it"
            self._cancel.clear()
            self._thread = threading.Thread(target=self._run, args=(base, test, twist, ranges, grid, vision),
                                            name="omniformation-sweep", daemon=True)
            self._thread.start()
        return None

    def cancel(self) -> bool:
        if not self.busy:
            return False
        self._cancel.set()
        return True

    def wait(self, timeout: float | None = None) -> SweepResult | None:
        t = self._thread
        if t is not None:
            t.join(timeout)
        return self.last

    def _run(self, base: Scenario, test: StepTest, twist: tuple[float, float], ranges: list[GainRange],
             grid: list[Gains], vision: tuple[CameraConfig, Gamma] | None) -> None:
        start = time.perf_counter()
        scores: list[StepScore | None] = [None] * len(grid)
        errors: list[str] = []
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_lower_priority) as pool:
            futures = {pool.submit(run_point, base, test, twist, g, vision): k for k, g in enumerate(grid)}
            done = 0
            pending = set(futures)
            while pending:
                if self._cancel.is_set():
                    for f in pending:
                        f.cancel()
                    break
                finished, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
                for f in finished:
                    try:
                        scores[futures[f]] = f.result()
                    except Exception as exc:  # noqa: BLE001 - one failed point is reported, the sweep goes on
                        errors.append(f"{type(exc).__name__}: {exc}"[:200])
                    done += 1
                    for fn in list(self.on_progress):
                        fn(done, len(grid))
        result = SweepResult(tuple(ranges), test, "vision" if vision else "truth", tuple(grid), tuple(scores),
                             time.perf_counter() - start, self._cancel.is_set(), tuple(errors))
        self.last = result
        for done_fn in list(self.on_done):
            done_fn(result)
