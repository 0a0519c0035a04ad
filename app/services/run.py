"""`run`'s composition: a checked :class:`RunPlan` in, a running live service out (the camera,
the fleet's bus and arena team, the ROS 2 node, the link and hardware rig, the service, its
recorder, Foxglove, the fleet bridge and adopter), every part closed through one ExitStack
whatever happens, the service first (it zeroes the robots). The command line (app.cli.live)
only parses and checks the arguments into the plan, prints, and calls :func:`compose`."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.files import UserError, bind_error, display_path

if TYPE_CHECKING:
    import zenoh

    from app.backends.arena import ArenaTeam
    from app.backends.hardware import HardwareTeam
    from app.contracts import FollowerLink, RealtimeFrameSource, Rig
    from app.backends.links import LinkSpec
    from app.fleet.bridge import FleetBridge, Presence
    from app.fleet.security import FleetKeys
    from app.live.config import ServiceConfig
    from app.params import Params
    from app.recording.writer import Recorder
    from app.services.foxglove_attach import FoxglovePlan
    from app.services.live import Service
    from app.services.ros2_node import Ros2Plan
    from core.config import Scenario
    from core.fleet import FleetScenario


@dataclass(frozen=True)
class RadioPlan:
    """How the followers' link authenticates its frames (docs/follower-protocol.md)."""

    radio_id: int | None = None  # this leader's number on a shared radio
    baud: int = 115200
    key: bytes | None = None  # this leader's radio key
    sender: int | None = None  # the key's radio id
    allow_unauthenticated: bool = False
    counter: Path | None = None  # the frame counter's high-water mark file

    def options(self) -> dict[str, Any]:
        """What a serial link is given to authenticate its frames."""
        from app.backends.serial_link import FrameCounter

        return {"radio_key": self.key, "sender_id": self.sender, "allow_unauthenticated": self.allow_unauthenticated,
                "counter": FrameCounter(path=self.counter) if self.counter is not None else None}


@dataclass(frozen=True)
class FleetPlan:
    """This leader on a fleet's bus (docs/fleet-protocol.md)."""

    name: str
    leader_id: str
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    keys: FleetKeys | None = None
    control: bool = False  # takes gains, formation and motion from the bus (STOP always)
    arena: str | None = None  # the fleet scenario's name it was given (--arena), for messages
    arena_radio: str = ""  # with an arena: this leader's radio's port ("": the bus drives the robots)


@dataclass
class RunPlan:
    """What the command line and the config ask for, checked before anything opens."""

    config: ServiceConfig
    scenario: Scenario | None
    fleet_scenario: FleetScenario | None
    real: bool  # a real rig: real camera, real robots, no simulator
    link: LinkSpec | None  # the followers' link to open (--link serial:...; None: the simulated team's own, or none)
    leader: LinkSpec | None  # the leader base's serial link (--leader serial:PATH; a ROS 2 base is the node's)
    camera: Rig | None
    n_followers: int
    scenario_name: str | None = None  # as given on the command line (the recording's metadata)
    camera_source: str | None = None  # a real rig's camera (index, device, video or folder)
    camera_fps: float | None = None
    host: str = "127.0.0.1"
    port: int = 8080
    token: str | None = None
    viewer_token: str | None = None
    rate_hz: float | None = None  # None: the config's
    seed: int | None = None  # None: the config's
    recordings: Path | None = None
    realtime: bool = False
    loop_process: bool = True  # the page in a process of its own (run --one-process: in the loop's)
    reserve_cpu: bool = False  # a CPU kept for the loop's thread (run --reserve-cpu)
    record: bool = True
    record_to: Path | None = None
    frames_hz: float = 10.0
    radio: RadioPlan = field(default_factory=RadioPlan)
    fleet: FleetPlan | None = None
    ros2: Ros2Plan | None = None
    foxglove: FoxglovePlan | None = None


@dataclass
class _Fleet:
    """This leader on a fleet's bus: the session, its arena team and liveliness token, and the
    starting values an arena gives."""

    session: zenoh.Session
    arena_team: ArenaTeam | None = None
    token: Any = None
    params: Params | None = None
    presence: Presence | None = None  # set when it was on the bus before its loop (waiting for robots)
    t_start: float = 0.0  # the session time it reached while waiting


@dataclass
class Running:
    """The composition, running: the service, its link and recorder, the fleet bridge."""

    service: Service
    link: FollowerLink | None
    recorder: Recorder | None
    bridge: FleetBridge | None

    @property
    def twin(self) -> str | None:
        """Why it gave way, when it missed its twin at start (one line), else None."""
        return self.bridge.twin if self.bridge is not None else None


