"""The study file: what it accepts, what it refuses in one line, and points and seeds that do not
depend on the order runs are made in."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from core.config import ConfigError
from core.study.point import METRICS, run_point
from core.study.spec import ScenarioSource, evaluate_objective, parse_study, point_key, run_seed, scenario_for

SCENARIOS = Path(__file__).resolve().parents[3] / "static_config" / "scenarios"


def load(name: str) -> ScenarioSource:
    path = SCENARIOS / f"{name}.toml"
    if not path.exists():
        raise ConfigError(f"scenario {name!r}: no such scenario")
    return ScenarioSource(name, path.read_text(), f"{name}.toml")


BASE = """
[study]
scenario = "experiment1"
duration_s = 4.0
seed = 1
replicates = 2
"""


def parse(text: str):
    return parse_study(text, "s.toml", load)


def test_grid_and_sample_cross_and_enumerate() -> None:
    spec = parse(BASE + """
[grid]
"gains.k_f1" = [0.1, 0.2, 0.3]
"measurement.position_noise_m" = {lo = 0.0, hi = 0.01, n = 3}
[sample]
n = 4
"latency.camera_ms" = {lo = 0.0, hi = 150.0}
""")
    assert spec.shape == (3, 3, 4) and spec.points == 36 and spec.runs == 72
    pts = [spec.point(k) for k in range(spec.points)]
    assert [p["gains.k_f1"] for p in pts[:4]] == [0.1] * 4
    assert pts[4]["measurement.position_noise_m"] == pytest.approx(0.005)
    cams = {p["latency.camera_ms"] for p in pts}
    assert len(cams) == 4 and all(0.0 <= c <= 150.0 for c in cams)
    keys = {point_key(p) for p in pts}
    assert len(keys) == 36
    again = parse(spec.text)  # the same file: the same sample, the same keys
    assert [point_key(again.point(k)) for k in range(36)] == [point_key(p) for p in pts]


def test_point_key_and_seed_depend_on_values_not_order() -> None:
    a = {"gains.k_f1": 0.2, "latency.camera_ms": 50.0}
    b = {"latency.camera_ms": 50.0, "gains.k_f1": 0.2}
    assert point_key(a) == point_key(b)
    assert point_key(a) != point_key({**a, "gains.k_f1": 0.2000001})
    seeds = {run_seed(1, point_key(a), r) for r in range(50)}
    assert len(seeds) == 50 and all(0 <= s < 2**32 for s in seeds)
    assert run_seed(1, point_key(a), 3) == run_seed(1, point_key(b), 3) != run_seed(2, point_key(a), 3)


def test_a_point_is_the_scenario_with_its_values() -> None:
    spec = parse(BASE + '[grid]\n"gains.k_f1" = [0.25]\n"team.followers" = [4]\n"start.offset_m" = [0.5]\n'
                 '"start.bearing_deg" = [0.0]\n')
    sc = scenario_for(spec, spec.scenarios[0], spec.point(0), seed=77)
    assert sc.gains.k_f1 == 0.25 and sc.seed == 77 and sc.duration_s == 4.0 and sc.n == 4
    np.testing.assert_allclose(sc.initial_p, sc.slots[:4] + [0.5, 0.0])
    np.testing.assert_allclose(sc.initial_a, math.pi / 2)


@pytest.mark.parametrize("body, says", [
    ('[grid]\n"gains.k_f9" = [0.1]\n', r"gains.k_f9 is not a known key"),
    ('[grid]\n"gains.k_f1" = [0.1, 5.0]\n', r"\"gains.k_f1\" = 5 does not fit experiment1: gains.k_f1 = 5.0: must be"),
    ('[grid]\n"gains.k_f1" = ["a"]\n', r"\"gains.k_f1\" value = 'a': must be a finite number"),
    ('[grid]\n', r"\[grid\] is empty"),
    ('[grid]\n"gains.k_f1" = []\n', r"= \[\]: empty"),
    ('[grid]\n"gains.k_f1" = {lo = 0.3, hi = 0.1, n = 3}\n', r"hi = 0.1: must be >= lo"),
    ('[grid]\n"team.followers" = [1, 9]\n', r"team.followers\" = 9: must be in \[1, 8\]"),
    ('[grid]\n"team.size" = [2]\n', r"not a known axis"),
    ('[grid]\n"seed" = [1, 2]\n', r"cannot be an axis: each run's seed"),
    ('[grid]\n"formation.slots" = [1.0]\n', r"is not a number: it cannot be an axis"),
    ('[sample]\nn = 4\n"latency.camera_ms" = {lo = 0.0, hi = 3000.0}\n', r"latency.camera_ms = 3000.0: must be"),
    ('[sample]\nn = 0\n"latency.camera_ms" = {lo = 0.0, hi = 1.0}\n', r"sample.n = 0: must be a whole number"),
    ('[optimize]\nobjective = "settling_s + __import__(\'os\')"\ntrials = 3\n"gains.k_f1" = {lo = 0.1, hi = 0.5}\n',
     r"objective"),
    ('[optimize]\nobjective = "settling_s"\ntrials = 3\n"gains.k_f1" = {lo = 0.1, hi = 0.5}\n[grid]\n"gains.a" = [0.1]\n',
     r"\[optimize\] is given with \[grid\]"),
    ('[study2]\n', r"study2 is not a known key"),
])
def test_bad_study_files_are_one_line(body: str, says: str) -> None:
    with pytest.raises(ConfigError, match=says) as err:
        parse(BASE + body)
    assert "\n" not in str(err.value) and str(err.value).startswith("s.toml: ")


def test_bad_study_table_values() -> None:
    with pytest.raises(ConfigError, match=r"study.replicates = 0: must be a whole number from 1"):
        parse(BASE.replace("replicates = 2", "replicates = 0"))
    with pytest.raises(ConfigError, match=r"study.feedback = 'lidar': must be one of truth, vision"):
        parse(BASE + 'feedback = "lidar"\n')
    with pytest.raises(ConfigError, match=r"study.duration_s = 'long'"):
        parse(BASE.replace("duration_s = 4.0", 'duration_s = "long"'))


def test_objective_is_arithmetic_over_the_metrics() -> None:
    assert evaluate_objective("settling_s + 10 * overshoot_m", {"settling_s": 3.0, "overshoot_m": 0.05}) == 3.5
    assert evaluate_objective("max(settling_s, 2) - abs(-1)", {"settling_s": 1.0}) == 1.0


def test_metrics_of_a_run_are_every_column() -> None:
    spec = parse(BASE)
    sc = scenario_for(spec, spec.scenarios[0], {}, seed=5)
    m = run_point(sc).metrics
    assert list(m) == list(METRICS)
    assert isinstance(m["converged"], bool) and m["collisions"] >= 0 and m["tracking_lost_s"] == 0.0
    assert m["max_error_m"] >= m["final_rms_m"] > 0 and m["min_distance_m"] > 0


def test_a_vision_study_varies_noise_on_the_pipelines_estimates_not_on_truth() -> None:
    with pytest.raises(ConfigError, match=r"\"measurement.position_noise_m\" is noise on ground-truth feedback.*"
                                          r"vary \"measurement.vision_position_noise_m\""):
        parse(BASE + 'feedback = "vision"\n[grid]\n"measurement.position_noise_m" = [0.0, 0.01]\n')
    spec = parse(BASE.replace("duration_s = 4.0", "duration_s = 2.0") + 'feedback = "vision"\n'
                 '[grid]\n"measurement.vision_position_noise_m" = [0.0, 0.02]\n')
    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_synthetic_rig
    from core.sim.runner import run_scenario

    rig, gamma = load_synthetic_rig(SYNTHETIC_CAMERA, SYNTHETIC_CALIBRATED)
    spread = []
    for k in range(2):
        sc = scenario_for(spec, spec.scenarios[0], spec.point(k), seed=3)
        assert sc.rate_hz == 30.0 and sc.measurement.vision_position_noise_m == spec.point(k)[
            "measurement.vision_position_noise_m"]
        run = run_scenario(sc, rig, gamma)
        seen = run.log.t >= 0
        err = np.linalg.norm(run.log.p_meas[seen] - run.log.p[seen], axis=-1)
        spread.append(float(np.nanstd(err)))
    assert spread[1] > spread[0] + 0.005  # 2 cm of noise on every estimate shows
