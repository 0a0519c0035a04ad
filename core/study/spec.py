"""A study file ([study], [grid], [sample], [optimize], [test]) -> a checked :class:`StudySpec`,
and its points: every combination of the grid's values crossed with the sample's points.

Parsing is pure (text in, objects out) and uses core.config's table reader, so an unknown key, a
wrong type or a value outside the parameter table's bound is one line naming it. An axis is any
numeric key of a scenario file as a dotted path (``gains.k_f1``, ``measurement.position_noise_m``,
``latency.camera_ms``, ``leader.speed_mps``, ...), checked the only way that cannot drift from the
scenario reader: its extreme values are written into the scenario's own document and that is
parsed by :func:`core.config.parse_scenario`. Besides those, ``team.followers`` (team size, slots
from a formation preset) and ``start.offset_m`` / ``start.bearing_deg`` / ``start.heading_deg``
(every follower starts this far from its slot, at this bearing, with this heading: regions of
attraction).

A point's key is a hash of its axis values, and each run's seed a hash of the study's seed, the
point's key and the replicate: neither depends on the order in which runs are made, so a run gives
the same numbers on one worker, two, or a cluster, today or when a study is resumed.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.bounds import FOLLOWERS
from core.config import ConfigError, Scenario, Table, parse_scenario_data, toml_document, toml_loads
from core.control.presets import FORMATION_PRESETS, default_formation, formation_preset
from core.control.tuning import OFFSET_M, STEP_KINDS, TURN_RPS, WINDOW_S, StepTest

FEEDBACKS = ("truth", "vision")
VISION_RATE_HZ = 30.0  # the synthetic camera's frame rate: one control step per frame (as `simulate --vision`)
MAX_REPLICATES = 100_000
MAX_RUNS = 100_000_000
MAX_SAMPLE = 1 << 24
MAX_TRIALS = 100_000
MAX_GRID_VALUES = 100_000

# axes that are not keys of a scenario file: (bound lo, hi, unit, whole number)
TEAM_FOLLOWERS = "team.followers"
START_OFFSET = "start.offset_m"
START_BEARING = "start.bearing_deg"
START_HEADING = "start.heading_deg"
SPECIAL_AXES: dict[str, tuple[float, float, str, bool]] = {
    TEAM_FOLLOWERS: (float(FOLLOWERS.lo), float(FOLLOWERS.hi), "followers", True),
    START_OFFSET: (0.0, 3.0, "m", False),
    START_BEARING: (-360.0, 360.0, "deg", False),
    START_HEADING: (-360.0, 360.0, "deg", False),
}
START_DEFAULTS = {START_OFFSET: 0.3, START_BEARING: -90.0, START_HEADING: 90.0}  # behind the slot, aligned
NOT_AXES = {"seed": "each run's seed derives from [study] seed, the point and the replicate",
            "name": "not a number", "description": "not a number"}
SCENARIO_AXIS = "scenario"  # the axis a study of several scenarios has

_DOTTED = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass(frozen=True)
class ScenarioSource:
    """A scenario file as text: a study applies its points to the document, then parses it."""

    name: str
    text: str
    source: str  # how errors name it


@dataclass(frozen=True)
class Axis:
    """One varied quantity: its dotted name and where its values come from."""

    name: str
    kind: str  # "grid", "sample", "optimize", "scenario"
    values: tuple[Any, ...] = ()  # grid and scenario axes
    lo: float = math.nan  # sample and optimize axes
    hi: float = math.nan
    log: bool = False
    integer: bool = False

    def scale(self, u: float) -> float:
        """A unit-interval draw mapped into [lo, hi] (logarithmically with ``log``)."""
        if self.log:
            v = math.exp(math.log(self.lo) + u * (math.log(self.hi) - math.log(self.lo)))
        else:
            v = self.lo + u * (self.hi - self.lo)
        return float(min(max(round(v) if self.integer else v, self.lo), self.hi))


@dataclass(frozen=True)
class Optimize:
    objective: str
    trials: int


@dataclass(frozen=True)
class StudySpec:
    """A checked study: what is run for every point (see the module's docstring)."""

    source: str
    text: str
    scenarios: tuple[ScenarioSource, ...]
    feedback: str
    duration_s: float | None
    seed: int
    replicates: int
    formation: str | None  # the preset for team.followers (None: a sensible one for the count)
    camera: str | None  # vision: the synthetic rig that renders frames (None: the shipped one)
    calibration: str | None  # vision: the Γ that reads them (None: the shipped one)
    test: StepTest | None  # a step test run from the team settled on its slots (`tune`), else the scenario's run
    axes: tuple[Axis, ...]  # scenario axis first (several scenarios), then the grid's, then the sample's
    sample_n: int = 0
    optimize: Optimize | None = None
    _sample: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def vision(self) -> bool:
        return self.feedback == "vision"

    @property
    def grid_axes(self) -> tuple[Axis, ...]:
        return tuple(a for a in self.axes if a.kind in ("scenario", "grid"))

    @property
    def sample_axes(self) -> tuple[Axis, ...]:
        return tuple(a for a in self.axes if a.kind == "sample")

    @property
    def optimize_axes(self) -> tuple[Axis, ...]:
        return tuple(a for a in self.axes if a.kind == "optimize")

    @property
    def shape(self) -> tuple[int, ...]:
        """Points along each grid axis, then the sample's count (1 without a sample)."""
        return tuple(len(a.values) for a in self.grid_axes) + (max(self.sample_n, 1),)

    @property
    def points(self) -> int:
        """Points of a grid / sample study (an optimisation: its trials)."""
        if self.optimize is not None:
            return self.optimize.trials
        return int(np.prod(self.shape))

    @property
    def runs(self) -> int:
        return self.points * self.replicates

    @property
    def axis_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.axes)

    def sample(self) -> np.ndarray:
        """The sample's points in the unit box, (n, d): scrambled Sobol seeded by the study's seed."""
        if self._sample is None:
            from scipy.stats import qmc

            d = len(self.sample_axes)
            if self.sample_n == 0 or d == 0:
                u = np.zeros((max(self.sample_n, 1), 0))
            else:
                import warnings

                with warnings.catch_warnings():  # a count that is no power of two is still a fine sample
                    warnings.simplefilter("ignore", UserWarning)
                    u = qmc.Sobol(d, scramble=True, seed=self.seed).random(self.sample_n)
            object.__setattr__(self, "_sample", u)
        assert self._sample is not None
        return self._sample

    def point(self, index: int) -> dict[str, Any]:
        """The axis values of point ``index`` (grid order: the first axis varies slowest, the sample fastest)."""
        idx = np.unravel_index(index, self.shape)
        out: dict[str, Any] = {}
        for a, k in zip(self.grid_axes, idx[:-1]):
            out[a.name] = a.values[int(k)]
        if self.sample_axes:
            u = self.sample()[int(idx[-1])]
            for a, x in zip(self.sample_axes, u):
                out[a.name] = a.scale(float(x))
        return out


