"""Foxglove live's front door in the Foxglove process (app.services.foxglove_live.FoxgloveProcess):
the clients connect here, and each connection is relayed byte for byte to the SDK's server, which
listens on 127.0.0.1 only, on a port of its own. What the SDK does not offer, the door does:

* **both subprotocols.** The SDK's handshake accepts only ``foxglove.sdk.v1``; a client that offers
  only the older ``foxglove.websocket.v1`` (the same messages under the older name: older Foxglove
  builds, most open-source clients) has its offer passed on as ``foxglove.sdk.v1`` and the SDK's
  answer given back under the name the client offered;
* **a client that does not read is dropped.** Each client's socket sends through a small kernel
  buffer (``SNDBUF``) and a bounded one here (``HIGH_WATER``); when that stays full for
  ``STALL_S`` seconds the client is disconnected (said once through app.refusals). Meanwhile
  the door stops reading the SDK's side for that client alone, so the SDK drops that client's
  oldest messages (its per-client backlog) and no other client waits;
* **TLS**, when served off this machine (the SDK's side is plain, on loopback).

A request head longer than ``HEAD_MAX`` or slower than ``HEAD_S`` is closed unanswered."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import ssl
import tempfile
import threading

from app.refusals import refuse

NEW, OLD = "foxglove.sdk.v1", "foxglove.websocket.v1"
STALL_S = 10.0  # a client whose send buffer stays full this long is disconnected
HIGH_WATER = 256 * 1024  # bytes buffered here per client before the door stops reading the SDK for it
SNDBUF = 64 * 1024  # the kernel's send buffer per client socket (small: a silent client fills it soon)
HEAD_MAX = 16 * 1024  # the opening handshake's request head
HEAD_S = 10.0  # time to send it


def _offer(head: bytes) -> tuple[bytes, bool]:
    """The request head as the SDK accepts it, and whether the client offered only the older name."""
    lines = head.split(b"\r\n")
    offered = [v.strip().decode("latin-1") for line in lines[1:] if line.lower().startswith(b"sec-websocket-protocol:")
               for v in line.split(b":", 1)[1].split(b",")]
    if NEW in offered or OLD not in offered:
        return head, False
    kept = [line for line in lines if not line.lower().startswith(b"sec-websocket-protocol:")]
    return b"\r\n".join([kept[0], f"Sec-WebSocket-Protocol: {NEW}".encode(), *kept[1:]]), True


def _answer(head: bytes) -> bytes:
    """The SDK's answer with the subprotocol named as the client offered it (the older name)."""
    return b"\r\n".join(f"Sec-WebSocket-Protocol: {OLD}".encode() if line.lower().startswith(b"sec-websocket-protocol:")
                        else line for line in head.split(b"\r\n"))


def tls_context(cert: bytes, key: bytes) -> ssl.SSLContext:
    """A server context from PEM bytes (written to a private temporary folder for the ssl module,
    removed at once); ssl.SSLError or ValueError if they are not a usable pair."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    with tempfile.TemporaryDirectory(prefix="omniformation-tls-") as tmp:
        paths = []
        for name, data in (("cert.pem", cert), ("key.pem", key)):
            path = os.path.join(tmp, name)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            paths.append(path)
        ctx.load_cert_chain(paths[0], paths[1])
    return ctx


class Relay:
    """The door: serves ``host:port`` (TLS with ``tls``), each connection relayed to the SDK at
    127.0.0.1:``upstream``; its own event loop on a thread. OSError if it cannot bind; ssl.SSLError
    or ValueError for TLS material that is not usable."""

    def __init__(self, host: str, port: int, upstream: int, tls: tuple[bytes, bytes] | None = None,
                 stall_s: float = STALL_S) -> None:
        self.upstream = upstream
        self.stall_s = stall_s
        self.connected = 0  # connections relayed (handshake passed on)
        self.dropped = 0  # clients disconnected for not reading
        ctx = tls_context(*tls) if tls else None
        self.loop = asyncio.new_event_loop()
        try:
            self.server = self.loop.run_until_complete(
                asyncio.start_server(self._serve, host, port, ssl=ctx, limit=HEAD_MAX, backlog=512))
        except BaseException:
            self.loop.close()
            raise
        self.port = int(self.server.sockets[0].getsockname()[1])
        self._thread = threading.Thread(target=self.loop.run_forever, name="foxglove-door", daemon=True)
        self._thread.start()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        sock = writer.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SNDBUF)
        writer.transport.set_write_buffer_limits(high=HIGH_WATER)
        peer = writer.get_extra_info("peername") or ("?", 0)
        client = f"{peer[0]}:{peer[1]}"
        up_w: asyncio.StreamWriter | None = None
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_S)
            head, old = _offer(head)
            up_r, up_w = await asyncio.open_connection("127.0.0.1", self.upstream)
            up_w.write(head)
            await up_w.drain()
            answer = await asyncio.wait_for(up_r.readuntil(b"\r\n\r\n"), HEAD_S)
            writer.write(_answer(answer) if old else answer)
            self.connected += 1
            down = asyncio.ensure_future(self._down(up_r, writer, client))
            up = asyncio.ensure_future(self._up(reader, up_w))
            done, pending = await asyncio.wait({down, up}, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            # every outcome retrieved (a reset is how a connection may end): never a line on stderr
            await asyncio.gather(*done, *pending, return_exceptions=True)
        except (TimeoutError, OSError, EOFError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError, ssl.SSLError):
            pass
        finally:
            for w in (writer, up_w):
                if w is not None:
                    with contextlib.suppress(Exception):
                        w.transport.abort()

    async def _down(self, up_r: asyncio.StreamReader, writer: asyncio.StreamWriter, client: str) -> None:
        """The SDK's messages to the client; a client that leaves its buffer full for stall_s is dropped."""
        with contextlib.suppress(OSError):
            await self._down_until_stalled(up_r, writer, client)

    async def _down_until_stalled(self, up_r: asyncio.StreamReader, writer: asyncio.StreamWriter, client: str) -> None:
        while True:
            data = await up_r.read(65536)
            if not data:
                return
            writer.write(data)
            try:
                await asyncio.wait_for(writer.drain(), self.stall_s)
            except TimeoutError:
                self.dropped += 1
                refuse("foxglove: a client that does not read, disconnected", client,
                       f"its send buffer stayed full for {self.stall_s:g} s")
                return

    @staticmethod
    async def _up(reader: asyncio.StreamReader, up_w: asyncio.StreamWriter) -> None:
        """The client's messages to the SDK (which refuses what it does not take)."""
        with contextlib.suppress(OSError):
            while True:
                data = await reader.read(65536)
                if not data:
                    return
                up_w.write(data)
                await up_w.drain()

    def close(self) -> None:
        def stop() -> None:
            self.server.close()
            self.loop.stop()

        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(stop)
        self._thread.join(5.0)
