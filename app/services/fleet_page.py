"""`omniformation fleet`: one page for a whole fleet (paper §6).

Everything comes from the bus (docs/fleet-protocol.md): every leader's state, events and
liveliness, and the arena's truth when there is one. One 3D scene shows the arena's robots
(each in its marker's hue) and leaders, and each leader's own estimates (drawn in the world
through the leader's pose); a panel per leader shows its errors and takes its controls
(STOP, release, gains, leader motion), sent to that leader's command key; *STOP every leader*
goes to the fleet-wide key. A leader takes changes other than STOP only when its operator
started it with ``--fleet-control``; a refusal comes back as its event and is shown.

This module is the bus side (subscriptions, decoding, sending); the widgets are
app.dashboard.fleet_view's. The page is refreshed ten times a second from the newest messages
(the bus is never waited on). With ``recorder`` every message also goes into one MCAP, a
channel per leader.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import viser

from app import wire
from app.backends.arena import read_truth
from app.dashboard.fleet_view import FleetPage, FleetSnapshot, LeaderPanel
from app.dashboard.widgets import on_page_thread
from app.files import UserError, bind_error
from app.fleet.bridge import read_state
from app.keys import root

if TYPE_CHECKING:
    from app.fleet.security import FleetKeys
    from app.services.foxglove_attach import FoxglovePlan

REFRESH_S = 0.1
# a state arriving while the page redraws waited up to the GIL's 5 ms switch interval for its callback
# (the bench's p99 was 4.4-5.0 ms): `omniformation fleet` sets app.realtime's SWITCH_INTERVAL_S


class FleetSink(Protocol):
    """Where the page also hands every bus message: the fleet recording (FleetRecorder),
    Foxglove live, or both."""

    def write(self, topic: str, msg: dict[str, Any]) -> None: ...

    def status(self) -> str: ...


class FleetView:
    """The fleet page on one viser server, fed from the bus: the widgets are app.dashboard.fleet_view's."""

    def __init__(self, server: viser.ViserServer, session: Any, fleet: str,
                 recorder: FleetSink | None = None, allow_viewer: Callable[..., None] | None = None) -> None:
        """``allow_viewer``: marks the controls a view-only client may press (the STOPs; the gate's)."""
        import zenoh

        self.server = server
        self.session = session
        self.fleet = fleet
        self.recorder = recorder
        self._zenoh = zenoh
        self._lock = threading.Lock()
        self.truth: dict[str, Any] | None = None
        self.states: dict[str, tuple[float, dict[str, Any]]] = {}  # id -> (monotonic time received, state)
        self.alive: set[str] = set()
        self.events: deque[str] = deque(maxlen=12)
        self.received = 0
        self.malformed = 0
        self.latencies: deque[float] = deque(maxlen=2000)  # s from a state's "sent" (when given) to here
        self.watchdog_stops = 0  # the robots' moves into their watchdog's hold, in the truths seen here
        self._held: list[bool] | None = None  # the last truth's watchdog flags
        self.page = FleetPage(server, self.send, self.send_all_stop, self.hand_over, allow_viewer)
        self._subs = [
            session.declare_subscriber(f"{root(fleet)}/arena/truth", self._on_truth),
            session.declare_subscriber(f"{root(fleet)}/leader/*/state", self._on_state),
            session.declare_subscriber(f"{root(fleet)}/leader/*/events", self._on_event),
            session.declare_subscriber(f"{root(fleet)}/arena/events", self._on_event),
            session.liveliness().declare_subscriber(f"{root(fleet)}/alive/*", self._on_alive, history=True),
        ]
        # the page's own token, once it hears the fleet: whoever sees it knows the page's subscribers are
        # declared (with the fleet's keys the page writes this, commands and handovers only)
        self._token = session.liveliness().declare_token(f"{root(fleet)}/page/alive")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._refresh_loop, name="omniformation-fleet-page", daemon=True)
        self._thread.start()

    @property
    def panels(self) -> dict[str, LeaderPanel]:
        return self.page.panels

    @property
    def hand_robot(self) -> Any:
        return self.page.hand_robot

    @property
    def hand_to(self) -> Any:
        return self.page.hand_to

    # -- in ------------------------------------------------------------------------------------
    def _decode(self, sample: Any) -> dict[str, Any] | None:
        try:
            msg = wire.decode(sample.payload.to_bytes())
        except wire.BadMessage:
            msg = None
        if not isinstance(msg, dict):
            with self._lock:
                self.malformed += 1
            return None
        return msg

    def _on_truth(self, sample: Any) -> None:
        msg = self._decode(sample)
        try:
            msg = read_truth(msg) if msg is not None else None
        except wire.BadMessage:
            with self._lock:
                self.malformed += 1
            msg = None
        if msg is None:
            return
        dog = msg.get("watchdog")
        with self._lock:
            self.truth = msg
            if isinstance(dog, list):  # a stop is a robot's move into its watchdog's hold
                held = [on is True for on in dog]
                if self._held is not None and len(self._held) == len(held):
                    self.watchdog_stops += sum(now and not was for was, now in zip(self._held, held))
                self._held = held
        if self.recorder is not None:
            self.recorder.write("arena/truth", msg)

    def _on_state(self, sample: Any) -> None:
        now, arrived = time.monotonic(), time.time()
        msg = self._decode(sample)
        leader = str(sample.key_expr).split("/")[-2]
        try:
            msg = read_state(msg) if msg is not None else None
        except wire.BadMessage:
            with self._lock:
                self.malformed += 1
            msg = None
        if msg is None:
            return
        sent = msg.get("sent")
        with self._lock:
            self.states[leader] = (now, msg)
            self.received += 1
            if isinstance(sent, (int, float)):
                self.latencies.append(arrived - float(sent))
        if self.recorder is not None:
            self.recorder.write(f"{leader}/state", msg)

    def _on_event(self, sample: Any) -> None:
        msg = self._decode(sample)
        if msg is None:
            return
        parts = str(sample.key_expr).split("/")
        who = parts[-2] if parts[-3] == "leader" else "arena"
        with self._lock:
            self.events.append(f"{who}: {msg.get('kind', '?')} — {str(msg.get('detail', ''))[:160]}")
        if self.recorder is not None:
            self.recorder.write(f"{who}/events", msg)

    def _on_alive(self, sample: Any) -> None:
        leader = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                self.alive.add(leader)
            else:
                self.alive.discard(leader)
            self.events.append(f"{leader}: {'joined' if sample.kind == self._zenoh.SampleKind.PUT else 'token lost'}")

    # -- out -----------------------------------------------------------------------------------
    def send(self, leader_id: str, changes: dict[str, Any]) -> None:
        self.session.put(f"{root(self.fleet)}/leader/{leader_id}/cmd",
                         json.dumps({"set": changes, "from": "fleet-dashboard"}))

    def hand_over(self, robot: str, to: str) -> str:
        """Ask the arena to give ``robot`` to leader ``to`` (e.g. back to a leader that came back
        empty-handed); the answer goes to the events and is returned."""
        if robot == "-" or to == "-":
            answer = "hand over: pick a robot and a leader first"
        else:
            answer = f"hand over {robot} to {to}: no arena answered"
            payload = json.dumps({"robot": robot, "to": to, "from": "fleet-dashboard"})
            for reply in self.session.get(f"{root(self.fleet)}/arena/handover", payload=payload, timeout=3.0):
                try:
                    got = json.loads(reply.ok.payload.to_bytes())
                except (AttributeError, ValueError, TypeError):
                    continue
                answer = (f"hand over {robot} to {to}: " + ("done" if got.get("granted") else
                                                             f"refused ({got.get('why', '?')})"))
        with self._lock:
            self.events.append(answer)
        return answer

    def send_all_stop(self) -> None:
        self.session.put(f"{root(self.fleet)}/all/cmd", json.dumps({"set": {"stop": True}, "from": "fleet-dashboard"}))

    # -- the page ------------------------------------------------------------------------------
    def _refresh_loop(self) -> None:
        while not self._stop.wait(REFRESH_S):
            try:
                on_page_thread(self.server, self.refresh)  # viser's thread: widgets.on_page_thread says why
            except Exception:
                import logging

                logging.getLogger(__name__).exception("fleet page refresh failed")

    def snapshot(self) -> FleetSnapshot:
        """What the bus gave so far, taken at once."""
        with self._lock:
            return FleetSnapshot(self.fleet, self.truth, dict(self.states), set(self.alive), list(self.events),
                                 watchdog_stops=self.watchdog_stops, extra="" if self.recorder is None else self.recorder.status(), now=time.monotonic())

    def refresh(self) -> None:
        self.page.show(self.snapshot())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        for sub in self._subs:
            sub.undeclare()
        self._token.undeclare()