@contextlib.contextmanager
def compose(plan: RunPlan, say: Callable[..., None]) -> Iterator[Running]:
    """Build and wire every part the plan asks for; on the way out (whatever happens) close them
    in reverse, the service first (the loop ends, every follower at zero). The caller starts the
    service (``running.service.start()``) and waits for it."""
    from app.services import ros2_node
    from app.services.foxglove_attach import attach_to_service

    _check_room(plan)
    with contextlib.ExitStack() as stack:
        handed = stack.enter_context(contextlib.ExitStack())  # closed here until the service owns them
        frames = _open_camera(plan, handed)
        fleet = _join_fleet(plan, stack, handed, say)
        node = ros2_node.open_run_node(plan.ros2, stack)
        base = ros2_node.leader_base(plan.ros2, node)
        link, hardware = _build_rig(plan, handed, base)
        service = _serve(plan, frames, link, hardware, fleet, base, say)
        handed.pop_all()  # the service closes the team, its link and the camera now
        stack.callback(service.close)
        recorder = _start_recorder(plan, service, say)
        if recorder is not None:
            stack.callback(lambda: say(f"omniformation: {recorder.closing_line()}"))
            stack.callback(recorder.close)
        attach_to_service(plan.foxglove, service, recorder, stack, say)
        bridge = _on_the_bus(plan, fleet, service, stack, say) if fleet is not None else None
        ros2_node.start_bridge(plan.ros2, node, service, base, plan.frames_hz, stack, say)
        stack.callback(service.close)  # first on the way out: the loop ends, every follower at zero
        yield Running(service, link, recorder, bridge)


def _open_camera(plan: RunPlan, handed: contextlib.ExitStack) -> RealtimeFrameSource | None:
    if not plan.real or plan.camera_source is None:
        return None
    from app.backends.camera import open_frame_source

    try:
        frames = open_frame_source(plan.camera_source, plan.camera_fps,
                                   settings=plan.camera[0].capture if plan.camera else None)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    handed.callback(frames.close)
    return frames


def _join_fleet(plan: RunPlan, stack: contextlib.ExitStack, handed: contextlib.ExitStack,
                say: Callable[..., None]) -> _Fleet | None:
    """On the bus before anything drives: an id taken, or no arena, ends here."""
    fp = plan.fleet
    if fp is None:
        return None
    from app.fleet.bridge import name_taken
    from app.services.bus import open_bus

    fleet = _Fleet(open_bus(list(fp.listen), list(fp.connect), f"--fleet {fp.name}", fp.keys))
    stack.callback(fleet.session.close)
    config, fleet_scenario = plan.config, plan.fleet_scenario
    if fleet_scenario is not None:
        from app.backends.arena import ArenaTeam, NoArena

        try:
            fleet.arena_team = ArenaTeam(fleet.session, fp.name, fp.leader_id,
                                         config.measurement.position_noise_m, config.measurement.heading_noise_rad,
                                         config.seed if plan.seed is None else plan.seed,
                                         hues_deg=fleet_scenario.hues_deg, rate_hz=fleet_scenario.rate_hz)
        except NoArena as exc:
            raise UserError(f"--arena {fp.arena}: {exc}") from None
        handed.callback(fleet.arena_team.close)
        if fp.arena_radio:
            assert plan.radio.radio_id is not None
            fleet.arena_team.use_radio(fp.arena_radio, plan.radio.radio_id, plan.radio.baud, **plan.radio.options())
    if name_taken(fleet.session, fp.name, fp.leader_id):
        raise UserError(f"--leader-id {fp.leader_id}: a leader with this id is alive on fleet {fp.name}"
                        " already; every leader needs its own id")
    team = fleet.arena_team
    if team is not None and fleet_scenario is not None:
        from app.keys import root
        from app.params import Params, default_slots

        if not team.owned:  # it comes back after its robots were adopted: alive, empty-handed
            fleet.token = fleet.session.liveliness().declare_token(f"{root(fp.name)}/alive/{fp.leader_id}")
            handed.callback(fleet.token.undeclare)
            from app.fleet.bridge import Presence, WaitingState

            fleet.presence = Presence.new()
            waiting = WaitingState(fleet.session, fp.name, fp.leader_id, fleet.presence, fp.control)
            say(f"omniformation: {fp.leader_id} owns no robot in the arena now (other leaders adopted"
                " them); waiting for the operator to hand one over (the fleet page's Hand over)")
            try:
                team.wait_for_robots()
            finally:
                fleet.t_start = waiting.close()
        me = fleet_scenario.leaders[fleet_scenario.leader_index(fp.leader_id)]
        n_owned = len(team.owned)
        slots = default_slots(n_owned) if fleet.token is None else team.slots_for_owned()
        fleet.params = Params(n_followers=n_owned, slots=slots, leader_mode=me.mode,  # type: ignore[arg-type]
                              leader_speed_mps=me.speed_mps, leader_turn_deg_s=me.turn_deg_s)
    return fleet


