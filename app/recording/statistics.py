"""A recording's numbers, tallied in one pass a block of ticks at a time (:func:`scan`): per
follower the settling time, steady-state error RMS and max, time not tracked; the safety
summary (collisions, near misses, limit hits, ring exits, obstacle clearance); the latency;
the step tests as the page scored them and as recomputed here. What :mod:`app.recording.report`
writes as summary.json and summary.md, beside its figures (drawn from every k-th tick, at
most MAX_PLOTTED points per line), so memory does not grow with the recording's length.

Errors use the true pose when the recording has one (simulation), else the estimate.
"""

from __future__ import annotations

from typing import Any
from dataclasses import dataclass, field

import numpy as np

from app.recording.reader import Recording
from app.recording.schema import json_floats, scenario_obstacles
from core.control.tuning import SETTLE_TOL_M

SETTLED_M = SETTLE_TOL_M  # settled: the error stays under 2 cm to the end (the page's step tests and sweeps use the same)
SETTLED_MEANS = f"the error stays under {SETTLED_M * 100:.0f} cm to the end"
DISTANCE_BLOCK = 4096  # ticks at a time for the pairwise distances (bounded memory on an hour's recording)


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
    filter_acting: np.ndarray | None = None  # (T,) the safety filter changed a command (None: not recorded)
    v_each: np.ndarray | None = None  # (T, n) eq. 21 per follower
    v_rate: np.ndarray | None = None  # (T, n) its rate as the loop measured it (NaN: not recorded)
    limits: np.ndarray | None = None  # (T, n) core.control.tuning flags (NaN: not recorded)

    def min_distance(self) -> np.ndarray:
        """(T,) the smallest centre distance between two robots (followers and the leader) per tick."""
        out = np.full(len(self.t), np.inf)
        m = self.p.shape[1] + 1
        if m < 2:
            return out
        for a in range(0, len(self.t), DISTANCE_BLOCK):  # in blocks: the pairwise arrays are m^2 per tick
            p = self.p[a:a + DISTANCE_BLOCK]
            pts = np.concatenate([np.zeros((len(p), 1, 2)), p], axis=1)
            d = np.linalg.norm(pts[:, :, None, :] - pts[:, None, :, :], axis=-1)
            d[:, np.arange(m), np.arange(m)] = np.inf
            out[a:a + len(p)] = np.nanmin(d.reshape(len(p), -1), axis=1)
        return out


MAX_PLOTTED = 20_000  # points per line in a figure (every k-th tick of a longer recording)
SERIES_FIELDS = ("t", "leader", "followers_world", "p_true", "p_est", "p_d", "a_est", "a_raw", "tracked", "v_lyap",
                 "commands", "v_rate", "limits")
PER_FOLLOWER_OPTIONAL = ("v_rate", "limits")  # not in recordings made before the Lyapunov monitor
SAFETY_ACTING = ("on, changed", "on, infeasible", "on, no solver")  # the tick's safety status when the filter acted


class _Block:
    """Column arrays for `size` ticks, filled one tick at a time (shapes from the recording's
    first tick) and used again for the next block."""

    def __init__(self, first: dict[str, Any], size: int) -> None:
        self.cols: dict[str, np.ndarray] = {}
        for name in SERIES_FIELDS:
            like = first.get(name) if first.get(name) is not None and name not in PER_FOLLOWER_OPTIONAL else first["a_est"]
            self.cols[name] = np.full((size, *json_floats(like).shape), np.nan)
        self.cols["acting"] = np.zeros(size, dtype=bool)
        self.cols["loop_t"] = np.full(size, np.nan)  # the loop's own clock (set back at a reset)
        self.cols["latency"] = np.full(size, np.nan)
        self.size, self.rows = size, 0

    def add(self, tk: dict[str, Any], session_t: float) -> None:
        """One tick, at its session time (the recording's clock; its own ``t`` is the loop's)."""
        k, cols = self.rows, self.cols
        cols["acting"][k] = str(tk.get("safety", "")).startswith(SAFETY_ACTING)
        latency = tk.get("latency_ms")
        cols["latency"][k] = latency if isinstance(latency, (int, float)) else np.nan
        cols["loop_t"][k] = tk.get("t", np.nan)
        for name in SERIES_FIELDS:
            value = session_t if name == "t" else tk.get(name)
            if name == "a_raw" and value is None:
                value = tk["a_est"]
            if value is None and name in PER_FOLLOWER_OPTIONAL:
                cols[name][k] = np.nan
                continue
            try:
                cols[name][k] = value
            except (TypeError, ValueError):  # JSON null (a NaN when written) inside
                cols[name][k] = json_floats(value)
        self.rows += 1

    def full(self) -> bool:
        return self.rows == self.size

    def taken(self) -> dict[str, np.ndarray]:
        """The rows filled so far (views), and the block emptied for the next ticks."""
        out = {name: a[:self.rows] for name, a in self.cols.items()}
        self.rows = 0
        return out


