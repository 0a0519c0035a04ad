"""static_config TOML -> frozen, validated config objects.

Parsing is pure (text in, objects out); reading files is the caller's job.
Every problem raises :class:`ConfigError` whose message is one line naming the
file, the key, the bad value and what is allowed. Unknown keys are refused too:
a misspelt key silently ignored is a bug report waiting to happen.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.control.presets import FORMATION_PRESETS, formation_preset
from core.control.safety import SafetySettings
from core.obstacles import Obstacle, as_array, surface_distance
from core.sim.profiles import ConstantProfile, Eq39Profile, GoalProfile, LeaderProfile, Segment, SegmentsProfile
from core.sim.team import DISTURBANCE_KINDS, Disturbance, FollowerDynamics
from core.bounds import (GOAL_LIMIT_M, GOAL_SPEED, LEADER_SPEED, LEADER_TURN, MIN_SCALE, SAFETY_DISTANCE, SLOT_LIMIT_M,
                         number_default)
from core.types import GAIN_BOUNDS, Bound, FloatArray, Gains


class ConfigError(ValueError):
    """A user mistake in a config file: the message is one line for people."""


@dataclass(frozen=True)
class MeasurementNoise:
    """Gaussian noise on the ground-truth leader-frame measurements (truth feedback), and on the
    vision pipeline's position estimates (vision feedback: a rig whose calibration or markers are
    worse than the synthetic one's; none by default, the camera being the measurement)."""

    position_noise_m: float = 0.0
    heading_noise_rad: float = 0.0
    vision_position_noise_m: float = 0.0


@dataclass(frozen=True)
class Latency:
    """A real rig's delays for the stepped simulator ([latency]): what the camera saw reaches the
    controller ``camera_s`` later (exposure, USB, processing), a command reaches its follower
    ``radio_s`` after it is computed, each varying by up to ``jitter_s`` (whole ticks, at random).
    ``compensate``: the controller predicts each follower to the moment its command will act
    (core.control.prediction)."""

    camera_s: float = 0.0
    radio_s: float = 0.0
    jitter_s: float = 0.0
    compensate: bool = True

    @property
    def total_s(self) -> float:
        return self.camera_s + self.radio_s

    @classmethod
    def split(cls, total_s: float, camera_share: float = 0.6, jitter_s: float = 0.0,
              compensate: bool = True) -> "Latency":
        return cls(total_s * camera_share, total_s * (1.0 - camera_share), jitter_s, compensate)


@dataclass(frozen=True)
class Scenario:
    """Everything a simulated run needs. Poses in the leader frame at t = 0, SI units."""

    name: str
    description: str
    duration_s: float
    rate_hz: float
    seed: int
    leader: LeaderProfile
    initial_p: FloatArray  # (n, 2) m
    initial_a: FloatArray  # (n,) rad
    slots: FloatArray  # (m, 2) m, m >= n
    gains: Gains
    dynamics: FollowerDynamics
    measurement: MeasurementNoise
    disturbances: tuple[Disturbance, ...]
    obstacles: tuple[Obstacle, ...] = ()  # world frame (= the leader frame at t = 0)
    safety: SafetySettings | None = None  # the safety filter on every command ([safety]); None: off
    switches: tuple[tuple[float, FloatArray], ...] = ()  # (scenario time s, new slots (n, 2)), in order
    min_scale: float = 1.0  # the formation may shrink to this to pass a gap ([formation] min_scale)
    latency: Latency = Latency()  # a real rig's camera and radio delays ([latency]); none by default

    @property
    def stepped(self) -> bool:
        """Needs the stepped simulator (core.sim.stepped): obstacles, the filter, a goal, switches
        or latency."""
        return bool(self.obstacles) or self.safety is not None or isinstance(self.leader, GoalProfile) \
            or bool(self.switches) or self.latency.total_s > 0 or self.latency.jitter_s > 0

    @property
    def n(self) -> int:
        return int(self.initial_p.shape[0])

    def replace(self, **changes: Any) -> "Scenario":
        return dataclasses.replace(self, **changes)


