"""One reader for every message on the fleet's bus (docs/fleet-protocol.md, "Payloads"): size
and depth limits before anything looks inside, exact JSON types after (a string or a boolean
is never a number, an integer has at most 18 digits), and one line saying what is wrong. Every
program of the fleet reads the bus through it, so a message built to break a parser (deeply
nested, a 400-digit integer, a list for an object) is a refusal to count and answer, never a
traceback. Shared by the fleet's programs and the arena backend (imports no folder of app)."""

from __future__ import annotations

import json
import math
from typing import Any

from core.bounds import BUS, PARAMETERS

MAX_BYTES = 256 * 1024  # a truth of 8 teams of 8 robots is ~20 KiB
MAX_DEPTH = 6  # {"commands": {"R1": [v, w]}} is 3 deep; a state's p_est 3
MAX_DIGITS = 18  # an integer on the bus is a tick, a count or milliseconds


class BadMessage(ValueError):
    """A message that is not what the protocol says: one line saying why."""


def _no_constant(name: str) -> Any:
    raise BadMessage(f"{name} is not a number JSON allows")


def _integer(text: str) -> int:
    if len(text.lstrip("-")) > MAX_DIGITS:
        raise BadMessage(f"an integer of {len(text.lstrip('-'))} digits (at most {MAX_DIGITS})")
    return int(text)


def _refusal(value: Any) -> str:
    """Why a parsed message is refused ('' if it is not): a container nested deeper than
    MAX_DEPTH, or a number that is not finite (a float too large for a double, as 1e999, reads
    as infinity). One pass, a level at a time; plain JSON holds only dicts, lists, strings,
    numbers, booleans and null."""
    isfinite = math.isfinite
    if type(value) is float and not isfinite(value):
        return f"{value} is not a finite number"
    level = [value]
    depth = 0
    while level:
        depth += 1
        inner = []
        for v in level:
            t = type(v)
            if t is not list and t is not dict:
                continue
            if depth > MAX_DEPTH:
                return f"nested deeper than {MAX_DEPTH}"
            for x in (v if t is list else v.values()):
                tx = type(x)
                if tx is float:
                    if not isfinite(x):
                        return f"{x} is not a finite number"
                elif tx is list or tx is dict:
                    inner.append(x)
        level = inner
    return ""


def decode(data: bytes | None) -> Any:
    """JSON within the bus's limits, or BadMessage. Sizes first (nothing larger is parsed), then
    the parse (NaN, Infinity, non-finite floats and long integers refused as they are read; a
    nesting deep enough to exhaust the parser is refused whole), then the depth."""
    if data is None:
        raise BadMessage("no payload")
    if len(data) > MAX_BYTES:
        raise BadMessage(f"{len(data)} bytes (at most {MAX_BYTES})")
    try:
        value = json.loads(data, parse_int=_integer, parse_constant=_no_constant)
    except BadMessage:
        raise
    except RecursionError:
        raise BadMessage(f"nested deeper than {MAX_DEPTH}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise BadMessage(f"not JSON ({str(exc)[:60]})") from None
    why = _refusal(value)  # the floats checked here, not as they are read: a call per number cost a truth 3x
    if why:
        raise BadMessage(why)
    return value


# -- exact types --------------------------------------------------------------------------------
def is_number(x: Any) -> bool:
    """A JSON number (a boolean is not one); finite by decode()."""
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def is_integer(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def obj(x: Any, what: str, required: tuple[str, ...] = (), optional: tuple[str, ...] = (),
        more: bool = False) -> dict[str, Any]:
    """An object with these fields (no other unless ``more``: a message others read too, which
    may grow), else BadMessage naming the first that is wrong."""
    if not isinstance(x, dict):
        raise BadMessage(f"{what} must be a JSON object, not {type(x).__name__}")
    missing = [k for k in required if k not in x]
    if missing:
        raise BadMessage(f"{what} has no {missing[0]!r}")
    unknown = [] if more else [k for k in x if k not in required and k not in optional]
    if unknown:
        raise BadMessage(f"{what}: unknown field {str(unknown[0])[:40]!r}")
    return x


def number(x: Any, what: str) -> float:
    if not is_number(x):
        raise BadMessage(f"{what} must be a number, not {json.dumps(x)[:30]}")
    return float(x)


def integer(x: Any, what: str) -> int:
    if not is_integer(x):
        raise BadMessage(f"{what} must be a whole number, not {json.dumps(x)[:30]}")
    return int(x)


def text(x: Any, what: str, longest: int = 64) -> str:
    if not isinstance(x, str) or len(x) > longest:
        raise BadMessage(f"{what} must be a string of at most {longest} characters")
    return x


def numbers(x: Any, n: int, what: str) -> list[float]:
    """A list of exactly ``n`` numbers."""
    if not isinstance(x, list) or len(x) != n:
        raise BadMessage(f"{what} must be a list of {n} numbers")
    return [number(v, what) for v in x]


def check_numbers(x: Any, n: int, what: str) -> None:
    """As :func:`numbers`, for a reader that keeps the list as it is (a truth's poses, many a
    message): the exact types checked in one expression, the same refusal when one is not."""
    if type(x) is not list or len(x) != n or not all(type(v) is float or type(v) is int for v in x):
        numbers(x, n, what)  # says which rule it broke (a list subclass or a float subclass: accepted there)


# -- the values a command may set (docs/fleet-protocol.md, "cmd") ------------------------------------
# by their kind in the parameter table (core.bounds): the bus's own are those a command may carry
NUMBER_SETTINGS = tuple(n for n, row in PARAMETERS.items() if row.kind in ("gain", "number") and BUS in row.setters)
FLAG_SETTINGS = tuple(n for n, row in PARAMETERS.items() if row.kind == "flag" and BUS in row.setters)


def setting(name: str, value: Any) -> Any:
    """A command's value of the type its setting takes (its range is the parameters' to check),
    else BadMessage: a number is a JSON number, a flag true or false, ``leader_mode`` a string,
    ``slots`` a list of [x, y], ``goal`` [x, y] or null."""
    if name in NUMBER_SETTINGS:
        return number(value, name)
    if name in FLAG_SETTINGS:
        if not isinstance(value, bool):
            raise BadMessage(f"{name} must be true or false, not {json.dumps(value)[:30]}")
        return value
    if name == "leader_mode":
        return text(value, name, 16)
    if name == "goal":
        return None if value is None else tuple(numbers(value, 2, name))
    if name == "slots":
        if not isinstance(value, list) or not 1 <= len(value) <= 64:
            raise BadMessage("slots must be a list of [x, y]")
        return [numbers(v, 2, "slots") for v in value]
    raise BadMessage(f"{name!r} cannot be set")