@dataclass(frozen=True)
class FleetPagePlan:
    """`omniformation fleet` as checked: the bus, where to serve, the recording and Foxglove."""

    fleet: str
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    keys: FleetKeys | None = None
    host: str = "127.0.0.1"
    port: int = 8090
    token: str | None = None
    viewer_token: str | None = None
    record: Path | None = None
    foxglove: FoxglovePlan | None = None


@dataclass
class FleetPageRunning:
    """The fleet page, served: its view of the bus, its gate (the URLs), its recorder."""

    view: FleetView
    gate: Any
    recorder: Any


@contextlib.contextmanager
def serve_fleet_page(plan: FleetPagePlan, say: Callable[..., None]) -> Iterator[FleetPageRunning]:
    """On the bus, the page served behind its gate, the fleet recorded and given to Foxglove as the
    plan asks; all of it closed on the way out through one ExitStack (the view first, the bus last)."""
    import sys

    from app.dashboard.gate import quietly, serve_gated
    from app.realtime import SWITCH_INTERVAL_S
    from app.recording.fleet import FleetRecorder
    from app.services.bus import open_bus
    from app.services.foxglove_attach import serve_fleet

    with contextlib.ExitStack() as stack:
        session = open_bus(list(plan.listen), list(plan.connect), f"fleet {plan.fleet}", plan.keys)
        stack.callback(session.close)
        try:
            server, gate = serve_gated(plan.host, plan.port, plan.token, plan.viewer_token)
        except OSError as exc:
            raise UserError(bind_error(plan.host, plan.port, exc)) from None
        stack.callback(quietly, server.stop)
        stack.callback(gate.close)
        gate.page_kind = "fleet"
        recorder = None
        if plan.record is not None:
            try:
                recorder = FleetRecorder(plan.record)
            except OSError as exc:
                raise UserError(f"{plan.record}: cannot record: {exc.strerror or exc}") from None
            stack.callback(recorder.close)
        sys.setswitchinterval(SWITCH_INTERVAL_S)  # states reach the page's callbacks sooner (REFRESH_S says why)
        sink, fox = serve_fleet(plan.foxglove, recorder, say)
        if fox is not None:
            stack.callback(fox.close)
        view = FleetView(server, session, plan.fleet, sink, allow_viewer=gate.filter.allow_viewer)
        stack.callback(view.close)
        yield FleetPageRunning(view, gate, recorder)