class Table:
    """A TOML table being read: checks types and ranges, remembers which keys were used."""

    def __init__(self, data: Any, source: str, prefix: str) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: {prefix or 'file'} = {data!r}: must be a table")
        self.data = data
        self.source = source
        self.prefix = prefix
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def fail(self, name: str, value: Any, allowed: str) -> ConfigError:
        return ConfigError(f"{self.source}: {self.key(name)} = {value!r}: must be {allowed}")

    def has(self, name: str) -> bool:
        return name in self.data

    def raw(self, name: str) -> Any:
        self.used.add(name)
        if name not in self.data:
            raise ConfigError(f"{self.source}: {self.key(name)} is missing")
        return self.data[name]

    def number(
        self, name: str, lo: float, hi: float, default: float | None = None, lo_open: bool = False,
        unit: str = "",
    ) -> float:
        if default is not None and name not in self.data:
            self.used.add(name)
            return default
        value = self.raw(name)
        lo_br = "(" if lo_open else "["
        allowed = f"a number in {lo_br}{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(name, value, allowed)
        v = float(value)
        if not math.isfinite(v) or v > hi or (v <= lo if lo_open else v < lo):
            raise self.fail(name, value, allowed)
        return v

    def bounded(self, name: str, bound: Bound, default: float | None = None) -> float:
        """A number within one of core.bounds' declared ranges (the page and the store use the same)."""
        return self.number(name, bound.lo, bound.hi, default=default, lo_open=not bound.lo_inclusive, unit=bound.unit)

    def integer(self, name: str, lo: int, hi: int, default: int | None = None) -> int:
        if default is not None and name not in self.data:
            self.used.add(name)
            return default
        value = self.raw(name)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise self.fail(name, value, f"a whole number from {lo} to {hi}")
        return value

    def text(self, name: str, default: str | None = None, choices: tuple[str, ...] = ()) -> str:
        if default is not None and name not in self.data:
            self.used.add(name)
            return default
        value = self.raw(name)
        if not isinstance(value, str) or (choices and value not in choices):
            raise self.fail(name, value, "one of " + ", ".join(choices) if choices else "a string")
        return value

    def flag(self, name: str, default: bool) -> bool:
        if not self.has(name):
            self.used.add(name)
            return default
        value = self.raw(name)
        if not isinstance(value, bool):
            raise self.fail(name, value, "true or false")
        return value

    def point(self, name: str, limit: float) -> tuple[float, float]:
        value = self.raw(name)
        allowed = f"[x, y] with |x|, |y| <= {limit:g} m"
        if (
            not isinstance(value, list)
            or len(value) != 2
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)
            or not all(math.isfinite(float(c)) and abs(float(c)) <= limit for c in value)
        ):
            raise self.fail(name, value, allowed)
        return float(value[0]), float(value[1])

    def table(self, name: str, optional: bool = True) -> "Table":
        if optional and name not in self.data:
            self.used.add(name)
            return Table({}, self.source, self.key(name))
        return Table(self.raw(name), self.source, self.key(name))

    def tables(self, name: str) -> list["Table"]:
        value = self.raw(name) if name in self.data else []
        self.used.add(name)
        if not isinstance(value, list):
            raise self.fail(name, value, "an array of tables ([[...]])")
        return [Table(v, self.source, f"{self.key(name)}[{i + 1}]") for i, v in enumerate(value)]

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise ConfigError(
                f"{self.source}: {self.key(unknown[0])} is not a known key"
                f" (known here: {', '.join(sorted(self.used)) or 'none'})"
            )


MIN_SLOT_SPACING_M = 0.05  # two slots closer than this would put two robots in one place
WORKSPACE_LIMIT_M = 10.0


def _turn(t: Table) -> float:
    return math.radians(t.bounded("turn_deg_s", LEADER_TURN, default=0.0))


def _speed(t: Table) -> float:
    return t.bounded("speed_mps", LEADER_SPEED)


