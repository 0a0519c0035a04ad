"""The page's only door: who may open the dashboard and command the robots.

viser serves its page and websocket with no check of ``Origin`` or ``Host`` and, when the
port it is asked for is taken, silently takes the next one. It has no hook for either, so
this layer stands in front of it (the `websockets` library viser itself is built on, not a
fork): the :class:`Gate` binds the address the operator asked for (a taken port or an
address this machine does not have is an :class:`OSError` at once, never another port) and
forwards what it lets in to a viser server on a loopback port of its own.

What it lets in:

* every request's ``Host`` must name this server: on a loopback address, only
  ``127.0.0.1``, ``localhost`` or ``[::1]`` with the served port (a DNS-rebinding page
  arrives with its own host name and is refused); on another address, an IP literal, this
  machine's names or ``localhost``;
* a websocket must come from the page itself: its ``Origin`` is ``http://`` + its ``Host``
  (any other web page open in the operator's browser is refused);
* on any address other than loopback a token is required, generated unless given, handed
  out as ``?token=…`` in the printed URL (as notebook servers do) and then kept by the
  browser as an HttpOnly, SameSite=Strict cookie named for the port (a browser sends a host's
  cookies to every port of it: a replay on another port must not overwrite the live page's).

Two roles: a client that presents the token (or any client on loopback) is the **operator**; a
client that presents the viewer token (``viewer_token``, a second printed URL) is a **viewer**: it
sees everything and may press STOP, nothing else (the input filter refuses the rest).

Every message a client sends goes through :class:`app.dashboard.input_filter.InputFilter` before
viser sees it: only a value for a known control, of the right type and within its bounds, passes.
A refused update is answered (to that client alone) with the value in force (at most once a second
per control) and a notice; the log says so at most once a second per remote address (reconnecting
buys no line), in one line, and refused requests likewise at most once a second per reason.

How much (docs/page-access.md): each connection has a budget (app.dashboard.allowance.Budget: ``RATE`` messages a
second, ``BURST`` at once); what is over it is dropped before it is decoded, a connection that stays
over it is closed and its address refused for ``BAN_S``; all of an address's connections together
have ``ADDRESS_RATE`` of messages forwarded (STOP always passes); at most ``PER_ADDRESS`` websockets per
address and ``MAX_CONNECTIONS`` in all, the last ``OPERATOR_RESERVE`` of them for operators.

viser's own loopback port would let a local page around the gate, so the gate marks its
upstream connections with a per-process secret header and refuses, before viser's own
handlers run, any websocket on that port that does not carry it. That check reads viser's
table of live connections (through app.dashboard.viser_private, present since viser 1.0):
where it is missing the gate refuses to start rather than serve unguarded.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import importlib.resources
import json
import http
import http.client
import io
import ipaddress
import logging
import secrets
import socket
import threading
import time
from dataclasses import dataclass
from http.cookies import SimpleCookie
from collections.abc import Callable
from typing import Any, TypeVar
from urllib.parse import parse_qs, urlsplit

import viser
import websockets.asyncio.client
import websockets.asyncio.server
import websockets.exceptions
from websockets.datastructures import Headers
from websockets.http11 import Request, Response
from websockets.typing import Subprotocol

from core.link.protocol import WATCHDOG_S

from app.dashboard.allowance import RATE, Budget, Throttle, one_line
from app.dashboard import viser_private
from app.refusals import refuse
from app.dashboard.input_filter import OPERATOR, VIEWER, InputFilter, Verdict
from app.dashboard.viser_private import GuiUpdateMessage

log = logging.getLogger(__name__)
T = TypeVar("T")

LOOPBACK = {"127.0.0.1", "localhost", "::1"}
COOKIE = "omniformation_token"
GATE_HEADER = "X-Omniformation-Gate"
# What the gate adds to the page it serves (viser has no hook for either): the keyboard's STOP, a
# bar fixed to the window with STOP and the state line, the health banner, the light mode, links to
# other pages in new tabs, "Wide panel". The files are assets/page.css and assets/page.js (package
# data), documented in docs/page-access.md ("What the page adds").
PAGE_KINDS = ("live", "replay", "fleet")
# A live page that has had no new tick for this long says it is not connected (its STOP reaches
# nothing): the loop's state line carries the tick it was drawn from, redrawn about five times a
# second (app.dashboard.controls.STATUS_S), so this is four missed redraws, and a page whose link
# went says so within a second of the last tick it had (assets/page.js).
LINK_LOST_S = 0.8


@functools.cache
def _asset(name: str) -> str:
    return (importlib.resources.files("app.dashboard") / "assets" / name).read_text(encoding="utf-8")


def page_head(kind: str = "live") -> bytes:
    """What goes before the page's ``</head>``: the style, the kind of page (a replay never looks
    live), then the script."""
    if kind not in PAGE_KINDS:
        raise ValueError(f"page kind {kind!r}: must be one of {', '.join(PAGE_KINDS)}")
    page = f"kind: {json.dumps(kind)}, lost_s: {LINK_LOST_S!r}, watchdog_s: {WATCHDOG_S!r}"  # the robots' own watchdog
    return (f"<style>\n{_asset('page.css')}</style>\n<script>window.OMNI_PAGE = {{{page}}};</script>\n"
            f"<script>\n{_asset('page.js')}</script>\n").encode()


MAX_MESSAGE = 50 * 1024 * 1024  # viser's own limit (what the page is sent)
MAX_CLIENT_MESSAGE = 1024 * 1024  # what a client may send in one message (the page's largest is a few hundred bytes)
CONN_HEADER = "X-Omniformation-Connection"  # which gate connection an upstream websocket serves
ROLE_HEADER = "X-Omniformation-Role"
ADDRESS_HEADER = "X-Omniformation-Address"  # the client's address, for "STOP by viewer 10.0.0.7"
NOTICE_EVERY_S = 1.0  # a client is told of refused updates this often at most (and sent a control's value back)
BAN_S = 30.0  # and its address refused this long
ADDRESS_RATE = 200.0  # messages a second all connections from one address may have forwarded to viser (STOP always)
ADDRESS_BURST = 600
PER_ADDRESS = 16  # open websockets from one address
MAX_CONNECTIONS = 64  # open websockets in all
OPERATOR_RESERVE = 8  # of which the last few only for operators
VIEWER_GREY_S = 1.5  # a viewer's controls are greyed out this long after it connects (the page is there by then)
REGISTER_WAIT_S = 10.0  # a refusal waits this long at most to be told to a client viser has not taken in yet
_BIND_TIMEOUT_S = 30.0
CLOSE_TIMEOUT_S = 1.0  # a client that does not answer a close (a flooder still sending) is cut off after this


class NotThroughTheGate(ConnectionError):
    """A websocket reached viser's loopback port without passing the gate."""