def point_key(values: dict[str, Any]) -> str:
    """A stable key of a point's axis values (the same values: the same key, on any machine)."""
    canon = json.dumps([[k, _canon(values[k])] for k in sorted(values)], separators=(",", ":"))
    return hashlib.sha256(canon.encode()).hexdigest()[:16]


def _canon(v: Any) -> Any:
    if isinstance(v, bool) or isinstance(v, str):
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    return repr(float(v))


def run_seed(study_seed: int, key: str, replicate: int) -> int:
    """A run's seed (0 .. 2^32 - 1) from the study's seed, the point's key and the replicate."""
    digest = hashlib.sha256(f"{study_seed}/{key}/{replicate}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


# ------------------------------------------------------------------------------- the file


def parse_study(text: str, source: str, load_scenario: Any) -> StudySpec:
    """Parse a study document. ``load_scenario(name_or_path) -> ScenarioSource`` reads a scenario
    (the caller owns files); a ConfigError names what is wrong in one line."""
    top = toml_document(text, source)
    st = top.table("study", optional=False)
    names: list[str]
    if st.has("scenarios"):
        if st.has("scenario"):
            raise st.fail("scenarios", st.raw("scenarios"), "given alone: `scenario` or `scenarios`, not both")
        raw = st.raw("scenarios")
        if not isinstance(raw, list) or not raw or not all(isinstance(x, str) and x for x in raw):
            raise st.fail("scenarios", raw, "a non-empty list of scenario names or .toml paths")
        if len(set(raw)) != len(raw):
            raise st.fail("scenarios", raw, "a list without repeats")
        names = list(raw)
    else:
        names = [st.text("scenario")]
    scenarios = tuple(load_scenario(n) for n in names)
    feedback = st.text("feedback", default="truth", choices=FEEDBACKS)
    duration = st.number("duration_s", 0.0, 86400.0, lo_open=True, unit="s") if st.has("duration_s") else None
    if duration is None:
        st.used.add("duration_s")
    seed = st.integer("seed", 0, 2**32 - 1, default=0)
    replicates = st.integer("replicates", 1, MAX_REPLICATES, default=1)
    formation: str | None = st.text("formation", choices=FORMATION_PRESETS) if st.has("formation") else None
    if formation is None:
        st.used.add("formation")
    camera = st.text("camera") if st.has("camera") else None
    calibration = st.text("calibration") if st.has("calibration") else None
    st.used.update(("camera", "calibration"))
    if (camera is not None or calibration is not None) and feedback != "vision":
        raise st.fail("camera" if camera is not None else "calibration", camera or calibration,
                      'given only with feedback = "vision"')
    st.finish()
    test = _parse_test(top)

    axes: list[Axis] = []
    if len(scenarios) > 1:
        axes.append(Axis(SCENARIO_AXIS, "scenario", tuple(s.name for s in scenarios)))
    has_grid, has_sample, has_opt = top.has("grid"), top.has("sample"), top.has("optimize")
    if has_opt and (has_grid or has_sample):
        raise ConfigError(f"{source}: [optimize] is given with [{'grid' if has_grid else 'sample'}]: an optimisation"
                          " searches its own ranges (give [optimize] alone, or [grid] / [sample])")
    grid = top.table("grid")
    if has_grid and not grid.data:
        raise ConfigError(f"{source}: [grid] is empty: give at least one axis (a list, or {{lo, hi, n}}), or leave"
                          " [grid] out")
    for name in list(grid.data):
        axes.append(_grid_axis(grid, name))
    grid.finish()
    sample_n = 0
    sample = top.table("sample")
    if has_sample:
        sample_n = sample.integer("n", 1, MAX_SAMPLE)
        ranged = [k for k in sample.data if k != "n"]
        if not ranged:
            raise ConfigError(f"{source}: [sample] has no axis: give at least one \"key\" = {{lo, hi}}")
        for name in ranged:
            axes.append(_range_axis(sample, name, "sample"))
    sample.finish()
    optimize = None
    if has_opt:
        ot = top.table("optimize", optional=False)
        objective = ot.text("objective")
        trials = ot.integer("trials", 1, MAX_TRIALS)
        ranged = [k for k in ot.data if k not in ("objective", "trials")]
        if not ranged:
            raise ConfigError(f"{source}: [optimize] has no axis: give at least one \"key\" = {{lo, hi}}")
        for name in ranged:
            axes.append(_range_axis(ot, name, "optimize"))
        ot.finish()
        why = objective_error(objective)
        if why:
            raise ot.fail("objective", objective, why)
        optimize = Optimize(objective, trials)
    top.finish()
    seen: set[str] = set()
    for a in axes:
        if a.name in seen:
            raise ConfigError(f"{source}: axis \"{a.name}\" is given twice (in [grid] and [sample]): once")
        seen.add(a.name)
    spec = StudySpec(source, text, scenarios, feedback, duration, seed, replicates, formation, camera, calibration,
                     test, tuple(axes), sample_n, optimize)
    if spec.runs > MAX_RUNS:
        raise ConfigError(f"{source}: {spec.points} points x {replicates} replicates = {spec.runs} runs: at most"
                          f" {MAX_RUNS}")
    _check_axes(spec)
    return spec


def _parse_test(top: Table) -> StepTest | None:
    if not top.has("test"):
        top.used.add("test")
        return None
    t = top.table("test", optional=False)
    kind = t.text("kind", choices=STEP_KINDS)
    window = t.number("window_s", WINDOW_S[0], WINDOW_S[1], default=10.0, unit="s")
    if kind == "offset":
        follower = t.integer("follower", 1, int(FOLLOWERS.hi), default=1)
        size = t.number("size_cm", -OFFSET_M[1] * 100, OFFSET_M[1] * 100, default=10.0, unit="cm") / 100.0
        if abs(size) < OFFSET_M[0]:
            raise t.fail("size_cm", size * 100, f"at least {OFFSET_M[0] * 100:g} cm either way")
        test = StepTest("offset", follower - 1, size, window_s=window)
    elif kind == "switch":
        test = StepTest("switch", formation=t.text("formation", default="line abreast", choices=FORMATION_PRESETS),
                        window_s=window)
    else:
        deg = t.number("size_deg_s", -math.degrees(TURN_RPS[1]), math.degrees(TURN_RPS[1]), default=5.0, unit="deg/s")
        if abs(deg) < math.degrees(TURN_RPS[0]):
            raise t.fail("size_deg_s", deg, f"at least {math.degrees(TURN_RPS[0]):g} deg/s either way")
        test = StepTest("turn", size=math.radians(deg), window_s=window)
    t.finish()
    return test


def _axis_name(table: Table, name: str) -> None:
    if not _DOTTED.match(name):
        raise ConfigError(f"{table.source}: [{table.prefix}] \"{name}\" is not an axis: a dotted key of a scenario"
                          f" file (gains.k_f1) or one of {', '.join(SPECIAL_AXES)}")
    if name in NOT_AXES:
        raise ConfigError(f"{table.source}: [{table.prefix}] \"{name}\" cannot be an axis: {NOT_AXES[name]}")
    if name.split(".")[0] in ("team", "start") and name not in SPECIAL_AXES:
        raise ConfigError(f"{table.source}: [{table.prefix}] \"{name}\" is not a known axis (known: "
                          f"{', '.join(SPECIAL_AXES)})")


def _number(table: Table, name: str, value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ConfigError(f"{table.source}: [{table.prefix}] \"{name}\" {what} = {value!r}: must be a finite number")
    return float(value)


def _grid_axis(grid: Table, name: str) -> Axis:
    _axis_name(grid, name)
    raw = grid.raw(name)
    if isinstance(raw, list):
        if not raw:
            raise ConfigError(f"{grid.source}: [grid] \"{name}\" = []: empty; give at least one value")
        values = [_number(grid, name, v, "value") for v in raw]
        if len(values) > MAX_GRID_VALUES:
            raise ConfigError(f"{grid.source}: [grid] \"{name}\": {len(values)} values, at most {MAX_GRID_VALUES}")
        if len(set(values)) != len(values):
            raise ConfigError(f"{grid.source}: [grid] \"{name}\" = {raw!r}: a value is listed twice")
    elif isinstance(raw, dict):
        sub = Table(raw, grid.source, f"grid.\"{name}\"")
        lo = sub.number("lo", -1e12, 1e12)
        hi = sub.number("hi", -1e12, 1e12)
        n = sub.integer("n", 1, MAX_GRID_VALUES)
        log = sub.flag("log", False)
        sub.finish()
        if hi < lo:
            raise sub.fail("hi", hi, f">= lo ({lo:g})")
        if n > 1 and hi == lo:
            raise sub.fail("n", n, f"1 when lo = hi ({lo:g}): the grid would repeat one value")
        if log and lo <= 0:
            raise sub.fail("lo", lo, "> 0 with log = true")
        arr = np.geomspace(lo, hi, n) if log else np.linspace(lo, hi, n)
        values = [float(v) for v in arr]
    else:
        raise ConfigError(f"{grid.source}: [grid] \"{name}\" = {raw!r}: must be a list of numbers or {{lo, hi, n}}")
    integer = SPECIAL_AXES.get(name, (0, 0, "", False))[3]
    if integer:
        if not all(v == int(v) for v in values):
            raise ConfigError(f"{grid.source}: [grid] \"{name}\" = {raw!r}: must be whole numbers")
        return Axis(name, "grid", tuple(int(v) for v in values), integer=True)
    return Axis(name, "grid", tuple(values))


def _range_axis(table: Table, name: str, kind: str) -> Axis:
    _axis_name(table, name)
    raw = table.raw(name)
    if not isinstance(raw, dict):
        raise ConfigError(f"{table.source}: [{table.prefix}] \"{name}\" = {raw!r}: must be {{lo, hi}} (log = true"
                          " for a logarithmic range)")
    sub = Table(raw, table.source, f"{table.prefix}.\"{name}\"")
    lo = sub.number("lo", -1e12, 1e12)
    hi = sub.number("hi", -1e12, 1e12)
    log = sub.flag("log", False)
    sub.finish()
    if hi <= lo:
        raise sub.fail("hi", hi, f"> lo ({lo:g})")
    if log and lo <= 0:
        raise sub.fail("lo", lo, "> 0 with log = true")
    integer = SPECIAL_AXES.get(name, (0, 0, "", False))[3]
    return Axis(name, kind, lo=lo, hi=hi, log=log, integer=integer)


TRUTH_ONLY = ("measurement.position_noise_m", "measurement.heading_noise_deg")


def _check_axes(spec: StudySpec) -> None:
    """Every axis's extreme values, applied to every scenario and parsed as the scenario reader
    parses a file: a value a scenario file could not hold is refused here, not in run 9,000."""
    for axis in spec.axes:
        if axis.kind == "scenario":
            continue
        if spec.vision and axis.name in TRUTH_ONLY:
            raise ConfigError(f"{spec.source}: \"{axis.name}\" is noise on ground-truth feedback, which a vision study"
                              " does not use (the pipeline's own error is its measurement): vary"
                              " \"measurement.vision_position_noise_m\" (noise added to the pipeline's estimates)")
        extremes = [min(axis.values), max(axis.values)] if axis.values else [axis.lo, axis.hi]
        section = {"grid": "grid", "sample": "sample", "optimize": "optimize"}[axis.kind]
        for value in extremes:
            if axis.name in SPECIAL_AXES:
                lo, hi, unit, integer = SPECIAL_AXES[axis.name]
                if not lo <= value <= hi:
                    raise ConfigError(f"{spec.source}: [{section}] \"{axis.name}\" = {value:g}: must be in [{lo:g},"
                                      f" {hi:g}] {unit}")
            for sc in spec.scenarios:
                try:
                    scenario_for(spec, sc, {axis.name: value}, seed=0)
                except ConfigError as exc:
                    raise ConfigError(f"{spec.source}: [{section}] \"{axis.name}\" = {value:g} does not fit"
                                      f" {sc.name}: {_tail(str(exc))}") from None
                except ValueError as exc:
                    raise ConfigError(f"{spec.source}: [{section}] \"{axis.name}\" = {value:g} does not fit"
                                      f" {sc.name}: {exc}") from None


def _tail(message: str) -> str:
    """A scenario reader's message without its own source (the study's error names the study)."""
    head, sep, rest = message.partition(": ")
    return rest if sep else message


# ------------------------------------------------------------------------ applying a point


def scenario_for(spec: StudySpec, source: ScenarioSource, values: dict[str, Any], seed: int) -> Scenario:
    """The scenario of one run: ``values`` (axis -> value) written into the scenario's document,
    the study's duration and the run's seed, then parsed (every bound checked by the reader)."""
    doc = copy.deepcopy(toml_loads(source.text, source.source))
    src = f"{source.source} (study point)"
    doc["seed"] = int(seed)
    if spec.duration_s is not None:
        doc["duration_s"] = float(spec.duration_s)
    if spec.vision:
        doc["rate_hz"] = VISION_RATE_HZ
    special = {k: v for k, v in values.items() if k in SPECIAL_AXES}
    for name, value in values.items():
        if name in SPECIAL_AXES or name == SCENARIO_AXIS:
            continue
        _set_number(doc, name, value, src)
    if special or spec.test is not None:
        _place_team(doc, special, spec.formation, src, settled=spec.test is not None and not special)
    return parse_scenario_data(doc, src)


def _set_number(doc: dict[str, Any], dotted: str, value: Any, source: str) -> None:
    parts = dotted.split(".")
    node: Any = doc
    for i, part in enumerate(parts[:-1]):
        nxt = node.get(part) if isinstance(node, dict) else None
        if nxt is None:
            nxt = node[part] = {}
        if not isinstance(nxt, dict):
            raise ConfigError(f"{source}: {'.'.join(parts[:i + 1])} is not a table: \"{dotted}\" cannot be an axis")
        node = nxt
    old = node.get(parts[-1])
    if old is not None and (isinstance(old, bool) or not isinstance(old, (int, float))):
        raise ConfigError(f"{source}: {dotted} = {old!r} is not a number: it cannot be an axis")
    node[parts[-1]] = value


def _place_team(doc: dict[str, Any], special: dict[str, Any], formation: str | None, source: str,
                settled: bool) -> None:
    """team.followers and start.*: the team's size (slots from a preset) and each follower's start
    relative to its slot. ``settled`` (a step test without start axes): each on its slot, aligned."""
    slots_doc = doc.get("formation", {}).get("slots") if isinstance(doc.get("formation"), dict) else None
    followers = doc.get("followers")
    n = int(special.get(TEAM_FOLLOWERS, len(followers) if isinstance(followers, list) else 0))
    if TEAM_FOLLOWERS in special:
        slots = formation_preset(formation, n) if formation else default_formation(n)
        doc.setdefault("formation", {})["slots"] = [[float(x), float(y)] for x, y in slots]
    else:
        if not isinstance(slots_doc, list) or len(slots_doc) < n:
            raise ConfigError(f"{source}: formation.slots: fewer than the followers")
        slots = np.array(slots_doc[:n], dtype=np.float64)
    if settled:
        offset, bearing, heading = 0.0, 0.0, 90.0
    else:
        offset = float(special.get(START_OFFSET, START_DEFAULTS[START_OFFSET]))
        bearing = float(special.get(START_BEARING, START_DEFAULTS[START_BEARING]))
        heading = float(special.get(START_HEADING, START_DEFAULTS[START_HEADING]))
    b = math.radians(bearing)
    doc["followers"] = [{"position": [float(x) + offset * math.cos(b), float(y) + offset * math.sin(b)],
                         "heading_deg": heading} for x, y in np.asarray(slots, dtype=np.float64)[:n]]


# ---------------------------------------------------------------------------- objectives

OBJECTIVE_NAMES = ("converged", "settling_s", "overshoot_m", "final_rms_m", "max_error_m", "effort",
                   "min_distance_m", "collisions", "tracking_lost_s")


def objective_error(expr: str) -> str | None:
    """Why ``expr`` is no objective (one line), or None: arithmetic (+ - * / **, numbers,
    parentheses, min(), max(), abs()) over the metrics' names."""
    import ast

    try:
        tree = ast.parse(expr, mode="eval")
    except SyntaxError:
        return "an arithmetic expression over the metrics (e.g. \"settling_s + 10 * overshoot_m\")"
    allowed = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Constant, ast.Name, ast.Load, ast.Add, ast.Sub, ast.Mult,
               ast.Div, ast.Pow, ast.USub, ast.UAdd, ast.Call)
    for node in ast.walk(tree):
        if not isinstance(node, allowed):
            return f"arithmetic over {', '.join(OBJECTIVE_NAMES)} (found {type(node).__name__})"
        if isinstance(node, ast.Constant) and (isinstance(node.value, bool) or not isinstance(node.value, (int, float))):
            return "numbers and metric names only"
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in ("min", "max", "abs") or node.keywords:
                return "calls to min(), max() and abs() only"
        if isinstance(node, ast.Name) and node.id not in OBJECTIVE_NAMES and node.id not in ("min", "max", "abs"):
            return f"names among {', '.join(OBJECTIVE_NAMES)} (found {node.id!r})"
    return None


def evaluate_objective(expr: str, medians: dict[str, float]) -> float:
    """``expr`` over ``medians`` (checked by :func:`objective_error` first)."""
    import ast
    import operator

    ops: dict[type, Any] = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
                            ast.Div: operator.truediv, ast.Pow: operator.pow, ast.USub: operator.neg,
                            ast.UAdd: operator.pos}
    funcs: dict[str, Any] = {"min": min, "max": max, "abs": abs}

    def ev(node: ast.AST) -> float:
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant):
            return float(node.value)  # type: ignore[arg-type]  # numbers only: objective_error checked it
        if isinstance(node, ast.Name):
            return float(medians[node.id])
        if isinstance(node, ast.UnaryOp):
            return float(ops[type(node.op)](ev(node.operand)))
        if isinstance(node, ast.BinOp):
            try:
                return float(ops[type(node.op)](ev(node.left), ev(node.right)))
            except (ZeroDivisionError, OverflowError):
                return math.inf
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            return float(funcs[node.func.id](*(ev(a) for a in node.args)))
        raise ValueError(f"objective: {type(node).__name__} is not allowed")

    return ev(ast.parse(expr, mode="eval"))


def flat_fields(text: str, source: str) -> list[tuple[str, Any]]:
    """A study document's fields as (``[table] key``, value) in document order: what resume
    compares to name the first field that changed."""
    out: list[tuple[str, Any]] = []

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        else:
            out.append((prefix, node))

    walk("", toml_loads(text, source))
    return out
