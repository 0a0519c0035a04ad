"""Fill numba's cache with every kernel the loop reaches in the worlds `run` makes with the
default config: `python -m app.services.warmup`, a step of `make test` (the suite's first
processes would otherwise compile the same kernels side by side).

The warm-up itself (why, and what it steps) is app.live.warmup's, below the loop, which runs it
as its run() starts; this composition root only builds the two kinds of world and their loops.
"""

from __future__ import annotations

import sys
import time

from app.live.warmup import compiled, warm_up
from app.params import Params, ParamsStore, default_slots


def warm_all() -> int:
    """Warm both kinds of world `run` can make (the synthetic camera's, the simulator's poses) with
    the default config, each once; how many kernel signatures were compiled, not loaded."""
    # here, not above: a mistaken argument is refused before any kernel loads
    from app.backends.world import Backends
    from app.files import DEFAULT_CONFIG
    from app.live.config import load_service_config
    from app.live.loop import ServiceLoop
    from app.params import MAX_FOLLOWERS

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    before = compiled()
    for camera in (config.camera(), None):
        n = 3  # run's default team; a kernel's compiled code does not depend on the team's size
        loop = ServiceLoop(ParamsStore(Params(n_followers=n, slots=default_slots(n))),
                           Backends(dynamics=config.dynamics, camera=camera))
        try:
            warm_up(loop, say=False)
        finally:
            loop.close_team()
    return compiled() - before


if __name__ == "__main__":  # `python -m app.services.warmup`: fill numba's cache once, e.g. before a test suite
    if sys.argv[1:]:  # it warms what `run` reaches with the default config: there is nothing to choose
        print(f"python -m app.services.warmup: takes no arguments (got {' '.join(sys.argv[1:])!r})", file=sys.stderr)
        sys.exit(2)
    t0 = time.perf_counter()
    made = warm_all()
    print(f"omniformation: {made} kernel signatures compiled into numba's cache in {time.perf_counter() - t0:.1f} s"
          if made else "omniformation: numba's cache already holds every kernel the loop reaches", flush=True)