def _series(cols: dict[str, np.ndarray], start: float, truth: bool, has_filter: bool) -> Series:
    return Series(
        t=cols["t"] - start, leader=cols["leader"], followers_world=cols["followers_world"],
        p=cols["p_true"] if truth else cols["p_est"], p_d=cols["p_d"], a_est=cols["a_est"], a_raw=cols["a_raw"],
        tracked=cols["tracked"].astype(bool), v_lyap=np.nansum(cols["v_lyap"], axis=1),
        commands=cols["commands"], truth=truth, filter_acting=cols["acting"] if has_filter else None,
        v_each=cols["v_lyap"], v_rate=cols["v_rate"], limits=cols["limits"],
    )


class _Episodes:
    """Runs of consecutive ticks where a condition holds, counted across blocks."""

    def __init__(self) -> None:
        self.count = 0
        self.ticks = 0
        self._last = False

    def add(self, mask: np.ndarray) -> None:
        if mask.size == 0:
            return
        m = mask.astype(np.int8)
        self.count += int(np.count_nonzero(np.diff(np.concatenate([[int(self._last)], m])) == 1))
        self.ticks += int(m.sum())
        self._last = bool(m[-1])


class _Moments:
    """Sum of squares, count and maximum of the errors seen since the last reset."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.sq, self.count, self.max = 0.0, 0, -np.inf

    def add(self, e: np.ndarray) -> None:
        if e.size:
            self.sq += float(np.sum(e**2))
            self.count += e.size
            self.max = max(self.max, float(e.max()))

    def rms_max_cm(self) -> tuple[float | None, float | None]:
        if not self.count:
            return None, None
        return round(float(np.sqrt(self.sq / self.count)) * 100, 3), round(self.max * 100, 3)


class Tally:
    """The summary's numbers for a whole recording, accumulated block after block of ticks: what
    the recording's full arrays would give, in memory that does not grow with its length (a few
    numbers per follower). The blocks must come in order, the recording's ticks each once."""

    def __init__(self, n: int, t_end: float, gains: dict[str, Any], boxes: np.ndarray, truth: bool) -> None:
        self.n, self.truth, self.boxes = n, truth, boxes
        self.late_from = 0.75 * t_end  # not settled: the steady error is that of the last quarter
        self.v_max, self.w_max = float(gains.get("v_max", np.inf)), float(gains.get("w_max", np.inf))
        self._seen = 0  # ticks so far
        self.first_valid_t = np.full(n, np.nan)
        self.last_valid = np.full(n, -1)  # tick index
        self.last_above = np.full(n, -1)  # the last tick whose error was >= SETTLED_M
        self.settle_t = np.full(n, np.nan)  # the time of the tick after it
        self._settle_next = np.zeros(n, dtype=bool)  # the last above was a block's last tick
        self.since = [_Moments() for _ in range(n)]  # errors after the last above
        self.late = [_Moments() for _ in range(n)]
        self.not_tracked = np.zeros(n, dtype=np.int64)
        self.min_distance = np.inf
        self.collisions, self.near_misses, self.limit_hits, self.boundary_exits = (_Episodes() for _ in range(4))
        self.obstacle_hits, self.obstacle_near = _Episodes(), _Episodes()
        self.obstacle_clearance = np.inf
        self.acting: int | None = None

    @classmethod
    def of(cls, rec: Recording, n: int, t_end: float, truth: bool) -> "Tally":
        """A tally for `rec`'s ticks: its first gains' limits, and its obstacles if `truth` (the
        clearance is measured from true poses only)."""
        gains = rec.params[0][1].get("gains", {}) if rec.params else {}
        return cls(n, t_end, gains, recorded_obstacles(rec) if truth else np.zeros((0, 4)), truth)

    def add(self, s: Series) -> None:
        t, B = s.t, len(s.t)
        if B == 0:
            return
        after = t >= 0
        if self._settle_next.any():
            self.settle_t[self._settle_next] = t[0]
            self._settle_next[:] = False
        err = np.linalg.norm(s.p_d - s.p, axis=-1)  # (B, n)
        for i in range(self.n):
            e = err[:, i]
            ok = np.isfinite(e) & after
            valid = np.flatnonzero(ok)
            if valid.size:
                if self.last_valid[i] < 0:
                    self.first_valid_t[i] = t[valid[0]]
                self.last_valid[i] = self._seen + valid[-1]
                above = np.flatnonzero(ok & (e >= SETTLED_M))
                if above.size:
                    j = int(above[-1])
                    self.last_above[i] = self._seen + j
                    self.since[i].reset()
                    if j + 1 < B:
                        self.settle_t[i] = t[j + 1]
                    else:
                        self._settle_next[i] = True
                    self.since[i].add(e[j + 1:][ok[j + 1:]])
                else:
                    self.since[i].add(e[ok])
                self.late[i].add(e[ok & (t >= self.late_from)])
            self.not_tracked[i] += int(np.count_nonzero(~s.tracked[after, i]))
        close = s.min_distance()[after]
        finite = close[np.isfinite(close)]
        if finite.size:
            self.min_distance = min(self.min_distance, float(finite.min()))
        self.collisions.add(close < COLLISION_M)
        self.near_misses.add(close < NEAR_MISS_M)
        at_limit = (np.abs(s.commands[..., 0]) >= self.v_max - 1e-6) | (np.abs(s.commands[..., 1]) >= self.w_max - 1e-6)
        self.limit_hits.add(at_limit[after].any(axis=1))
        self.boundary_exits.add((np.linalg.norm(s.p, axis=-1) > BOUNDARY_M).any(axis=1)[after])
        gap = obstacle_gap(self.boxes, s)
        if gap is not None and after.any():
            self.obstacle_clearance = min(self.obstacle_clearance, float(np.nanmin(gap[after])))
            self.obstacle_hits.add(gap[after] <= 0.0)
            self.obstacle_near.add(gap[after] < OBSTACLE_CLEARANCE_M)
        if s.filter_acting is not None:
            self.acting = (self.acting or 0) + int(np.count_nonzero(s.filter_acting[after]))
        self._seen += B

    def followers(self, dt: float) -> list[dict[str, Any]]:
        out = []
        for i in range(self.n):
            if self.last_valid[i] < 0:
                settle, steady = None, self.late[i]
            elif self.last_above[i] < 0:
                settle, steady = float(self.first_valid_t[i]), self.since[i]
            elif self.last_above[i] == self.last_valid[i]:
                settle, steady = None, self.late[i]  # not settled by the end
            else:
                settle, steady = float(self.settle_t[i]), self.since[i]
            rms, peak = steady.rms_max_cm()
            out.append({
                "follower": i + 1,
                "settling_time_s": None if settle is None else round(settle, 2),
                "steady_error_rms_cm": rms,
                "steady_error_max_cm": peak,
                "time_not_tracked_s": round(float(self.not_tracked[i] * dt), 2),
            })
        return out

    def safety(self, dt: float) -> dict[str, Any]:
        """Robotarium's kind of per-run safety summary: collisions, near misses, actuator limit hits."""
        near_obstacle = {} if not np.isfinite(self.obstacle_clearance) else {
            "obstacle_clearance_cm": round(self.obstacle_clearance * 100, 1),
            "obstacle_hits": self.obstacle_hits.count,
            "obstacle_near_misses": self.obstacle_near.count,
        }
        return {"safety": {
            "distances_from": "true poses" if self.truth else "estimated poses",
            "min_distance_cm": round(self.min_distance * 100, 1) if np.isfinite(self.min_distance) else None,
            "collisions": self.collisions.count,
            "near_misses": self.near_misses.count,
            "time_under_min_distance_s": round(float(self.near_misses.ticks * dt), 2),
            "actuator_limit_hits": self.limit_hits.count,
            "boundary_exits": self.boundary_exits.count,
            **near_obstacle,
            "filter_acting_s": None if self.acting is None else round(float(self.acting * dt), 2),
        }}