def _parse_leader(t: Table) -> LeaderProfile:
    kind = t.text("profile", choices=("constant", "eq39", "segments", "goal"))
    profile: LeaderProfile
    if kind == "goal":
        profile = GoalProfile(t.point("goal", GOAL_LIMIT_M), t.bounded("speed_mps", GOAL_SPEED))
    elif kind == "constant":
        profile = ConstantProfile(_speed(t), _turn(t))
    elif kind == "eq39":
        profile = Eq39Profile(
            speed_mps=_speed(t),
            k1_rps=math.radians(t.bounded("k1_deg_s", LEADER_TURN)),
            k2_per_s=t.number("k2_per_s", 0.0, 100.0, lo_open=True, unit="1/s"),
            t1_s=t.number("t1_s", 0.0, 1e6, unit="s"),
            t_start_s=t.number("t_start_s", 0.0, 1e6, unit="s"),
            t_end_s=t.number("t_end_s", 0.0, 1e6, unit="s"),
        )
        if profile.t_end_s < profile.t_start_s:
            raise t.fail("t_end_s", profile.t_end_s, f">= t_start_s ({profile.t_start_s:g})")
    else:
        segs = []
        for seg_t in t.tables("segments"):
            segs.append(Segment(seg_t.number("t_start_s", 0.0, 1e6, unit="s"), _speed(seg_t), _turn(seg_t)))
            seg_t.finish()
        if not segs:
            raise t.fail("segments", [], "at least one [[leader.segments]] table")
        starts = [s.t_start_s for s in segs]
        if starts != sorted(starts):
            raise t.fail("segments", starts, "in increasing t_start_s order")
        profile = SegmentsProfile(tuple(segs))
    t.finish()
    return profile


def _parse_dataclass(t: Table, cls: Any, bounds: dict[str, tuple[float, float, str]]) -> Any:
    values = {}
    for f in dataclasses.fields(cls):
        if t.has(f.name):
            lo, hi, unit = bounds[f.name]
            values[f.name] = t.number(f.name, lo, hi, unit=unit)
    t.finish()
    return cls(**values)


_DYNAMICS_BOUNDS = {
    "actuator_tau_s": (0.0, 5.0, "s"),
    "speed_max_mps": (0.0, 5.0, "m/s"),
    "turn_max_rps": (0.0, 20.0, "rad/s"),
    "accel_max_mps2": (0.0, 50.0, "m/s^2"),
    "turn_accel_max_rps2": (0.0, 500.0, "rad/s^2"),
    "wheel_noise_mps": (0.0, 0.5, "m/s"),
    "wheel_base_m": (0.01, 2.0, "m"),
}


def parse_dynamics(t: Table) -> FollowerDynamics:
    """A [dynamics] table: the simulated followers' lag, limits and wheel noise."""
    return _parse_dataclass(t, FollowerDynamics, _DYNAMICS_BOUNDS)


def parse_measurement(t: Table) -> MeasurementNoise:
    """A [measurement] table: noise on ground-truth feedback."""
    noise = MeasurementNoise(
        t.number("position_noise_m", 0.0, 0.5, default=0.0, unit="m"),
        math.radians(t.number("heading_noise_deg", 0.0, 90.0, default=0.0, unit="deg")),
        t.number("vision_position_noise_m", 0.0, 0.5, default=0.0, unit="m"),
    )
    t.finish()
    return noise


def parse_gains(t: Table) -> Gains:
    values = {}
    for name, bound in GAIN_BOUNDS.items():
        if t.has(name):
            values[name] = t.number(name, bound.lo, bound.hi, lo_open=not bound.lo_inclusive, unit=bound.unit)
    t.finish()
    return Gains(**values)


MAX_TOML_DEPTH = 64  # arrays and tables inside one another: more is no configuration of ours


def _depth(value: Any) -> int:
    """How deep arrays and tables nest in ``value`` (iterative: a deep document cannot overflow)."""
    deepest, todo = 0, [(value, 0)]
    while todo:
        v, d = todo.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list):
            deepest = max(deepest, d + 1)
            if d + 1 <= MAX_TOML_DEPTH:
                todo.extend((x, d + 1) for x in v)
    return deepest


def toml_loads(text: str, source: str) -> dict[str, Any]:
    """A TOML document as data, or ConfigError naming ``source``: not TOML, or nested deeper
    than MAX_TOML_DEPTH (tomllib recurses once per level: 5,000 ``[`` overflow its stack)."""
    too_deep = ConfigError(f"{source}: arrays or tables nested deeper than {MAX_TOML_DEPTH} levels")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        raise too_deep from None
    if _depth(data) > MAX_TOML_DEPTH:
        raise too_deep
    return data


