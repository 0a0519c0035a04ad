"""Frozen value types shared across core and app: gains, commands, poses.

Arrays are vectorised over followers: positions (n, 2) in metres, headings (n,)
in radians, both in the leader frame unless a name says otherwise.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.intp]


def float_rows(x: Any, shape: tuple[int, ...]) -> FloatArray:
    """``x`` as a C-contiguous float64 array of ``shape``, broadcast if it is smaller; no
    copy (and no broadcasting machinery) when it already is one."""
    a = np.asarray(x, dtype=np.float64)
    if a.shape != shape:
        a = np.broadcast_to(a, shape)
    return np.ascontiguousarray(a)


def numbers_in_field_order(obj: Any) -> FloatArray:
    """A frozen dataclass of numbers as a float array in field order, for compiled kernels:
    made on first use and kept on the object (it cannot change), read-only."""
    cached = obj.__dict__.get("_numbers_in_field_order")
    if cached is None:
        cached = np.array([float(getattr(obj, f.name)) for f in dataclasses.fields(obj)])
        cached.flags.writeable = False
        object.__setattr__(obj, "_numbers_in_field_order", cached)
    return cached


class Image(Protocol):
    """A BGR image (H, W, 3) uint8: a numpy array, or an image that makes its pixels when
    looked at (core.camera.render.SyntheticFrame). Either gives a numpy array for a
    rectangle, ``img[y0:y1, x0:x1]``, and for all of itself, ``np.asarray(img)``; code that
    needs only rectangles asks only for those."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    def __getitem__(self, key: Any) -> Any: ...

    def __array__(self, dtype: Any = ..., /, *, copy: Any = ...) -> NDArray[Any]: ...


@dataclass(frozen=True)
class Bound:
    """The allowed range of one tunable number, with its unit and meaning for people."""

    lo: float
    hi: float
    unit: str
    meaning: str
    lo_inclusive: bool = False

    def check(self, name: str, value: float) -> None:
        """Raise ValueError naming the key, the value and the allowed range."""
        ok = math.isfinite(value) and (
            (value >= self.lo if self.lo_inclusive else value > self.lo) and value <= self.hi
        )
        if not ok:
            lo_br = "[" if self.lo_inclusive else "("
            raise ValueError(
                f"{name} = {value!r}: must be a number in {lo_br}{self.lo:g}, {self.hi:g}] {self.unit}"
            )

    def clamp(self, value: float) -> float:
        """Nearest allowed value (used where a person's input is clamped, not refused)."""
        if not math.isfinite(value):
            return self.lo if self.lo_inclusive else self.lo + 1e-9
        lo = self.lo if self.lo_inclusive else math.nextafter(self.lo, math.inf)
        return min(max(value, lo), self.hi)


# Ranges of the controller parameters. The meanings follow paper §2.2 and §2.4.
GAIN_BOUNDS: dict[str, Bound] = {
    "k_f1": Bound(0.0, 1.0, "m/s", "eq. 4: k_f1/a is the gain for small position errors"),
    "k_f2": Bound(0.0, 1.0, "m/s", "eq. 4: k_f1 + k_f2 is the saturation value of the pose term", lo_inclusive=True),
    "a": Bound(0.0, 2.0, "m", "eq. 4: error (m) at which the pose term starts to saturate"),
    "k_w1": Bound(0.0, 5.0, "rad/s", "eq. 12: saturation value of the heading term"),
    "k_w2": Bound(0.0, 20.0, "1/rad", "eq. 12: how fast the heading term reaches saturation"),
    "v_max": Bound(0.0, 2.0, "m/s", "hard limit on every commanded linear speed"),
    "w_max": Bound(0.0, 10.0, "rad/s", "hard limit on every commanded angular speed"),
    "accel_v_max": Bound(0.0, 20.0, "m/s^2", "hard limit on the change of commanded linear speed"),
    "accel_w_max": Bound(0.0, 100.0, "rad/s^2", "hard limit on the change of commanded angular speed"),
    "tau_ar": Bound(0.0, 5.0, "s", "low-pass time constant of the reference-angle rate in eq. 11 (0 = raw)", lo_inclusive=True),
}


@dataclass(frozen=True)
class Gains:
    """Controller gains (eq. 4, eq. 12) and hard command limits, validated on construction.

    Defaults and why:
      * k_f1 = 0.10 m/s, a = 0.10 m: small-error gain k_f1/a = 1/s, a position
        error halves in about 0.7 s, well inside the followers' abilities.
      * k_f2 = 0.05 m/s: the pose term saturates at 0.15 m/s, so with the
        leader's 0.06 m/s the followers need at most about 0.25 m/s.
      * k_w1 = 0.5 rad/s: as in the paper's fig. 5.
      * k_w2 = 3.0: fig. 5 shows k_w2 = 1, but tanh^3 is flat near zero and a
        small heading error then decays slowly, leaving a position error of
        about |zeta_r| sin(a~) / (k_f1/a). On paper_simulation (ideal
        followers, t >= 30 s) the largest error is 1.6 cm with k_w2 = 1,
        0.98 cm with 2 (the peak is the step of w_l at t = 100 s) and 0.74 cm
        with 3; with tau_ar = 0.2 s it drops to 0.35 cm.
      * v_max = 0.3 m/s, w_max = 2.0 rad/s: what a 15 x 25 cm follower with
        small gear motors (the paper's) can do; always enforced.
      * accel_v_max = 0.5 m/s^2, accel_w_max = 5 rad/s^2: keep commands
        smooth for the motors; always enforced.
      * tau_ar = 0.2 s: eq. 11's reference-angle rate is the wrapped change
        of a_r over dt, low-passed. Raw (tau_ar = 0, as printed), measurement
        noise is amplified by 1/dt straight into w: with 3 mm / 1 deg noise at
        30 Hz the error RMS after the transient is 1.3-1.6 cm raw and
        0.2-0.3 cm filtered, and the w command's spread halves.
    """

    k_f1: float = 0.10
    k_f2: float = 0.05
    a: float = 0.10
    k_w1: float = 0.5
    k_w2: float = 3.0
    v_max: float = 0.30
    w_max: float = 2.0
    accel_v_max: float = 0.5
    accel_w_max: float = 5.0
    tau_ar: float = 0.2

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{f.name} = {value!r}: must be a number")
            GAIN_BOUNDS[f.name].check(f.name, float(value))

    def replace(self, **changes: Any) -> "Gains":
        """A new validated Gains with some values changed."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def as_array(self) -> FloatArray:
        """The gains in field order (see GAIN_INDEX), for compiled kernels."""
        return numbers_in_field_order(self)


GAIN_INDEX: dict[str, int] = {f.name: i for i, f in enumerate(dataclasses.fields(Gains))}


@dataclass(frozen=True)
class Commands:
    """Per-follower velocity commands: v (n,) m/s, w (n,) rad/s; ``observed_at``: the
    monotonic time of the observation they were computed from (NaN: not said), which a link
    that can (protocol 2's DRIVE) sends along so that a robot refuses a command from an old one."""

    v: FloatArray
    w: FloatArray
    observed_at: float = float("nan")

    @staticmethod
    def zeros(n: int) -> "Commands":
        return Commands(np.zeros(n), np.zeros(n))