class LatencyTally:
    """Frame-to-command latencies in 0.05 ms bins up to 2 s (a fixed 320 KB, whatever the length):
    percentiles to the bin."""

    BIN_MS = 0.05
    BINS = 40_000

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS + 1, dtype=np.int64)  # the last bin: 2 s or more

    def add(self, latency_ms: np.ndarray) -> None:
        values = latency_ms[np.isfinite(latency_ms)]
        np.add.at(self.counts, np.clip((values / self.BIN_MS).astype(np.int64), 0, self.BINS), 1)

    def summary(self) -> dict[str, float] | None:
        total = int(self.counts.sum())
        if total == 0:
            return None
        cum = np.cumsum(self.counts)
        at = {f"p{q}": round(float(np.searchsorted(cum, q / 100 * total) + 1) * self.BIN_MS, 2) for q in (50, 95, 99)}
        return {**at, "max": round(float(np.nonzero(self.counts)[0][-1] + 1) * self.BIN_MS, 2), "ticks": total}


@dataclass(frozen=True)
class Scan:
    """What one pass over a recording gives the report: the figures' series (every k-th tick)
    and the summary's tally (every tick)."""

    shown: Series
    tally: Tally
    t_first: float
    t_last: float
    dt: float  # the median tick interval
    latency: LatencyTally = field(default_factory=LatencyTally)
    segments: list["Segment"] = field(default_factory=list)  # between resets (one: the session had none)

    @property
    def truth(self) -> bool:
        return self.shown.truth


