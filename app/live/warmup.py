"""Compile and warm every kernel the loop can reach before its clock starts.

Why: numba compiles a kernel on its first call (core.jit). On a fresh clone, whose
cache on disk is empty, that first call came inside a paced tick and the loop fell
seconds behind its schedule (hundreds of ticks skipped at start, more each time the
vision pipeline entered a new phase). Here a throwaway simulated world of the same
kind (the same team size; the synthetic camera when the loop sees through a camera,
the simulator's poses otherwise) is stepped with nobody watching and nothing sent to
any robot: through the pipeline's start-up into tracking, with the safety filter on,
the goal mode's navigation and a box in view (the free-space scan). Its store, team
and feedback are its own; the real loop's world is untouched. Then one barrier QP is
solved with the loop's solver, whose library is imported at its first solve.

The whole sequence runs on every start, not only when its first ticks compile something: a
cache that is warm for the first tick's kernels may be cold for a later phase's (one module's
cache removed or invalidated by an edit), and a kernel first used after the start-up then
compiled inside a paced tick (seconds of skipped ticks). On a warm cache the sequence loads
every kernel from disk (about 1-2 s with the synthetic camera, a fraction of that without);
one line is printed only when something was compiled.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import TYPE_CHECKING, Any

from app.params import Params, ParamsStore, default_slots

if TYPE_CHECKING:
    from app.live.loop import ServiceLoop

log = logging.getLogger(__name__)

MAX_TICKS = 900  # a cold cache: the pipeline's start-up is done well within this (30 s simulated)
AFTER_READY_TICKS = 30  # ticks of tracking once the start-up is over (its kernels differ)
WARM_LINE = "warmed the loop's kernels"  # the start of the one line said when something compiled
_warmed: set[str] = set()  # kinds of world warmed in this process (a second loop needs no warm-up)


def kernels() -> list[Any]:
    """Every numba-compiled kernel of the core modules loaded now."""
    from numba.core.dispatcher import Dispatcher

    found: dict[int, Any] = {}
    # copies taken in one step (dict.copy holds the interpreter lock throughout): list(d.items()) can
    # let another thread run mid-copy, and one importing a module then broke the loop's start
    for name, module in sys.modules.copy().items():
        if not name.startswith("core.") or module is None:
            continue
        for value in vars(module).copy().values():
            if isinstance(value, Dispatcher):
                found[id(value)] = value
    return list(found.values())


def compiled() -> int:
    """How many kernel signatures this process compiled rather than loaded from numba's cache."""
    return sum(sum(fn.stats.cache_misses.values()) for fn in kernels())


def warm_up(loop: ServiceLoop, say: bool = True) -> float:
    """Step a throwaway world like ``loop``'s until every kernel it reaches has run once; returns the
    seconds it took (0.0 when this process had warmed such a world already). On a cold cache, one
    line says so and how long it took."""
    from app.live.loop import ServiceLoop
    from core.control.safety import load_solver

    camera = loop.backends.camera
    kind = "vision" if camera is not None else "truth"
    if kind in _warmed:
        return 0.0
    t0 = time.perf_counter()
    if camera is not None and camera[0].model is None:  # a real rig: the synthetic camera runs the same pipeline
        from app.files import DEFAULT_CONFIG
        from app.live.config import load_service_config
        from app.params import MAX_FOLLOWERS

        camera = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS).camera()
    from core.obstacles import Obstacle

    n = loop.store.get().n_followers
    store = ParamsStore(Params(n_followers=n, slots=default_slots(n), leader_mode="goal", goal=(0.0, 4.0),
                               leader_speed_mps=0.05, safety=True))
    box = (Obstacle(1.2, 1.5, 0.3, 0.3),)  # beside the path: the scan sees it, navigation plans around it
    shadow = ServiceLoop(store, rate_hz=loop.rate_hz, seed=loop.seed, dynamics=loop.dynamics, camera=camera,
                         obstacles=loop.backends.obstacles or box)
    after = 0
    before = compiled()
    try:
        for _ in range(MAX_TICKS):
            if loop.stopping:  # asked to stop while warming: the loop ends at once
                break
            shadow.tick()
            if shadow._world.ready:
                after += 1
                if after >= AFTER_READY_TICKS:
                    break
    finally:
        shadow.close_team()
    # the throwaway world's followers may never come close enough for the barrier QP, whose library
    # and solver are imported at the first solve
    load_solver(shadow._safety_settings(store.get()).solver)
    took = time.perf_counter() - t0
    made = compiled() - before  # compiled, not loaded from numba's cache
    _warmed.add(kind)
    if made and say:
        print(f"omniformation: {WARM_LINE} ({made} compiled) in {took:.1f} s, before the loop's clock started"
              " (numba's cache keeps them)", flush=True)
    return took


def warm_all() -> int:
    """Warm both kinds of world `run` can make (the synthetic camera's, the simulator's poses) with
    the default config, each once; how many kernel signatures were compiled, not loaded."""
    from app.files import DEFAULT_CONFIG
    from app.live.config import load_service_config
    from app.live.loop import ServiceLoop
    from app.params import MAX_FOLLOWERS

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    before = compiled()
    for camera in (config.camera(), None):
        n = 3  # run's default team; a kernel's compiled code does not depend on the team's size
        loop = ServiceLoop(ParamsStore(Params(n_followers=n, slots=default_slots(n))), dynamics=config.dynamics,
                           camera=camera)
        try:
            warm_up(loop, say=False)
        finally:
            loop.close_team()
    return compiled() - before


if __name__ == "__main__":  # `python -m app.live.warmup`: fill numba's cache once, e.g. before a test suite
    import sys

    if sys.argv[1:]:  # it warms what `run` reaches with the default config: there is nothing to choose
        print(f"python -m app.live.warmup: takes no arguments (got {' '.join(sys.argv[1:])!r})", file=sys.stderr)
        sys.exit(2)
    t0 = time.perf_counter()
    made = warm_all()
    print(f"omniformation: {made} kernel signatures compiled into numba's cache in {time.perf_counter() - t0:.1f} s"
          if made else "omniformation: numba's cache already holds every kernel the loop reaches", flush=True)
