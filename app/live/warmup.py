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

This module sits below the loop (app.live.loop calls :func:`warm_up` as its run() starts): it
knows a loop only by :class:`Warmable`, what the warm-up asks of one, and the loop makes its
own throwaway twin on a world its own world makes (app.contracts.World.simulated). Filling the
cache for every kind of world `run` makes (`python -m app.services.warmup`, a step of `make
test`) builds worlds, so it is a composition root's: app.services.warmup.
"""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING, Any, Protocol

from app.params import Params, ParamsStore, default_slots

if TYPE_CHECKING:  # for the types alone: importing them loads kernels, and `python -m app.services.warmup`
    # refuses a mistaken argument before any kernel loads
    from core.obstacles import Obstacle

    from app.contracts import Rig

MAX_TICKS = 900  # a cold cache: the pipeline's start-up is done well within this (30 s simulated)
AFTER_READY_TICKS = 30  # ticks of tracking once the start-up is over (its kernels differ)
WARM_LINE = "warmed the loop's kernels"  # the start of the one line said when something compiled
_warmed: set[str] = set()  # kinds of world warmed in this process (a second loop needs no warm-up)


class Warmable(Protocol):
    """What the warm-up asks of a loop (app.live.loop.ServiceLoop is one)."""

    store: ParamsStore

    @property
    def camera(self) -> Rig | None:
        """The rig the loop sees through (None: the simulator's poses)."""
        ...

    @property
    def obstacles(self) -> tuple[Obstacle, ...]: ...

    @property
    def stopping(self) -> bool: ...

    @property
    def ready(self) -> bool:
        """The team's start-up is over (the pipeline tracks every follower)."""
        ...

    def throwaway(self, store: ParamsStore, camera: Rig | None, obstacles: tuple[Obstacle, ...]) -> Warmable:
        """A loop like this one (rate, seed, dynamics) on a simulated world of its own."""
        ...

    def tick(self) -> object: ...

    def solver(self, params: Params) -> str:
        """The barrier QP's solver this loop uses with ``params``."""
        ...

    def close_team(self) -> None: ...


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


def warm_up(loop: Warmable, say: bool = True) -> float:
    """Step a throwaway world like ``loop``'s until every kernel it reaches has run once; returns the
    seconds it took (0.0 when this process had warmed such a world already). On a cold cache, one
    line says so and how long it took."""
    from core.control.safety import load_solver
    from core.obstacles import Obstacle

    camera = loop.camera
    kind = "vision" if camera is not None else "truth"
    if kind in _warmed:
        return 0.0
    t0 = time.perf_counter()
    if camera is not None and camera[0].model is None:  # a real rig: the synthetic camera runs the same pipeline
        from app.files import DEFAULT_CONFIG
        from app.live.config import load_service_config
        from app.params import MAX_FOLLOWERS

        camera = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS).camera()
    n = loop.store.get().n_followers
    store = ParamsStore(Params(n_followers=n, slots=default_slots(n), leader_mode="goal", goal=(0.0, 4.0),
                               leader_speed_mps=0.05, safety=True))
    box = (Obstacle(1.2, 1.5, 0.3, 0.3),)  # beside the path: the scan sees it, navigation plans around it
    shadow = loop.throwaway(store, camera, loop.obstacles or box)
    after = 0
    before = compiled()
    try:
        for _ in range(MAX_TICKS):
            if loop.stopping:  # asked to stop while warming: the loop ends at once
                break
            shadow.tick()
            if shadow.ready:
                after += 1
                if after >= AFTER_READY_TICKS:
                    break
    finally:
        shadow.close_team()
    # the throwaway world's followers may never come close enough for the barrier QP, whose library
    # and solver are imported at the first solve
    load_solver(shadow.solver(store.get()))
    took = time.perf_counter() - t0
    made = compiled() - before  # compiled, not loaded from numba's cache
    _warmed.add(kind)
    if made and say:
        print(f"omniformation: {WARM_LINE} ({made} compiled) in {took:.1f} s, before the loop's clock started"
              " (numba's cache keeps them)", flush=True)
    return took
