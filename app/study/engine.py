"""Running a study on Dask: an embedded ``LocalCluster`` (N worker processes, one thread each) by
default, or a running scheduler's address (``dask scheduler`` and ``dask worker`` started by the
user, on this machine or a cluster's).

* Each worker loads the kernels (and, for vision, the rig) once, before its first batch: a worker
  plugin, so a worker that joins or is restarted later does it too.
* Runs go in batches of about :data:`BATCH_S` seconds of compute (measured from the batches that
  came back: a truth run of a few milliseconds rides with hundreds of others, a vision run of half
  a second with one or two), and at most :data:`IN_FLIGHT` batches per worker are in flight: the
  client holds the (point, replicate) pairs already done, never the whole study, so its memory
  stays flat however many runs there are.
* A finished batch is written at once as one Parquet part (app.study.store). A worker that dies
  mid-batch: Dask runs its batch again on another, and the client writes a batch once, when its
  result arrives, so every run appears exactly once. A run that raises is a failure row; a batch
  that kills its workers again and again (Dask gives up on it) becomes failure rows too.
* Ctrl-C stops submitting, drops the batches in flight and keeps every part already written: the
  same command resumes.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from distributed import WorkerPlugin

from app.study.batch import RunItem, run_batch, run_runs, warm_up
from app.study.store import StudyFolder
from core.study.spec import StudySpec, point_key, run_seed

BATCH_S = 1.0  # seconds of compute a batch aims at
IN_FLIGHT = 2  # batches in flight per worker
MAX_BATCH = 5000


def default_workers() -> int:
    """The CPUs this process may use, less one, at least 1."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, cpus - 1)


class WarmUp(WorkerPlugin):
    """A Dask worker plugin: the kernels (and the rig) loaded before the worker's first task, on
    every worker, those that join or are restarted later included."""

    name = "omniformation-study-warm-up"
    idempotent = True

    def __init__(self, spec: StudySpec) -> None:
        self.spec = spec

    def setup(self, worker: Any) -> None:
        worker.omniformation_warm_up_s = warm_up(self.spec)


@dataclass
class Progress:
    """The terminal's progress line: runs done / total, runs per second, time left."""

    total: int
    done_before: int
    points: int
    replicates: int
    out: Any = field(default_factory=lambda: sys.stderr)
    every_s: float = 0.5
    start: float = field(default_factory=time.monotonic)
    _last: float = 0.0
    done: int = 0
    failed: int = 0

    def update(self, done: int, failed: int, force: bool = False) -> None:
        self.done, self.failed = done, failed
        now = time.monotonic()
        if not force and now - self._last < (self.every_s if self.tty else 10.0):
            return
        self._last = now
        self.out.write(("\r" if self.tty else "") + self.line() + ("" if self.tty else "\n"))
        self.out.flush()

    @property
    def tty(self) -> bool:
        return bool(getattr(self.out, "isatty", lambda: False)())

    def line(self) -> str:
        elapsed = max(time.monotonic() - self.start, 1e-9)
        made = self.done - self.done_before
        rate = made / elapsed
        left = self.total - self.done - self.failed
        eta = _duration(left / rate) if rate > 0 else "?"
        frac = self.done / self.total if self.total else 1.0
        bar = "#" * int(round(24 * frac))
        reps = max(self.replicates, 1)
        fail = f", {self.failed} failed" if self.failed else ""
        return (f"[{bar:<24}] {self.done // reps}/{self.points} points ({self.done}/{self.total} runs{fail})"
                f" · {rate / reps:.2f} points/s ({rate:.1f} runs/s) · {eta} left   ")

    def finish(self) -> None:
        self.update(self.done, self.failed, force=True)
        if self.tty:
            self.out.write("\n")
            self.out.flush()