def toml_document(text: str, source: str) -> Table:
    """A TOML document's top table, or ConfigError naming ``source``."""
    return Table(toml_loads(text, source), source, "")


def parse_scenario(text: str, source: str) -> Scenario:
    """Parse a scenario TOML document; ``source`` names it in error messages."""
    return parse_scenario_data(toml_loads(text, source), source)


def parse_scenario_data(data: dict[str, Any], source: str) -> Scenario:
    """A scenario document already read (a study writes its points into one): the same checks."""
    top = Table(data, source, "")
    name = top.text("name")
    description = top.text("description", default="")
    duration = top.number("duration_s", 0.0, 86400.0, lo_open=True, unit="s")
    rate = top.number("rate_hz", 1.0, 1000.0, unit="Hz")
    if duration * rate < 1.0:
        raise top.fail("duration_s", duration, f"at least one control tick (1/{rate:g} s at rate_hz = {rate:g})")
    seed = top.integer("seed", 0, 2**32 - 1, default=0)
    leader = _parse_leader(top.table("leader", optional=False))

    followers = top.tables("followers")
    if not followers:
        raise top.fail("followers", [], "at least one [[followers]] table")
    p0, a0 = [], []
    for ft in followers:
        p0.append(ft.point("position", WORKSPACE_LIMIT_M))
        a0.append(math.radians(ft.number("heading_deg", -360.0, 360.0, unit="deg")))
        ft.finish()

    formation = top.table("formation", optional=False)
    slots_raw = formation.raw("slots")
    if not isinstance(slots_raw, list):
        raise formation.fail("slots", slots_raw, "a list of [x, y] points")
    slots = [Table({"slot": s}, source, formation.key(f"slots[{i + 1}]")).point("slot", SLOT_LIMIT_M)
             for i, s in enumerate(slots_raw)]
    if len(slots) < len(p0):
        raise formation.fail("slots", slots_raw, f"at least as many points as followers ({len(p0)})")
    for i in range(len(slots)):
        for j in range(i):
            if math.dist(slots[i], slots[j]) < MIN_SLOT_SPACING_M:
                raise formation.fail("slots", slots_raw, f"points at least {MIN_SLOT_SPACING_M * 100:g} cm apart"
                                     f" (slots {j + 1} and {i + 1} are not: two robots cannot stand in one place)")
    min_scale = formation.bounded("min_scale", MIN_SCALE, default=1.0)
    switches = _parse_switches(formation, len(p0), duration, seed)
    formation.finish()

    gains = parse_gains(top.table("gains"))
    dynamics = parse_dynamics(top.table("dynamics"))
    measurement = parse_measurement(top.table("measurement"))

    disturbances = []
    for dt_ in top.tables("disturbances"):
        follower = dt_.integer("follower", 1, len(p0))
        kind = dt_.text("kind", choices=DISTURBANCE_KINDS)
        start = dt_.number("start_s", 0.0, 1e6, unit="s")
        end = dt_.number("end_s", 0.0, 1e6, unit="s")
        if end <= start:
            raise dt_.fail("end_s", end, f"> start_s ({start:g})")
        dt_.finish()
        disturbances.append(Disturbance(follower - 1, start, end, kind))
    obstacles = _parse_obstacles(top, np.array(p0, dtype=np.float64), leader)
    safety = _parse_safety(top)
    lt = top.table("latency")
    latency = Latency(camera_s=lt.number("camera_ms", 0.0, 2000.0, default=0.0, unit="ms") / 1e3,
                      radio_s=lt.number("radio_ms", 0.0, 2000.0, default=0.0, unit="ms") / 1e3,
                      jitter_s=lt.number("jitter_ms", 0.0, 1000.0, default=0.0, unit="ms") / 1e3,
                      compensate=lt.flag("compensate", True))
    lt.finish()
    top.finish()

    return Scenario(
        name=name,
        description=description,
        duration_s=duration,
        rate_hz=rate,
        seed=seed,
        leader=leader,
        initial_p=np.array(p0, dtype=np.float64),
        initial_a=np.array(a0, dtype=np.float64),
        slots=np.array(slots, dtype=np.float64),
        gains=gains,
        dynamics=dynamics,
        measurement=measurement,
        disturbances=tuple(disturbances),
        obstacles=obstacles,
        safety=safety,
        switches=switches,
        min_scale=min_scale,
        latency=latency,
    )


