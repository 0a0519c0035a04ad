"""`omniformation arena`'s composition: a fleet's shared world on its bus (app.fleet.arena), its
stepping thread and, with ``--radio``, the emulated radio's; stopped, joined and closed through
one ExitStack, its summary taken after the last step. The command line checks the arguments,
prints the status lines and writes the summary file."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from app.files import UserError
from app.keys import root

if TYPE_CHECKING:
    from app.fleet.arena import Arena
    from app.fleet.security import FleetKeys
    from core.fleet import FleetScenario


@dataclass(frozen=True)
class ArenaPlan:
    """`arena` as checked: the scenario, the fleet's name, the bus, the radio's options."""

    scenario: FleetScenario
    fleet: str
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    keys: FleetKeys | None = None
    radio: bool = False
    radio_drop: float = 0.0
    radio_delay_s: float = 0.0
    radio_auth: Any = None  # the robots' radio keys (app.backends.emulator.robot_auth), None: the open key


@dataclass
class RunningArena:
    """The arena, stepping: ``stop`` ends it; ``summary`` is filled once it stopped."""

    arena: Arena
    stop: threading.Event
    summary: dict[str, Any]


@contextlib.contextmanager
def run_arena(plan: ArenaPlan) -> Iterator[RunningArena]:
    """The arena on the bus (one per fleet: another alive there is one line), stepping on its own
    thread (and the radio on another) until ``stop`` is set or the block ends."""
    from app.fleet.arena import Arena
    from app.services.bus import open_bus

    with contextlib.ExitStack() as stack:
        session = open_bus(list(plan.listen), list(plan.connect), f"arena {plan.fleet}", plan.keys)
        stack.callback(session.close)
        replies = session.liveliness().get(f"{root(plan.fleet)}/arena/alive", timeout=1.0)
        if any(getattr(r, "ok", None) is not None for r in replies):
            raise UserError(f"fleet {plan.fleet}: an arena runs on this bus already; one world per fleet")
        arena = Arena(plan.scenario, session, plan.fleet, radio=plan.radio, radio_drop=plan.radio_drop,
                      radio_delay_s=plan.radio_delay_s, radio_auth=plan.radio_auth)
        stack.callback(arena.close)
        running = RunningArena(arena, threading.Event(), {})
        stack.callback(_summarise, running, plan.fleet)
        stepper = threading.Thread(target=arena.run, args=(running.stop,), name="omniformation-arena", daemon=True)
        stepper.start()
        stack.callback(stepper.join, 10.0)
        if arena.radio is not None:
            carrier = threading.Thread(target=arena.radio.run, args=(running.stop,), name="omniformation-radio",
                                       daemon=True)
            carrier.start()
            stack.callback(carrier.join, 5.0)
        stack.callback(running.stop.set)
        yield running


def _summarise(running: RunningArena, fleet: str) -> None:
    """The arena's counts and owners after its last step (before it closes)."""
    arena = running.arena
    running.summary.update({"fleet": fleet, "t": round(arena.t, 3), **vars(arena.counts), "owners": list(arena.owners),
                            "alive": sorted(arena.alive), "ever_alive": sorted(arena.ever_alive),
                            "two_owners": arena.two_owners})
    if arena.radio is not None:
        running.summary["radio"] = arena.radio.summary()
