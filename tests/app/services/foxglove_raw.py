"""A hostile Foxglove client on a raw socket, written from the protocols' documents alone:
RFC 6455 (the opening handshake, frames: FIN + opcode, a masked payload from a client, 7/16/64-bit
lengths) and Foxglove's WebSocket protocol (subprotocol ``foxglove.sdk.v1`` or the older
``foxglove.websocket.v1``; the server's JSON ``serverInfo`` and ``advertise``; a client's JSON
``subscribe``). It can stop reading at any point: a socket nobody reads is what a stalled viewer
looks like to the server. The tests and the bench use it."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
from typing import Any


class Refused(OSError):
    """The server answered the opening handshake with something other than 101."""


def _mask(payload: bytes) -> bytes:
    key = os.urandom(4)
    return key + bytes(b ^ key[i % 4] for i, b in enumerate(payload))


def frame(payload: bytes, opcode: int = 0x1) -> bytes:
    """One final client frame (masked, as RFC 6455 requires of a client)."""
    n = len(payload)
    if n < 126:
        head = struct.pack("!BB", 0x80 | opcode, 0x80 | n)
    elif n < 1 << 16:
        head = struct.pack("!BBH", 0x80 | opcode, 0x80 | 126, n)
    else:
        head = struct.pack("!BBQ", 0x80 | opcode, 0x80 | 127, n)
    return head + _mask(payload)


class RawClient:
    """Opening handshake on a plain socket; ``protocol`` is the subprotocol the server chose."""

    def __init__(self, host: str, port: int, subprotocols: str = "foxglove.sdk.v1", timeout: float = 10.0,
                 rcvbuf: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:  # a small receive window: a silent client's socket fills sooner
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(timeout)
        self.sock.connect((host, port))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {subprotocols}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise Refused(f"closed during the handshake: {head!r}")
            head += chunk
        lines = head.decode("latin-1").split("\r\n")
        if not lines[0].startswith("HTTP/1.1 101"):
            raise Refused(lines[0])
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
        self.protocol = headers.get("sec-websocket-protocol", "")
        self._buf = b""

    def _read(self, n: int) -> bytes:
        while len(self._buf) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("closed by the server")
            self._buf += chunk
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def recv(self) -> tuple[int, bytes]:
        """The next server frame: (opcode, payload) (a server's frames are not masked)."""
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack("!H", self._read(2))[0]
        elif n == 127:
            n = struct.unpack("!Q", self._read(8))[0]
        return b0 & 0x0F, self._read(n)

    def recv_json(self, op: str) -> dict[str, Any]:
        """Text frames until one whose ``op`` is ``op``."""
        while True:
            opcode, payload = self.recv()
            if opcode == 0x8:
                raise ConnectionError(f"closed by the server: {payload[2:]!r}")
            if opcode == 0x1:
                msg = json.loads(payload)
                if msg.get("op") == op:
                    return dict(msg)

    def send_json(self, msg: Any) -> None:
        self.sock.sendall(frame(json.dumps(msg).encode()))

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def subscribe_all(self) -> list[dict[str, Any]]:
        """Read up to ``advertise`` and subscribe to every channel in it; the channels."""
        channels = list(self.recv_json("advertise")["channels"])
        self.send_json({"op": "subscribe", "subscriptions": [{"id": 1 + k, "channelId": c["id"]}
                                                              for k, c in enumerate(channels)]})
        return channels

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


def self_signed(folder: Any) -> tuple[Any, Any]:
    """A certificate for 127.0.0.1 and its PKCS#8 key, PEM, written in ``folder``: (cert, key) paths."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=1))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = folder / "cert.pem", folder / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path