ROBOT_RADIUS_M = SafetySettings.follower_radius_m  # a follower's footprint (15 x 25 cm) seen as a disc; the leader's is larger
LEADER_RADIUS_M = 0.25


def _parse_obstacles(top: Table, p0: FloatArray, leader: LeaderProfile) -> tuple[Obstacle, ...]:
    """[[obstacles]]: boxes in the world frame; none may hold a robot at the start or the goal."""
    out = []
    for ot in top.tables("obstacles"):
        x, y = ot.point("center", WORKSPACE_LIMIT_M)
        size = ot.raw("size")
        if (not isinstance(size, list) or len(size) != 2
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in size)
                or not all(math.isfinite(float(c)) and 0.0 < float(c) <= 5.0 for c in size)):
            raise ot.fail("size", size, "[length, width] in (0, 5] m")
        heading = math.radians(ot.number("heading_deg", -360.0, 360.0, default=0.0, unit="deg"))
        height = ot.number("height_m", 0.0, 2.0, default=0.3, lo_open=True, unit="m")
        ot.finish()
        o = Obstacle(x, y, float(size[0]), float(size[1]), heading, height)
        box = as_array([o])
        gaps = surface_distance(p0, box)[:, 0]
        if np.any(gaps < ROBOT_RADIUS_M):
            k = int(np.argmin(gaps))
            raise ot.fail("center", [x, y], f"clear of the robots: follower {k + 1} starts"
                          f" {max(gaps[k], 0.0) * 100:.0f} cm from its surface (at least {ROBOT_RADIUS_M * 100:.0f} cm)")
        if surface_distance(np.zeros((1, 2)), box)[0, 0] < LEADER_RADIUS_M:
            raise ot.fail("center", [x, y], f"clear of the leader, which starts at the origin (at least"
                          f" {LEADER_RADIUS_M * 100:.0f} cm from its surface)")
        if isinstance(leader, GoalProfile) and surface_distance(np.array([leader.goal]), box)[0, 0] < LEADER_RADIUS_M:
            raise ot.fail("center", [x, y], f"clear of the leader's goal {list(leader.goal)} (at least"
                          f" {LEADER_RADIUS_M * 100:.0f} cm)")
        out.append(o)
    return tuple(out)


def _parse_safety(top: Table) -> SafetySettings | None:
    """[safety]: present means the filter runs (core.control.safety); its distances."""
    if not top.has("safety"):
        top.used.add("safety")
        return None
    t = top.table("safety", optional=False)
    if not t.flag("enabled", True):
        t.finish()
        return None
    d = t.bounded("min_distance_m", SAFETY_DISTANCE, default=number_default("safety_distance_m"))
    margin = t.number("obstacle_margin_m", 0.0, 1.0, default=0.10, unit="m")
    t.finish()
    return SafetySettings.for_distance(d, obstacle_margin_m=margin)


def _parse_switches(formation: Table, n: int, duration: float, seed: int) -> tuple[tuple[float, FloatArray], ...]:
    """Formation switches: [[formation.switches]] (at_s, preset) in order, or ``switch_every_s``:
    a preset drawn at random (from the scenario's seed) every so many seconds."""
    out: list[tuple[float, FloatArray]] = []
    for st in formation.tables("switches"):
        at = st.number("at_s", 0.0, duration, unit="s")
        name = st.text("preset", choices=FORMATION_PRESETS)
        st.finish()
        if out and at <= out[-1][0]:
            raise st.fail("at_s", at, f"later than the switch before ({out[-1][0]:g} s)")
        out.append((at, formation_preset(name, n)))
    if formation.has("switch_every_s"):
        if out:
            raise formation.fail("switch_every_s", formation.raw("switch_every_s"),
                                 "absent when [[formation.switches]] are listed (one or the other)")
        every = formation.number("switch_every_s", 1.0, 3600.0, unit="s")
        rng = np.random.default_rng(seed + 7)
        k = 1
        while k * every < duration:
            out.append((k * every, formation_preset(FORMATION_PRESETS[int(rng.integers(len(FORMATION_PRESETS)))], n)))
            k += 1
    else:
        formation.used.add("switch_every_s")
    return tuple(out)
