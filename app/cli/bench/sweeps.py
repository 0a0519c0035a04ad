"""Gain sweeps: their time, and the live loop's rate while the page's worker sweeps."""

from __future__ import annotations

from collections.abc import Callable
from app.cli.bench.family import Family


def bench_sweeps() -> tuple[float, float, float, float, int]:
    """Seconds for a 5 x 5 sweep on experiment1 (truth, then vision), and the live loop's rate
    (vision in the loop, as `make run`) before and while the page's worker process sweeps."""
    import time as _time

    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_scenario, load_synthetic_rig
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service
    from app.live.sweep import run_sweep
    from core.control.tuning import StepTest, parse_gain_range
    from core.sim.sweep import settled_start

    scenario = load_scenario("experiment1")
    base = settled_start(scenario)
    test = StepTest("offset", 0, 0.10)
    ranges = [parse_gain_range("k_w2=1:4:5"), parse_gain_range("k_f1=0.05:0.3:5")]
    twist = (scenario.leader.twist(0.0)[0], 0.0)
    truth = run_sweep(base, test, twist, ranges, scenario.gains).seconds
    rig = load_synthetic_rig(SYNTHETIC_CAMERA, SYNTHETIC_CALIBRATED)
    vision = run_sweep(base.replace(rate_hz=30.0), test, twist, ranges, scenario.gains, rig).seconds

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics)
    svc.start()
    try:
        _time.sleep(3.0)
        tick0, t0 = svc.loop.tick_count, _time.monotonic()
        _time.sleep(6.0)
        alone = (svc.loop.tick_count - tick0) / (_time.monotonic() - t0)
        while svc.loop.last is None or svc.loop.last.phase != "tracking":
            _time.sleep(0.2)
        tuning = svc.dashboard.tuning
        assert tuning is not None
        why = tuning.start_sweep("vision")
        if why:
            raise RuntimeError(f"the sweep did not start: {why}")
        tick0, t0 = svc.loop.tick_count, _time.monotonic()
        result = svc.sweeps.wait(600)
        during = (svc.loop.tick_count - tick0) / (_time.monotonic() - t0)
    finally:
        svc.close()
    return truth, vision, alone, during, len(result.gains) if result is not None else 0


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """A 5 x 5 sweep's time, and the live loop's rate while the page's worker sweeps."""
    truth_s, vision_s, alone_hz, sweeping_hz, points = bench_sweeps()
    print_fn(f"5 x 5 sweep (k_w2 x k_f1, offset step, experiment1): truth feedback {truth_s:.1f} s (target <= 10 s),"
             f" vision in the loop {vision_s:.1f} s (target <= 120 s)")
    print_fn(f"live loop at 30 Hz (vision in the loop) while the page's worker sweeps ({points} points, vision):"
             f" {sweeping_hz:.2f} Hz ({(sweeping_hz / 30 - 1) * 100:+.1f} % of 30; target within 1 %);"
             f" {alone_hz:.2f} Hz before it")
    return {"sweep_truth_s": truth_s, "sweep_vision_s": vision_s, "loop_hz_before_sweep": alone_hz,
            "loop_hz_during_sweep": sweeping_hz}


FAMILY = Family('sweeps', run_family, "a 5 x 5 gain sweep's time, and the live loop's rate while the page's worker sweeps",
                default=False, order=20)
