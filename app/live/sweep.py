"""Sweeps: one step test run by the simulator over a grid of one or two gains, in a worker
process, so the live loop keeps its rate.

The worker is one process started for the sweep (``spawn``: a fresh interpreter, never a
fork of the threads serving the page and the robots), at a lower CPU priority than the loop;
the grid's points go to it one by one, so progress is counted point by point and a cancel
drops every point not started (the one running finishes in well under a second with truth
feedback, a few seconds with vision). ``omniformation tune`` runs the same points as a study
(app.study); :func:`run_sweep` runs them here, one after the other.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import threading
import time
from collections.abc import Callable


from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.control.tuning import GainRange, StepScore, StepTest, sweep_grid
from core.sim.sweep import SweepResult, run_step_test
from core.study.spec import point_key, run_seed
from core.types import Gains

WORKER_NICE = 19  # the lowest priority: the robots' loop comes first


def _lower_priority() -> None:
    try:
        os.nice(WORKER_NICE)
    except OSError:
        pass


def point_seed(base: Scenario, ranges: list[GainRange], gains: Gains) -> int:
    """A sweep point's seed as a study of the same sweep derives it (core.study.spec.run_seed: the
    base's seed, the point's values, replicate 0), so the page's sweeps, `tune` and a study file of
    the same sweep give the same numbers."""
    return run_seed(base.seed, point_key({f"gains.{r.name}": float(getattr(gains, r.name)) for r in ranges}), 0)


def run_point(base: Scenario, test: StepTest, twist: tuple[float, float], gains: Gains,
              vision: tuple[CameraConfig, Gamma] | None, seed: int | None = None) -> StepScore:
    """One point of a sweep (the worker's task), through the one point function (core.study.point)."""
    rig, gamma = vision if vision is not None else (None, None)
    sc = base if seed is None else base.replace(seed=seed)
    return run_step_test(sc, test, twist, gains, rig, gamma).score


def run_sweep(base: Scenario, test: StepTest, twist: tuple[float, float], ranges: list[GainRange], base_gains: Gains,
              vision: tuple[CameraConfig, Gamma] | None = None,
              progress: Callable[[int, int], None] | None = None) -> SweepResult:
    """Every point here, one after the other: the serial sweep (`tune` runs the same points as a study)."""
    grid = sweep_grid(ranges, base_gains)
    start = time.perf_counter()
    scores: list[StepScore | None] = []
    for k, g in enumerate(grid):
        scores.append(run_point(base, test, twist, g, vision, point_seed(base, ranges, g)))
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
            futures = {pool.submit(run_point, base, test, twist, g, vision, point_seed(base, ranges, g)): k
                       for k, g in enumerate(grid)}
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