class _QuietRefusals(logging.Filter):
    """websockets logs a failed connection handler with its traceback; a refused one is not news."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, NotThroughTheGate)


logging.getLogger("websockets.server").addFilter(_QuietRefusals())


def _same(given: str, secret: str) -> bool:
    """A constant-time comparison that takes any text a client sends (non-ASCII included)."""
    return secrets.compare_digest(given.encode("utf-8", "surrogateescape"), secret.encode())


def _is_upgrade(request: Request) -> bool:
    return any(v.strip().lower() == "websocket" for v in request.headers.get_all("Upgrade"))


def is_loopback(host: str) -> bool:
    return host in LOOPBACK


def new_token() -> str:
    return secrets.token_urlsafe(18)


@dataclass
class GateCounts:
    """What the gate refused, by reason (shown in tests and logs)."""

    host: int = 0
    origin: int = 0
    token: int = 0
    bypass: int = 0
    messages: int = 0  # messages from let-in clients that the input filter refused
    flood: int = 0  # messages dropped over a connection's budget (never decoded)
    cut: int = 0  # connections closed for staying over their budget
    banned: int = 0  # requests from an address refused for a while
    full: int = 0  # websockets refused: too many from the address, or in all
    address: int = 0  # messages dropped over their address's budget (all its connections together)


class Gate:
    """Serves ``server`` (a viser server on a loopback port) at ``host``:``port``, checked.

    ``token``: required from clients when given; ``None`` on a non-loopback host makes one.
    """

    def __init__(self, server: viser.ViserServer, host: str, port: int, token: str | None = None,
                 viewer_token: str | None = None) -> None:
        self.server = server
        self.host = host
        self.token = token if token is not None or is_loopback(host) else new_token()
        self.viewer_token = viewer_token if viewer_token is not None else new_token()
        if self.token and _same(self.viewer_token, self.token):
            raise ValueError("the viewer token must differ from the operator's token")
        self.refused = GateCounts()
        self.filter = InputFilter(server)
        self.roles: dict[int, str] = {}  # viser client id -> OPERATOR or VIEWER
        self.addresses: dict[int, str] = {}  # viser client id -> the client's address (as the gate saw it)
        self._client_of: dict[str, int] = {}  # gate connection key -> viser client id
        self._taken_in: dict[str, Callable[[], None]] = {}  # gate connection key -> tell it viser took its client in
        self._telling: dict[str, asyncio.Task[None]] = {}  # gate connection key -> its refusal waiting for its client
        self._notice_throttle = Throttle(NOTICE_EVERY_S)
        self._banned: dict[str, float] = {}  # address -> refused until (monotonic)
        self._open: dict[str, int] = {}  # address -> open websockets
        self._address_budget: dict[str, Budget] = {}  # address -> what all its connections together may forward
        self._secret = secrets.token_hex(16)
        self._upstream = server.get_port()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._bound = threading.Event()
        self._error: BaseException | None = None
        self.port = 0
        self.page_kind = "live"  # what the page says it is: "live", "replay" (commands nothing) or "fleet"
        self._guard_upstream()
        self._thread = threading.Thread(target=self._run, args=(port,), name="omniformation-gate", daemon=True)
        self._thread.start()
        if not self._bound.wait(_BIND_TIMEOUT_S):
            raise OSError(f"could not bind {host}:{port} within {_BIND_TIMEOUT_S:g} s")
        if self._error is not None:
            raise self._error

    # -- the URL people open -------------------------------------------------------------

    @property
    def url(self) -> str:
        shown = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        if ":" in shown:
            shown = f"[{shown}]"
        base = f"http://{shown}:{self.port}/"
        return base + (f"?token={self.token}" if self.token else "")

    @property
    def viewer_url(self) -> str:
        """The URL for someone who may watch (and press STOP), nothing more."""
        return self.url.split("?")[0] + f"?token={self.viewer_token}"

    @property
    def cookie(self) -> str:
        """The cookie that keeps this page's token (one per port: see the module's docstring)."""
        return f"{COOKIE}_{self.port}"

    @property
    def open_connections(self) -> int:
        return sum(list(self._open.values()))  # read from other threads: a copy

    def role_of(self, client_id: int) -> str:
        return self.roles.get(client_id, VIEWER)  # unknown: the least a client may do

    def who(self, client_id: int) -> str:
        """A client as people name it: its role and address ("viewer 10.0.0.7")."""
        return f"{self.role_of(client_id)} {self.addresses.get(client_id) or '(address unknown)'}"

    # -- viser's own port: only the gate may connect -------------------------------------

    def _guard_upstream(self) -> None:
        table, callbacks = viser_private.connection_hooks(self.server)

        async def check(client: Any) -> None:
            connection = table.get(client.client_id)
            request = getattr(connection, "request", None)
            given = request.headers.get(GATE_HEADER, "") if request is not None else ""
            if not _same(given, self._secret):
                self.refused.bypass += 1
                if connection is not None:
                    await connection.close(1008, "connect through the dashboard's address")
                raise NotThroughTheGate("a websocket on viser's loopback port without the gate's mark")
            assert request is not None
            self.roles[client.client_id] = OPERATOR if request.headers.get(ROLE_HEADER, "") == OPERATOR else VIEWER
            self._client_of[request.headers.get(CONN_HEADER, "")] = client.client_id
            self.addresses[client.client_id] = request.headers.get(ADDRESS_HEADER, "")

        def forget(client: Any) -> None:
            self.roles.pop(client.client_id, None)
            self.addresses.pop(client.client_id, None)
            for key in [k for k, v in self._client_of.items() if v == client.client_id]:
                del self._client_of[key]

        def taken_in(client: Any) -> None:  # viser counts the client connected: its clicks count from now
            for key in [k for k, v in list(self._client_of.items()) if v == client.client_id]:
                tell = self._taken_in.pop(key, None)
                if tell is not None:
                    tell()

        callbacks.insert(0, check)  # before viser's own handlers build anything for the client
        self.server.on_client_disconnect(forget)
        self.server.on_client_connect(taken_in)
        self.server.on_client_connect(self._greet)

    def _greet(self, client: viser.ClientHandle) -> None:
        """A viewer is told what it may do, and its copy of the page greys out every control but
        STOP (the input filter refuses them whatever the page shows)."""
        if self.role_of(client.client_id) != VIEWER:
            return
        client.add_notification("View only", "You may watch and press STOP. Other controls are the operator's.",
                                with_close_button=True, color="blue")

        def grey_out() -> None:  # after the page's controls reached it (they come on another queue)
            if client.client_id not in self.roles:
                return
            for uuid in list(viser_private.control_table(self.server.gui)):
                if not self.filter.viewer_may(uuid):
                    viser_private.send_to(client, GuiUpdateMessage(uuid, {"disabled": True}))

        timer = threading.Timer(VIEWER_GREY_S, grey_out)
        timer.daemon = True
        timer.start()

    # -- the checks ------------------------------------------------------------------------

    def _allowed_host(self, host_header: str) -> bool:
        try:
            parts = urlsplit(f"//{host_header}")
            name, port = parts.hostname, parts.port
        except ValueError:
            return False
        if not name or port != self.port:
            return False
        if is_loopback(self.host):
            return name in LOOPBACK
        if name in LOOPBACK or name in (socket.gethostname().lower(), socket.getfqdn().lower()):
            return True
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return name == self.host.lower()
        return True

    def _token_from(self, request: Request) -> tuple[str, bool]:
        """(the token the client gave, whether it came in the URL's query)."""
        query = parse_qs(urlsplit(request.path).query).get("token", [""])[0]
        if query:
            return query, True
        cookie: SimpleCookie = SimpleCookie()
        for header in request.headers.get_all("Cookie"):
            with contextlib.suppress(Exception):
                cookie.load(header)
        morsel = cookie.get(self.cookie)
        return (morsel.value if morsel is not None else ""), False

    def refusal(self, request: Request) -> str:
        """Why this request may not pass ('' if it may)."""
        hosts = request.headers.get_all("Host")
        host_header = hosts[0] if len(hosts) == 1 else ""
        if not self._allowed_host(host_header):
            self.refused.host += 1
            return f"Host {', '.join(hosts)!r} is not this server's address"
        if _is_upgrade(request):
            origins = request.headers.get_all("Origin")
            origin = origins[0] if len(origins) == 1 else ""
            if origin != f"http://{host_header}":
                self.refused.origin += 1
                return f"Origin {origin!r} is not this page"
        if self.token and self.role(request) is None:
            self.refused.token += 1
            return "a token is required: open the URL the service printed (…/?token=…)"
        return ""

    def role(self, request: Request) -> str | None:
        """OPERATOR, VIEWER, or None (a token is required and none that counts was given)."""
        given, _ = self._token_from(request)
        if given and _same(given, self.viewer_token):
            return VIEWER
        if not self.token or _same(given, self.token):
            return OPERATOR
        return None

    # -- serving ---------------------------------------------------------------------------

    def _is_banned(self, address: str) -> bool:
        until = self._banned.get(address)
        if until is None:
            return False
        if time.monotonic() < until:
            return True
        del self._banned[address]
        return False

    def _ban(self, address: str) -> None:
        if len(self._banned) > 4096:  # addresses come and go: forget the ones whose time is up
            now = time.monotonic()
            self._banned = {a: t for a, t in self._banned.items() if t > now}
        self._banned[address] = time.monotonic() + BAN_S

    def _full(self, address: str, role: str | None) -> str:
        """Why one more websocket from ``address`` may not open now ('' if it may)."""
        total = self.open_connections
        if self._open.get(address, 0) >= PER_ADDRESS:
            return f"{PER_ADDRESS} connections from one address are open already"
        if total >= MAX_CONNECTIONS:
            return f"{MAX_CONNECTIONS} connections are open already"
        if role != OPERATOR and total >= MAX_CONNECTIONS - OPERATOR_RESERVE:
            return f"{total} connections are open already; the rest are kept for the operator"
        return ""

    def _refuse(self, connection: websockets.asyncio.server.ServerConnection, status: http.HTTPStatus,
                kind: str, why: str) -> Response:
        refuse(f"dashboard: {kind} request refused", _address(connection.remote_address), one_line(why), log)
        return connection.respond(status, f"omniformation: refused: {why}\n")

    async def _process_request(self, connection: websockets.asyncio.server.ServerConnection,
                               request: Request) -> Response | None:
        address = _address(connection.remote_address)
        if self._is_banned(address):
            self.refused.banned += 1
            return self._refuse(connection, http.HTTPStatus.TOO_MANY_REQUESTS, "banned",
                                f"{address} sent more than its budget; try again later")
        why = self.refusal(request)
        if why:
            return self._refuse(connection, http.HTTPStatus.FORBIDDEN, why.split(" ")[0], why)
        if _is_upgrade(request):
            full = self._full(address, self.role(request))
            if full:
                self.refused.full += 1
                return self._refuse(connection, http.HTTPStatus.SERVICE_UNAVAILABLE, "full", full)
            return None
        response = await asyncio.to_thread(self._fetch, request)
        given, from_query = self._token_from(request)
        if from_query and given and self.role(request) is not None:  # the operator's or the viewer's
            response.headers["Set-Cookie"] = f"{self.cookie}={given}; HttpOnly; SameSite=Strict; Path=/"
        return response

    def _fetch(self, request: Request) -> Response:
        """The page's files from viser (plain GET on its loopback port); the page itself gets
        what the gate adds (``page_head``)."""
        conn = http.client.HTTPConnection("127.0.0.1", self._upstream, timeout=30)
        page = urlsplit(request.path).path in ("/", "/index.html")
        try:
            encodings = request.headers.get_all("Accept-Encoding")
            headers = {"Accept-Encoding": encodings[0] if len(encodings) == 1 and not page else "identity"}
            conn.request("GET", request.path, headers=headers)
            up = conn.getresponse()
            body = up.read()
            if page and b"</head>" in body and (up.getheader("Content-Encoding") or "identity") == "identity":
                body = body.replace(b"</head>", page_head(self.page_kind) + b"</head>", 1)
            keep = {k: v for k, v in up.getheaders() if k.lower() in ("content-type", "content-encoding")}
            keep["Content-Length"] = str(len(body))
            keep["Cache-Control"] = "no-store"
            return Response(up.status, up.reason, Headers(keep), body)
        finally:
            conn.close()

    async def _handler(self, client: websockets.asyncio.server.ServerConnection) -> None:
        sub = [client.subprotocol] if client.subprotocol else None
        role = (self.role(client.request) if client.request is not None else None) or VIEWER
        address = _address(client.remote_address)
        if self._full(address, role):  # two handshakes at once: the count is exact here (no await since)
            self.refused.full += 1
            await client.close(1013, "too many connections")
            return
        self._open[address] = self._open.get(address, 0) + 1
        try:
            await self._serve(client, sub, role, address)
        finally:
            self._open[address] -= 1
            if not self._open[address]:
                del self._open[address]

    async def _serve(self, client: websockets.asyncio.server.ServerConnection, sub: list[Subprotocol] | None,
                     role: str, address: str) -> None:
        key = secrets.token_hex(8)
        taken_in = asyncio.Event()  # viser has taken the client in (after its first camera)
        loop = asyncio.get_running_loop()

        def tell() -> None:  # from viser's thread
            with contextlib.suppress(RuntimeError):  # the gate's loop closed meanwhile
                loop.call_soon_threadsafe(taken_in.set)

        self._taken_in[key] = tell
        try:
            async with websockets.asyncio.client.connect(
                f"ws://127.0.0.1:{self._upstream}/", subprotocols=sub, max_size=MAX_MESSAGE, compression=None,
                additional_headers={GATE_HEADER: self._secret, CONN_HEADER: key, ROLE_HEADER: role,
                                    ADDRESS_HEADER: address}, open_timeout=30,
                close_timeout=CLOSE_TIMEOUT_S,  # its queue unread once the client left: viser's close waits behind it
            ) as upstream:
                async def pump(src: Any, dst: Any) -> None:
                    try:
                        async for message in src:
                            await dst.send(message)
                    except websockets.exceptions.ConnectionClosed:
                        pass  # one side went away (a browser tab closed): the other is closed below

                async def checked(src: Any, dst: Any) -> None:
                    """The client's messages: within its budget (else dropped undecoded), each judged by
                    the input filter before viser sees it."""
                    budget = Budget(time.monotonic())
                    greeted = False  # its first camera: viser takes its clicks (STOP) only from then on
                    try:
                        async for message in src:
                            if not budget.take(time.monotonic()):
                                self._flooded(address, role, budget)
                                if budget.over:
                                    await src.close(1008, f"over the message budget; refused for {BAN_S:g} s")
                                    return
                                continue
                            verdict = self.filter.judge(message, role)
                            first = verdict.kind == "ViewerCameraMessage" and not greeted
                            greeted = greeted or first
                            if verdict.forward and not first and not self._address_allows(address, verdict):
                                self.refused.address += 1
                                refuse("dashboard: over the address's message budget", address,
                                       f"its connections together send more than {ADDRESS_RATE:g} messages a"
                                       " second: dropped", log)
                                continue
                            if verdict.forward:
                                await dst.send(message)
                            elif not verdict.quiet and not self._refused_message(key, role, address, verdict):
                                # viser has not taken the client in yet (its first camera still on its
                                # way): it is told once viser has (counted and logged already)
                                self._tell_later(taken_in, key, verdict)
                    except websockets.exceptions.ConnectionClosed:
                        pass

                tasks = {asyncio.create_task(checked(client, upstream)), asyncio.create_task(pump(upstream, client))}
                done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for task in pending:
                    task.cancel()
                for task in done:
                    task.exception()  # retrieved: never an "exception was never retrieved" on stderr
        except (websockets.exceptions.ConnectionClosed, OSError):
            pass
        finally:
            self._taken_in.pop(key, None)  # a connection that ended before viser took it in

    def _address_allows(self, address: str, verdict: Verdict) -> bool:
        """Whether all of ``address``'s connections together may have one more message forwarded:
        sixteen tabs each within its own budget are not sixteen budgets. STOP always passes (and a
        connection's first camera, without which viser would not take its STOP)."""
        if verdict.uuid and self.filter.viewer_may(verdict.uuid):
            return True
        now = time.monotonic()
        budget = self._address_budget.get(address)
        if budget is None:
            if len(self._address_budget) > 4096:  # addresses come and go: forget the full ones
                self._address_budget = {a: b for a, b in self._address_budget.items() if now - b.at < 60.0}
            budget = self._address_budget[address] = Budget(now, ADDRESS_RATE, ADDRESS_BURST)
        return budget.take(now)

    def _flooded(self, address: str, role: str, budget: Budget) -> None:
        """A message over a connection's budget: counted, logged briefly per address; a connection
        that stays over it costs its address ``BAN_S`` of refusals."""
        self.refused.flood += 1
        if budget.over:
            self.refused.cut += 1
            self._ban(address)
        what = f"closed, address refused for {BAN_S:g} s" if budget.over else "dropped"
        refuse(f"dashboard: over a connection's message budget ({what.split(',')[0]})", address,
               f"{role} sends more than {RATE:g} messages a second: {what}", log)

    def _refused_message(self, key: str, role: str, address: str, verdict: Verdict) -> bool:
        """Count it, log it (briefly, per address), and tell that client alone what is in force;
        False: there was no client to tell yet."""
        self.refused.messages += 1
        refuse("dashboard: message refused", address, f"{role}: {one_line(verdict.why)}", log)
        return self._tell(key, verdict)

    def _tell_later(self, taken_in: asyncio.Event, key: str, verdict: Verdict) -> None:
        """Tell the refusal once viser has taken the client in (one waits per connection: the
        notices are throttled to one a second anyway)."""
        if key in self._telling:
            return

        async def later() -> None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(taken_in.wait(), REGISTER_WAIT_S)
                self._tell(key, verdict)

        task = self._telling[key] = asyncio.get_running_loop().create_task(later())  # kept: tasks are held weakly
        task.add_done_callback(lambda _: self._telling.pop(key, None))

    def _tell(self, key: str, verdict: Verdict) -> bool:
        """Tell the client of gate connection ``key`` of a refusal (the value in force, a notice),
        within the notice throttles; False if viser has no such client (yet)."""
        client = self.server.get_clients().get(self._client_of.get(key, -1))
        if client is None:
            return False
        handle = self.filter.handle(verdict.uuid) if verdict.uuid else None
        if handle is not None and self._notice_throttle.due(("value", key, verdict.uuid)) >= 0:
            # the browser shows the value it sent: put it back (once a second per control is enough)
            viser_private.send_to(client, GuiUpdateMessage(verdict.uuid, {"value": handle.value}))
        if self._notice_throttle.due(("notice", key)) >= 0:
            client.add_notification("Refused", one_line(verdict.why, 300), auto_close_seconds=6.0, color="yellow")
        return True

    def _run(self, port: int) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        self._stop = asyncio.Event()

        async def main() -> None:
            try:
                server = await websockets.asyncio.server.serve(
                    self._handler, self.host, port, process_request=self._process_request,
                    max_size=MAX_CLIENT_MESSAGE, compression=None,
                    close_timeout=CLOSE_TIMEOUT_S,
                    select_subprotocol=lambda _, offered: next(
                        (Subprotocol(p) for p in offered if p.startswith("viser-v")), None),
                )
            except OSError as exc:
                self._error = exc
                self._bound.set()
                return
            sockets = server.sockets
            self.port = sockets[0].getsockname()[1] if sockets else port
            self._bound.set()
            assert self._stop is not None
            await self._stop.wait()
            server.close()
            await server.wait_closed()

        try:
            loop.run_until_complete(main())
        finally:
            loop.close()

    def close(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        self._thread.join(10.0)


def _address(remote: Any) -> str:
    """The host part of a peer's address (its port changes with every connection)."""
    if isinstance(remote, (tuple, list)) and remote:
        return str(remote[0])
    return str(remote)


def quietly(fn: Callable[[], T]) -> T:
    """``fn()`` with stdout swallowed: viser prints a banner with its own (loopback) address,
    whatever ``verbose`` says, and people must see only the gate's."""
    with contextlib.redirect_stdout(io.StringIO()):
        return fn()


def serve_gated(host: str, port: int, token: str | None = None,
                viewer_token: str | None = None) -> tuple[viser.ViserServer, Gate]:
    """A viser server on a loopback port of its own, and the gate that serves it at host:port.
    Raises OSError (port taken, address not on this machine) with the viser server stopped."""
    server = quietly(lambda: viser.ViserServer(host="127.0.0.1", port=0, verbose=False))
    try:
        gate = Gate(server, host, port, token, viewer_token)
    except BaseException:
        quietly(server.stop)
        raise
    return server, gate
