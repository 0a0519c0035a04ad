"""The service as a ROS 2 node on rmw_zenoh (docs/ros2.md): the node, a leader base on ROS 2 and
the bridge that publishes the loop's state (and takes STOP and goals with --ros2-control)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from app.files import UserError

if TYPE_CHECKING:
    from app.backends.links import LinkSpec

    from app.backends.ros2 import Ros2Node
    from app.contracts import FollowerLink
    from app.fleet.security import FleetKeys
    from app.services.live import Service


@dataclass(frozen=True)
class Ros2Plan:
    """``run --ros2`` as checked: the router, the keys, the domain, a ROS 2 leader base (its
    ``ros2:/TOPIC[:stamped]`` spec, app.backends.links) and whether ROS may send STOP and goals."""

    connect: tuple[str, ...]
    keys: FleetKeys | None
    domain: int
    leader: LinkSpec | None
    control: bool
    intruder_stop: bool = False  # --ros2-intruder-stop: another publisher on the base's command topic is STOP


def open_node(connect: list[str] | tuple[str, ...], keys: FleetKeys | None, domain: int, name: str) -> Ros2Node:
    """A ROS 2 node on a Zenoh client of the router at ``connect`` (the fleet's endpoint rules);
    one line (UserError) for a bad endpoint or a router that is not there."""
    from app.backends.ros2 import Ros2Node
    from app.ros2.session import open_ros2_session

    try:
        session = open_ros2_session(list(connect), keys)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    try:
        return Ros2Node(session, name, domain)
    except Exception:
        session.close()
        raise


def open_run_node(plan: Ros2Plan | None, stack: contextlib.ExitStack) -> Ros2Node | None:
    """The service's node (None without --ros2), closed last on the way out."""
    if plan is None:
        return None
    node = open_node(plan.connect, plan.keys, plan.domain, "omniformation")
    stack.callback(node.session.close)
    stack.callback(node.close)
    return node


def leader_base(plan: Ros2Plan | None, node: Ros2Node | None) -> FollowerLink | None:
    """``--leader ros2:TOPIC``: the leader's base on ROS 2 (its odometry on /odom), made by the link registry."""
    if plan is None or node is None or plan.leader is None:
        return None
    from app.backends import links
    from app.backends.ros2 import publishers_of

    topic = plan.leader.topic[0] if plan.leader.topic is not None else ""
    others = publishers_of(node.session, plan.domain, topic)
    if others:  # a robot is never commanded by two programs
        raise UserError(f"--leader {topic}: {', '.join(sorted(set(others)))} publish(es) on {topic} already (domain"
                        f" {plan.domain}); stop it first, a base takes commands from one program")
    return links.make(plan.leader, links.LEADER, links.Wiring(node=node))


def start_bridge(plan: Ros2Plan | None, node: Ros2Node | None, service: Service, base: Any, frames_hz: float,
                 stack: contextlib.ExitStack, say: Callable[[str], None]) -> None:
    """The loop's state out on ROS 2 (and STOP and goals in with --ros2-control)."""
    if plan is None or node is None:
        return
    from app.ros2.bridge import Ros2Bridge

    bridge = Ros2Bridge(node, service.store, plan.control, frames_hz,
                        base_state=(lambda: base.link_state) if base is not None else None)
    stack.callback(bridge.close)
    service.loop.subscribe(bridge.on_tick)
    if plan.intruder_stop and hasattr(base, "on_intrusion"):  # a ROS 2 base: a second commander is STOP
        base.on_intrusion(lambda text: service.store.update("ros2:intruder", stop=True))
    say(f"omniformation: ROS 2 node /omniformation on domain {plan.domain} via {', '.join(plan.connect)}"
        f" ({'taking STOP and goals' if plan.control else 'publishing only'})")


@contextlib.contextmanager
def run_emulated_base(connect: list[str], keys: FleetKeys | None, domain: int, rate_hz: float,
                      speed_scale: float) -> Iterator[Any]:
    """`emulate-base --ros2`: an emulated ROS 2 base on its own node, running until the block
    ends; the base, then its node and session, closed on the way out."""
    from app.ros2.base import EmulatedBase

    with contextlib.ExitStack() as stack:
        node = open_node(connect, keys, domain, "omniformation_base")
        stack.callback(node.session.close)
        stack.callback(node.close)
        base = EmulatedBase(node, rate_hz, speed_scale=speed_scale)
        base.start()
        stack.callback(base.close)
        yield base
