"""The link registry: one place maps a link spec's scheme to its parser and to the factory that
makes the link, and says which option takes it.

``--link`` (the followers) takes ``sim``, ``none`` or ``serial:PATH[,PATH...]``; ``--leader`` (the
leader's base) ``serial:PATH`` or ``ros2:/TOPIC[:stamped]``; the config's ``service.link`` what
``--link`` takes. The text rules are core.link.spec's; the command line only looks a spec up here
(app.cli.live, app.cli.ros2) and the services make each link through :func:`make` (app.services.run,
app.services.ros2_node). A new link type is one :class:`LinkType` in :data:`LINK_TYPES` (its
scheme's parser in core.link.spec.SCHEMES), docs/architecture.md says what else.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from core.link.spec import SCHEMES, LinkSpec, Scheme, parse_spec

from app.contracts import FollowerLink

__all__ = ["FOLLOWERS", "LEADER", "LINK_TYPES", "LinkSpec", "LinkType", "Wiring", "make", "parse_link", "schemes_for"]

FOLLOWERS = "--link"
LEADER = "--leader"


@dataclass(frozen=True)
class Wiring:
    """What a factory may need besides the spec: the team's size and limits, the radio's options
    (app.services.run.RadioPlan.options), a ROS 2 node (app.backends.ros2.Ros2Node)."""

    n: int = 1
    baud: int = 115200
    v_max: float = 0.3
    w_max: float = 2.0
    radio_id: int | None = None
    radio: dict[str, Any] = field(default_factory=dict)
    node: Any = None


@dataclass(frozen=True)
class LinkType:
    """A scheme, the options that take it, whether it may lead the simulated team (``--leader``
    without ``--camera``), and its factory (None: there is nothing to open)."""

    scheme: Scheme
    options: tuple[str, ...]
    what: str
    make: Callable[[LinkSpec, str, Wiring], FollowerLink] | None = None
    leads_simulated_team: bool = False


def _serial(spec: LinkSpec, option: str, wiring: Wiring) -> FollowerLink:
    from app.backends.serial_link import SerialLink, make_link

    ports = ",".join(spec.ports)
    if option == LEADER:  # the leader base, at address 0 (docs/follower-protocol.md)
        return SerialLink(ports, 1, baud=wiring.baud, addresses=[0])
    return make_link(ports, wiring.n, baud=wiring.baud, v_max=wiring.v_max, w_max=wiring.w_max,
                     radio_id=wiring.radio_id, **wiring.radio)


def _ros2(spec: LinkSpec, option: str, wiring: Wiring) -> FollowerLink:
    from app.backends.ros2 import Ros2Base

    assert spec.topic is not None and wiring.node is not None
    topic, stamped = spec.topic
    return Ros2Base(wiring.node, topic, stamped)


LINK_TYPES: dict[str, LinkType] = {t.scheme.name: t for t in (
    LinkType(SCHEMES["sim"], (FOLLOWERS,), "the simulated team's own link"),
    LinkType(SCHEMES["none"], (FOLLOWERS,), "a real rig that only observes: nothing is sent"),
    LinkType(SCHEMES["serial"], (FOLLOWERS, LEADER), "the robots' serial port or radio (docs/follower-protocol.md);"
             " one port per follower with a comma-separated list", _serial),
    LinkType(SCHEMES["ros2"], (LEADER,), "a ROS 2 base's command topic, its odometry on /odom (docs/ros2.md)",
             _ros2, leads_simulated_team=True),
)}


def schemes_for(option: str) -> tuple[str, ...]:
    """The schemes ``option`` takes, in the registry's order."""
    return tuple(name for name, t in LINK_TYPES.items() if option in t.options)


def parse_link(text: str, option: str) -> LinkSpec:
    """``text`` given to ``option`` (``--link``, ``--leader``): ValueError in one line naming the
    schemes it takes when it is none of them."""
    return parse_spec(text, option, schemes_for(option))


def make(spec: LinkSpec, option: str, wiring: Wiring) -> FollowerLink | None:
    """The link ``spec`` names, made for ``option``'s role; None for a scheme with nothing to open."""
    factory = LINK_TYPES[spec.scheme].make
    return factory(spec, option, wiring) if factory is not None else None