def scan(rec: Recording, block: int = DISTANCE_BLOCK, max_plotted: int = MAX_PLOTTED) -> Scan:
    """Read a recording's ticks once, in order, `block` at a time (its chunks are decoded one
    after the other): each block goes into the summary's tallies and its every k-th tick into
    the figures' series. Memory is one block and `max_plotted` rows, whatever the file's length.

    Time is the session's (the recording's own clock, which a reset does not set back). A reset
    (the loop's clock starting again) begins a new segment: the figures break their lines there
    (no line back to the start) and each segment has its own tally besides the session's.

    Errors use the true poses if any tick has them (simulation), else the estimates: both are
    tallied, since which one the recording has is known only at its end."""
    total = len(rec.ticks)
    first = rec.ticks[0]
    start = float(rec.metadata.get("scenario_start_s", "0") or 0)
    every = max(1, -(-total // max_plotted))
    n = json_floats(first["a_est"]).shape[0]
    t_end = float(rec.t[-1]) - start if len(rec.t) else 0.0
    tallies = {truth: Tally.of(rec, n, t_end, truth) for truth in (True, False)}
    segments: list[Segment] = []
    has_filter = "safety" in first
    kept: list[dict[str, np.ndarray]] = []
    truth = False
    t_first = t_last = np.nan
    rows = _Block(first, min(block, total))
    k0 = 0  # the recording's index of the block's first tick
    latency = LatencyTally()

    def flush() -> None:
        nonlocal truth, t_first, t_last, k0
        cols = rows.taken()
        if not len(cols["t"]):
            return
        latency.add(cols["latency"])
        truth = truth or bool(np.isfinite(cols["p_true"]).any())
        for which, tally in tallies.items():
            tally.add(_series(cols, start, which, has_filter))
        loop = dict(cols, t=cols["loop_t"])  # a segment's own clock: the loop's, from its reset
        for which, tally in segments[-1].tallies.items():
            tally.add(_series(loop, start if len(segments) == 1 else 0.0, which, has_filter))
        segments[-1].end_s = float(cols["t"][-1]) - start
        if k0 == 0:
            t_first = float(cols["t"][0]) - start
        t_last = float(cols["t"][-1]) - start
        take = np.arange((-k0) % every, len(cols["t"]), every)  # the recording's every k-th tick
        kept.append({name: a[take] for name, a in cols.items()})
        k0 += len(cols["t"])

    resets = sorted(float(e["t"]) for e in rec.events if e.get("kind") == "reset")
    previous = np.inf
    for k, tk in enumerate(rec.ticks):
        loop_t = float(tk.get("t", np.nan))
        if not segments or loop_t < previous - 1e-9:  # the first tick, or a reset: a new segment
            flush()
            if kept:  # a row of NaN: the figures' lines break at the reset
                kept.append({name: np.full((1, *a.shape[1:]), np.nan) if a.dtype.kind == "f" else a[-1:]
                             for name, a in kept[-1].items()})
            ends = [b for b in resets if b > float(rec.t[k]) + 1e-6] + [float(rec.t[-1])]
            seg_end = max(0.0, ends[0] - float(rec.t[k]))  # its length (the next reset the writer noted, or the end)
            segments.append(Segment(float(rec.t[k]) - start, float(rec.t[k]) - start,
                                    {w: Tally.of(rec, n, seg_end, w) for w in (True, False)}))
        previous = loop_t
        rows.add(tk, float(rec.t[k]))
        if rows.full():
            flush()
    flush()
    cols = {name: np.concatenate([c[name] for c in kept]) for name in kept[0]}
    dt = float(np.median(np.diff(rec.t))) if len(rec.t) > 1 else 0.0
    return Scan(_series(cols, start, truth, has_filter), tallies[truth], t_first, t_last, dt, latency, segments)


@dataclass
class Segment:
    """A stretch of the session between two resets (session time, s) and its own tallies (its
    times the loop's, from the reset)."""

    start_s: float
    end_s: float
    tallies: dict[bool, Tally]


COLLISION_M = 0.15  # two robot centres closer than this: their bodies (15 x 25 cm) touch
NEAR_MISS_M = 0.25  # the safety filter's default minimum distance
BOUNDARY_M = 2.2  # a follower further than this from the leader has left the camera's working ring (fig. 8)
OBSTACLE_CLEARANCE_M = 0.10  # a follower's body (a disc of 0.15 m) nearer than this to an obstacle: a near miss


def recorded_obstacles(rec: Recording) -> np.ndarray:
    """The world's boxes (core.obstacles.as_array rows) from the scenario the recording names."""
    from core.obstacles import as_array

    return as_array(scenario_obstacles(rec.metadata))


def obstacle_gap(boxes: np.ndarray, s: Series) -> np.ndarray | None:
    """(T,) the closest follower body to an obstacle's surface (true poses), or None (no obstacles, no truth)."""
    if len(boxes) == 0 or not s.truth:
        return None
    from core.config import ROBOT_RADIUS_M
    from core.obstacles import surface_distance

    fw = s.followers_world[..., :2].reshape(-1, 2)
    gaps = surface_distance(np.nan_to_num(fw, nan=1e9), boxes).min(axis=1).reshape(len(s.t), -1)
    return np.asarray(gaps.min(axis=1) - ROBOT_RADIUS_M)


def safety_summary(rec: Recording, s: Series, dt: float) -> dict[str, Any]:
    """The safety summary of one whole series (see Tally.safety)."""
    tally = Tally.of(rec, s.p.shape[1], float(s.t[-1]) if len(s.t) else 0.0, s.truth)
    tally.add(s)
    return tally.safety(dt)


def is_release(event: dict[str, Any]) -> bool:
    """A "stop" event that released STOP (the writer notes both under one kind)."""
    return "released" in str(event.get("detail", "")).lower()


def stop_intervals(rec: Recording, start: float) -> list[tuple[float, float]]:
    """(from, to) in the figures' time (s from the scenario's start) while STOP was engaged; one
    still engaged at the end runs to the last tick."""
    out: list[tuple[float, float]] = []
    since: float | None = None
    for e in sorted((e for e in rec.events if e.get("kind") == "stop"), key=lambda e: float(e["t"])):
        t = float(e["t"]) - start
        if is_release(e):
            if since is not None:
                out.append((since, t))
            since = None
        elif since is None:
            since = t
    if since is not None:
        out.append((since, float(rec.t[-1]) - start if len(rec.t) else since))
    return out


def summarise(rec: Recording, sc: Scan | None = None) -> dict[str, Any]:
    """summary.json's contents (one pass over the recording unless `sc` is that pass)."""
    sc = sc if sc is not None else scan(rec)
    stops = [e for e in rec.events if e.get("kind") == "stop"]
    released = [e for e in stops if is_release(e)]
    return {
        **sc.tally.safety(sc.dt),
        "recording": rec.path.name,
        "complete": rec.complete,
        "duration_s": round(sc.t_last - sc.t_first, 2),
        "errors_from": "true poses" if sc.truth else "estimated poses (no ground truth recorded)",
        "settled_means": SETTLED_MEANS,
        "followers": sc.tally.followers(sc.dt),
        "segments": [{"from_s": round(g.start_s, 2), "to_s": round(g.end_s, 2), "reset": k > 0,
                      "followers": g.tallies[sc.truth].followers(sc.dt)} for k, g in enumerate(sc.segments)],
        "stop_events": [{"t": round(float(e["t"]), 2), "detail": e["detail"]} for e in stops],
        "stops": len(stops) - len(released),  # STOP pressed (or a fault's STOP), not counting releases
        "releases": len(released),
        "events": len(rec.events),
        "latency_ms": sc.latency.summary(),  # frame (or observation) to commands written: p50, p95, p99, max
        "ticks_read": len(rec.t),
        "ticks_written": rec.ticks_written,  # null: the file has no intact summary (cut off)
        "lost_ticks": rec.lost_ticks,
        "lost_s": round(rec.lost_s, 3),
        "lost_where": [{"after_tick": g.after_tick, "t_from": round(g.t_from, 3), "t_to": round(g.t_to, 3),
                        "ticks": g.ticks} for g in rec.gaps()],
        "loss": rec.loss_note(),
        "step_tests": step_tests(rec),
    }


def step_tests(rec: Recording) -> list[dict[str, Any]]:
    """The session's step tests: what the page measured (recorded with each trial) beside the
    same scores computed here again from the recorded ticks (core.control.tuning.score_step)."""
    from core.control.tuning import score_step

    out = []
    for tr in rec.trials:
        row: dict[str, Any] = {"number": tr.get("number"), "label": tr.get("label"), "status": tr.get("status"),
                               "t0": tr.get("t0"), "gains": tr.get("gains"), "page": tr.get("team"),
                               "page_followers": tr.get("followers")}
        test = tr.get("test") or {}
        if tr.get("status") == "done" and isinstance(tr.get("t0"), (int, float)) and test.get("window_s"):
            t0, window = float(tr["t0"]), float(test["window_s"])
            idx = np.flatnonzero((rec.t >= t0 - 0.5 / 30) & (rec.t <= t0 + window + 0.5 / 30))
            ticks = [rec.ticks[int(k)] for k in idx]
            if len(ticks) >= 2:
                t = np.array([float(tk["t"]) for tk in ticks])
                p = np.array([json_floats(tk["p_est"]) for tk in ticks])
                target = np.array([json_floats(tk["slot_targets"])[np.array(tk["assignment"], dtype=int)]
                                   * np.array([float(tk.get("formation_scale", 1.0)), 1.0]) for tk in ticks])
                cmd = np.array([json_floats(tk["commands"]) for tk in ticks])
                score = score_step(t, p, target, cmd, t0, window, float(tr.get("wheel_base_m", 0.12)))
                row["report"] = {k: (float(v) if np.isfinite(v) else None) for k, v in score.worst.items()}
                row["report_settling_s"] = [float(v) if np.isfinite(v) else None for v in score.settling_s]
                row["report_overshoot_m"] = [float(v) for v in score.overshoot_m]
        out.append(row)
    return out