def _build_rig(plan: RunPlan, handed: contextlib.ExitStack,
               base: FollowerLink | None = None) -> tuple[FollowerLink | None, HardwareTeam | None]:
    """The followers' link (serial, or the emulator) and, on a real rig, the real team: each link
    made by the link registry (app.backends.links) from the spec the command line looked up."""
    from app.backends import links
    from core.types import Gains

    limits = plan.scenario.gains if plan.scenario is not None else Gains()
    link = None
    if plan.link is not None:
        wiring = links.Wiring(n=plan.n_followers, baud=plan.radio.baud, v_max=limits.v_max, w_max=limits.w_max,
                              radio_id=plan.radio.radio_id, radio=plan.radio.options())
        try:
            link = links.make(plan.link, links.FOLLOWERS, wiring)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if link is not None:
            handed.callback(link.close)
    hardware = None
    if plan.real:
        from app.backends.hardware import HardwareTeam

        leader = links.make(plan.leader, links.LEADER, links.Wiring(baud=plan.radio.baud)) if plan.leader is not None \
            else base
        hardware = HardwareTeam(plan.n_followers, link, leader)
        handed.callback(hardware.close)
    return link, hardware


def _serve(plan: RunPlan, frames: RealtimeFrameSource | None, link: FollowerLink | None, hardware: HardwareTeam | None,
           fleet: _Fleet | None, base: FollowerLink | None, say: Callable[..., None]) -> Service:
    from app.dashboard.gate import is_loopback
    from app.services.live import Service

    config = plan.config
    try:
        service = Service(host=plan.host, port=plan.port, scenario=plan.scenario,
                          n_followers=plan.n_followers, rate_hz=plan.rate_hz or config.rate_hz,
                          seed=config.seed if plan.seed is None else plan.seed, camera=plan.camera,
                          dynamics=config.dynamics, noise=config.measurement,
                          link=None if plan.real else link, frames=frames, hardware=hardware,
                          recordings=plan.recordings, token=plan.token, viewer_token=plan.viewer_token,
                          arena=fleet.arena_team if fleet else None, params=fleet.params if fleet else None,
                          realtime=plan.realtime, leader_base=None if plan.real else base,
                          page_process=plan.loop_process, reserve_cpu=plan.reserve_cpu)
    except OSError as exc:
        raise UserError(bind_error(plan.host, plan.port, exc)) from None
    if not is_loopback(plan.host):  # after the bind: an address not here is one line, no warning first
        say(f"omniformation: serving on {plan.host}: only browsers that open the URL below (it carries the"
            " token) may see and command the robots", err=True)
    return service


def _check_room(plan: RunPlan) -> None:
    """A recording the disk has no room for is refused before the camera, the page and the warm-up
    start (the recorder checks again when it opens its file)."""
    if not plan.record:
        return
    from app.files import default_recordings
    from app.recording.writer import RecordingRefused, check_room

    try:
        check_room(plan.record_to or plan.recordings or default_recordings(), plan.config.free_floor_bytes)
    except RecordingRefused as exc:
        raise UserError(str(exc)) from None


def _start_recorder(plan: RunPlan, service: Service, say: Callable[..., None]) -> Recorder | None:
    if not plan.record:
        return None
    from app.recording.writer import RecordingRefused
    from app.services.recording import start_recording

    try:
        recorder = start_recording(service, plan.config, plan.scenario, plan.scenario_name, plan.camera,
                                   plan.frames_hz, plan.record_to, plan.recordings)
    except (RecordingRefused, OSError) as exc:
        raise UserError(str(exc) if isinstance(exc, RecordingRefused) else
                        f"cannot record: {exc.strerror or exc}") from None
    say(f"omniformation: recording to {display_path(recorder.path)}")
    return recorder


def _on_the_bus(plan: RunPlan, fleet: _Fleet, service: Service, stack: contextlib.ExitStack,
                say: Callable[..., None]) -> FleetBridge:
    """The bridge (state out, STOP and, if allowed, commands in) and an arena leader's adopter."""
    from app.fleet.bridge import FleetBridge

    fp = plan.fleet
    assert fp is not None
    bridge = FleetBridge(service.store, fp.name, fp.leader_id, allow_control=fp.control,
                         session=fleet.session, token=fleet.token, on_twin=service.loop.stop,
                         presence=fleet.presence, t_start=fleet.t_start)
    stack.callback(bridge.close)
    service.loop.subscribe(bridge.on_tick)
    service.show_line(bridge.status)
    if fp.connect and not fleet.arena_team:  # an arena leader knows it is connected (it had the truth)
        deadline = time.monotonic() + 3.0
        while not bridge.peers() and time.monotonic() < deadline:
            time.sleep(0.1)
        if not bridge.peers():
            say(f"omniformation: fleet bus: no peer answers at {', '.join(fp.connect)}; retrying in the"
                " background (the loop runs; the page says 'fleet: disconnected')", err=True)
    if fleet.arena_team is not None:
        from app.fleet.adopter import Adopter

        adopter = Adopter(fleet.session, fp.name, fp.leader_id, fleet.arena_team, service.store,
                          event=bridge.event)
        team = fleet.arena_team
        bridge.empty = lambda: team.emptied
        bridge.truths_refused = lambda: team.truths_refused
        stack.callback(adopter.close)
    say(f"omniformation: on the fleet bus as {fp.name}/{fp.leader_id}"
        f" ({'taking commands' if fp.control else 'STOP only'} from it)")
    return bridge