def _duration(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


@dataclass
class Outcome:
    """What a session of a study did."""

    made: int  # runs made (written) this session
    failed: int  # runs that raised this session
    skipped: int  # runs already in results/ at the start
    total: int
    seconds: float
    workers: int
    first_result_s: float  # from the start (cluster and warm-up included) to the first part written
    interrupted: bool = False
    dashboard: str = ""


def pending_runs(spec: StudySpec, done: set[tuple[str, int]]) -> Iterator[RunItem]:
    """Every run of a grid / sample study not in ``done``, in point order (made lazily)."""
    for index in range(spec.points):
        values = spec.point(index)
        key = point_key(values)
        for r in range(spec.replicates):
            if (key, r) not in done:
                yield RunItem(key, values, r, run_seed(spec.seed, key, r))


def light(spec: StudySpec) -> StudySpec:
    """The spec as shipped with each batch: without the sample's array (the client resolves points)."""
    import dataclasses

    return dataclasses.replace(spec, _sample=None)


def serial_rows(spec: StudySpec) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every run of a study in this process, one after the other (the serial sweep)."""
    return run_runs(spec, list(pending_runs(spec, set())), "local")


class Engine:
    """A Dask client (and, by default, the LocalCluster behind it) for one study session."""

    def __init__(self, spec: StudySpec, workers: int | None = None, cluster: str | None = None,
                 say: Callable[[str], None] = print) -> None:
        from distributed import Client, LocalCluster

        self.say = say
        self.cluster: Any = None
        try:
            if cluster:
                self.client = Client(cluster, timeout="10s")
            else:
                n = workers or default_workers()
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
                self.client = Client(self.cluster)
        except OSError as exc:
            raise _user_error(f"--cluster {cluster}: no Dask scheduler answers there ({exc})" if cluster
                              else f"cannot start the local Dask cluster: {exc}") from None
        except ValueError as exc:
            raise _user_error(f"--cluster {cluster}: {exc} (give tcp://HOST:PORT)") from None
        self.client.register_plugin(WarmUp(light(spec)), name=WarmUp.name)

    @property
    def workers(self) -> int:
        info = self.client.scheduler_info(n_workers=-1)
        return max(1, sum(int(w.get("nthreads", 1)) for w in info.get("workers", {}).values()))

    @property
    def dashboard(self) -> str:
        try:
            return str(self.client.dashboard_link or "")
        except (KeyError, AttributeError):
            return ""

    def close(self) -> None:
        try:
            self.client.close(timeout=10)
        finally:
            if self.cluster is not None:
                self.cluster.close(timeout=10)


def _user_error(message: str) -> Exception:
    from app.files import UserError

    return UserError(message)


class Ledger:
    """What a session wrote: each finished batch's part, the failures file kept current, the counts,
    and when the first result came. The grid's loop and the optimisation's share it."""

    def __init__(self, spec: StudySpec, folder: StudyFolder, start: float) -> None:
        self.spec, self.folder, self.start = spec, folder, start
        self.failures = {(f["point"], f["replicate"]): f for f in folder.failures()}
        self.made = self.failed = 0
        self.first = math.nan

    def take(self, fut: Any, items: list[RunItem]) -> list[dict[str, Any]]:
        """A finished batch: its rows written as a part (returned), its failures recorded."""
        rows: list[dict[str, Any]]
        fails: list[dict[str, Any]]
        try:
            rows, fails = fut.result()
        except Exception as exc:  # noqa: BLE001 - a batch Dask gave up on: its runs are failure rows
            rows, fails = [], [{"point": i.point, "replicate": i.replicate, "seed": i.seed, **i.values,
                                "error": f"{type(exc).__name__}: {exc}"[:500], "worker": "?"} for i in items]
        if rows:
            self.folder.write_part(self.spec, rows)
            if not math.isfinite(self.first):
                self.first = time.monotonic() - self.start
        changed = False
        for r in rows:
            changed |= self.failures.pop((r["point"], r["replicate"]), None) is not None
        for f in fails:
            self.failures[(f["point"], f["replicate"])] = f
            changed = True
        if changed:
            self.folder.write_failures(self.spec, list(self.failures.values()))
        self.made += len(rows)
        self.failed += len(fails)
        return rows


def run_grid(spec: StudySpec, folder: StudyFolder, engine: Engine, progress: Progress | None = None,
             start: float | None = None) -> Outcome:
    """Every run of a grid / sample study not yet in ``folder``; parts written as batches finish.
    ``start`` (time.monotonic): when the session began, for the time to the first result."""
    from distributed import as_completed

    start = time.monotonic() if start is None else start
    done = folder.done()
    skipped = len(done)
    ledger = Ledger(spec, folder, start)
    todo = pending_runs(spec, done)
    shipped = light(spec)
    workers = engine.workers
    per_run = math.nan  # seconds of compute a run takes, from the batches back
    in_flight: dict[Any, list[RunItem]] = {}
    remaining = spec.runs - skipped
    ac = as_completed()
    exhausted = False
    interrupted = False
    batches = 0

    def batch_size() -> int:
        if not math.isfinite(per_run) or per_run <= 0:
            return 1
        left = max(remaining - ledger.made - ledger.failed, 1)
        return int(max(1, min(MAX_BATCH, round(BATCH_S / per_run), math.ceil(left / (IN_FLIGHT * workers)))))

    def top_up() -> None:
        nonlocal exhausted
        while not exhausted and len(in_flight) < IN_FLIGHT * workers:
            items = []
            size = batch_size()
            for item in todo:
                items.append(item)
                if len(items) >= size:
                    break
            if not items:
                exhausted = True
                return
            fut = engine.client.submit(run_batch, shipped, items, pure=False)
            in_flight[fut] = items
            ac.add(fut)

    try:
        top_up()
        for fut in ac:
            rows = ledger.take(fut, in_flight.pop(fut))
            if rows:
                mean = sum(r["wall_s"] for r in rows) / len(rows)
                per_run = mean if not math.isfinite(per_run) else 0.5 * per_run + 0.5 * mean
            if progress is not None:
                progress.update(skipped + ledger.made, ledger.failed)
            batches += 1
            if batches % 20 == 0:  # workers that joined (or left) a cluster since
                workers = engine.workers
            top_up()
    except KeyboardInterrupt:
        interrupted = True
        for fut in list(in_flight):
            fut.cancel()
        in_flight.clear()
    if progress is not None:
        progress.finish()
    return Outcome(ledger.made, ledger.failed, skipped, spec.runs, time.monotonic() - start, workers, ledger.first,
                   interrupted, engine.dashboard)
