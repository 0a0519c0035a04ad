"""Link specs: the text that names a robot link on the command line and in the config, parsed.

A spec is ``SCHEME`` or ``SCHEME:VALUE``: ``sim`` (the simulated team's own link), ``none`` (a
real rig that only observes), ``serial:PATH[,PATH...]`` (a serial port or pyserial URL, or one
port per follower), ``ros2:/TOPIC[:stamped]`` (a ROS 2 base's command topic). Pure text rules:
which link each scheme makes, and for which option, is the link registry's
(app.backends.links), which takes its parsers from :data:`SCHEMES`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from core.rmw_zenoh import check_topic

PortList = tuple[str, ...]
Ros2Topic = tuple[str, bool]  # (topic, stamped)


@dataclass(frozen=True)
class LinkSpec:
    """A parsed spec: its scheme and what the scheme's parser made of the rest (None without one)."""

    text: str
    scheme: str
    value: PortList | Ros2Topic | None = None

    @property
    def ports(self) -> PortList:
        """A serial spec's ports (none for another scheme)."""
        return tuple(str(v) for v in self.value) if self.scheme == "serial" and self.value is not None else ()

    @property
    def topic(self) -> Ros2Topic | None:
        """A ROS 2 spec's (topic, stamped) (None for another scheme)."""
        if self.scheme != "ros2" or self.value is None:
            return None
        return str(self.value[0]), bool(self.value[1])


@dataclass(frozen=True)
class Scheme:
    """One scheme: how people write it, and the parser of its value (None: it takes no value)."""

    name: str
    form: str
    parse: Callable[[str, str], PortList | Ros2Topic] | None = None


def serial_ports(value: str, spec: str) -> PortList:
    """``PATH[,PATH...]`` -> the ports (a pyserial URL such as ``socket://host:port`` is a port)."""
    ports = tuple(p.strip() for p in value.split(","))
    if any(not p for p in ports):
        raise ValueError(f"{spec!r}: an empty port name in the list")
    return ports


def ros2_topic(value: str, spec: str) -> Ros2Topic:
    """``/TOPIC`` or ``/TOPIC:stamped`` -> (topic, stamped: TwistStamped rather than Twist)."""
    stamped = value.endswith(":stamped")
    topic = value.removesuffix(":stamped")
    try:
        check_topic(topic)
    except ValueError as exc:
        raise ValueError(f"{spec!r}: must be ros2:/TOPIC or ros2:/TOPIC:stamped ({exc})") from None
    return topic, stamped


SCHEMES: dict[str, Scheme] = {s.name: s for s in (
    Scheme("sim", "sim"),
    Scheme("none", "none"),
    Scheme("serial", "serial:PATH", serial_ports),
    Scheme("ros2", "ros2:/TOPIC", ros2_topic),
)}


def forms(names: tuple[str, ...]) -> str:
    """The schemes ``names`` as people write them: 'sim', 'none' or 'serial:PATH'."""
    quoted = [f"'{SCHEMES[n].form}'" for n in names]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " or " + quoted[-1]


def parse_spec(text: str, option: str, allowed: tuple[str, ...]) -> LinkSpec:
    """``text`` given to ``option`` (e.g. ``--link``, ``service.link``), whose schemes are ``allowed``:
    its scheme and parsed value; ValueError in one line naming what is allowed otherwise."""
    name, colon, value = text.partition(":")
    scheme = SCHEMES.get(name)
    if scheme is None or name not in allowed or (scheme.parse is None) == bool(colon) \
            or (scheme.parse is not None and not value):
        raise ValueError(f"{option} {text!r}: must be {forms(allowed)}")
    if scheme.parse is None:
        return LinkSpec(text, name)
    try:
        return LinkSpec(text, name, scheme.parse(value, text))
    except ValueError as exc:
        raise ValueError(f"{option} {exc}") from None
