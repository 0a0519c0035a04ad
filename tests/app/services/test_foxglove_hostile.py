"""Foxglove live against hostile clients (docs/foxglove.md, docs/safety.md), written from the
protocols' documents alone (tests/app/services/foxglove_raw.py: RFC 6455 and Foxglove's WebSocket
protocol on a raw socket): clients that never read, a flood of messages the server refuses, each
subprotocol. `run --foxglove` serves from a process of its own (FoxgloveProcess), fed by the loop."""

from __future__ import annotations

import json
import os
import re
import threading

import ssl

import pytest
from websockets.sync.client import connect

from app.backends.world import Backends
from app.live.config import DEFAULT_CONFIG, load_service_config
from app.live.loop import ServiceLoop
from app.params import MAX_FOLLOWERS, Params, ParamsStore
from app.refusals import FIRSTS_PER_WINDOW, Refusals
from tests.app.services.foxglove_raw import RawClient, Refused, frame, self_signed
from tests.helpers import wait_for

SILENT = 300
STALL_S = 2.0  # a client that leaves its send buffer full this long is dropped (10 s in `run`)


@pytest.fixture
def served():
    """The live loop (vision, 3 followers, 30 Hz) running, served by a FoxgloveProcess."""
    from app.services.foxglove_process import FoxgloveProcess

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    store = ParamsStore(Params(n_followers=3))
    loop = ServiceLoop(store, Backends(seed=2, camera=config.camera()), rate_hz=30.0)
    live = FoxgloveProcess("127.0.0.1", 0, params=store.get(), stall_s=STALL_S)
    loop.subscribe(live.on_tick)
    store.subscribe(live.on_params)
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    try:
        yield loop, live
    finally:
        loop.stop()
        thread.join(30.0)
        live.close()


def _sockets() -> int:
    """Sockets this process holds open."""
    n = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            n += os.readlink(f"/proc/self/fd/{fd}").startswith("socket:")
        except OSError:
            pass
    return n


def test_clients_that_never_read_cannot_slow_the_loop(served):
    loop, live = served
    wait_for(lambda: loop.tick_count > 30, 120.0, "the loop's first ticks")
    before = _sockets()
    silent = []
    try:
        for _ in range(SILENT):  # each subscribes to every channel, then never reads its socket again
            c = RawClient("127.0.0.1", live.port, rcvbuf=4096)
            c.subscribe_all()
            silent.append(c)
        # the clients' sockets are the Foxglove process's: ours grew by our own ends only
        assert _sockets() - before <= SILENT + 2
        k0, skipped0, sent0 = loop.tick_count, loop.ticks_dropped, live.sent
        wait_for(lambda: loop.tick_count >= k0 + 90, 60.0, "90 more ticks with the silent clients connected")
        assert loop.ticks_dropped == skipped0, "the loop skipped ticks while Foxglove clients stayed silent"
        assert live.sent > sent0  # the states still go to the Foxglove process
        fresh = RawClient("127.0.0.1", live.port)  # and a new client is served among them
        channels = {c["topic"]: c["id"] for c in fresh.subscribe_all()}
        sub = 1 + list(channels).index("/omniformation/tick")
        while True:
            opcode, payload = fresh.recv()
            if opcode == 0x2 and payload[0] == 0x01 and int.from_bytes(payload[1:5], "little") == sub:
                assert len(json.loads(payload[13:])["p_est"]) == 3
                break
        fresh.close()
        # and each silent client is disconnected by the server once its buffer has stayed full for STALL_S
        assert all(_closed_by_server(c) for c in silent)
    finally:
        for c in silent:
            c.close()


def _closed_by_server(c: RawClient) -> bool:
    """Read what the socket holds until the server's end (True) or 60 s of nothing (False)."""
    c.sock.settimeout(60.0)
    try:
        while c.sock.recv(1 << 20):
            pass
        return True
    except ConnectionError:
        return True
    except OSError:
        return False


def test_a_flood_of_refused_messages_adds_at_most_50_lines(capfd):
    """10^5 messages the server refuses (not JSON, unknown ops, malformed subscribe and advertise),
    in bursts of 2,000 from 50 connections (the SDK cuts a connection that sends a few thousand in
    one burst: a client that wants to flood must come back), add at most 50 lines to stderr, and
    every refusal the server saw is said or counted."""
    from app.services.foxglove_process import FoxgloveProcess

    live = FoxgloveProcess("127.0.0.1", 0)
    bad = [b"not json", json.dumps({"op": "bogus"}).encode(), json.dumps({"op": "subscribe"}).encode(),
           json.dumps({"op": "advertise", "channels": [{"id": "x"}]}).encode()]
    burst = b"".join(frame(m) for m in bad) * 500
    sent = 0
    try:
        for _ in range(50):
            c = RawClient("127.0.0.1", live.port)
            c.recv_json("advertise")
            c.send_raw(burst)
            sent += 4 * 500
            c.sock.settimeout(10.0)
            try:  # ask the server to close (RFC 6455 close frame) and read until it has: the burst is behind
                c.send_raw(frame(b"\x03\xe8", opcode=0x8))
                while c.recv()[0] != 0x8:
                    pass
            except (ConnectionError, OSError):
                pass
            c.close()
        probe = RawClient("127.0.0.1", live.port)  # the server still serves
        probe.recv_json("advertise")
        probe.close()
    finally:
        live.close()  # the process says what it still counts as it ends
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert sent == 10**5
    assert 1 <= len(lines) <= 50, "\n".join(lines[:60])
    said = sum(1 for line in lines if "more of this kind are counted" in line)
    counted = sum(int(m.group(1)) for m in re.finditer(r": (\d+) more from", err))
    assert said + counted >= 0.9 * sent, (said, counted, lines)


def test_the_limit_holds_for_any_flood():
    """The rule itself, on a clock the test moves: 10^5 refusals of 3 kinds from 1,000 clients
    over 60 s make at most (firsts + one summary) per kind per 10 s window, and lose no count."""
    lines: list[str] = []
    now = [0.0]
    r = Refusals(lines.append, clock=lambda: now[0])
    for k in range(10**5):
        now[0] = k * 60.0 / 10**5
        r.refuse(("foxglove: invalid message", "bus: bad signature", "page: refused")[k % 3], f"10.0.0.{k % 1000}:1",
                 "why")
    r.flush(final=True)
    windows = 7  # 0-10, ..., 60 s, and the final flush
    assert len(lines) <= 3 * (FIRSTS_PER_WINDOW + 1) * windows
    assert len(lines) <= 130
    named = sum(1 for line in lines if "more of this kind" in line)
    counted = sum(int(m.group(1)) for line in lines if (m := re.search(r": (\d+) more from", line)))
    assert named + counted == 10**5
    assert r.total["bus: bad signature"] == 33333


def test_subprotocols_as_foxglove_sdk_allows(served):
    _, live = served
    c = RawClient("127.0.0.1", live.port, "foxglove.sdk.v1")
    assert c.protocol == "foxglove.sdk.v1"
    assert c.recv_json("serverInfo")["op"] == "serverInfo"
    c.close()
    both = RawClient("127.0.0.1", live.port, "foxglove.websocket.v1, foxglove.sdk.v1")
    assert both.protocol == "foxglove.sdk.v1"
    both.close()
    old = RawClient("127.0.0.1", live.port, "foxglove.websocket.v1")  # the older name alone: answered under it
    assert old.protocol == "foxglove.websocket.v1"
    assert old.recv_json("serverInfo")["op"] == "serverInfo"
    assert old.subscribe_all()
    old.close()
    with pytest.raises(Refused, match="400"):  # a client that offers neither is refused
        RawClient("127.0.0.1", live.port, "chat")


def test_tls_is_served_by_the_door_with_either_subprotocol(tmp_path):
    from app.services.foxglove_process import FoxgloveProcess

    cert, key = self_signed(tmp_path)
    live = FoxgloveProcess("127.0.0.1", 0, tls=(cert.read_bytes(), key.read_bytes()))
    try:
        assert live.url.startswith("wss://")
        ctx = ssl.create_default_context(cafile=str(cert))
        ctx.check_hostname = False
        for offer in (["foxglove.sdk.v1"], ["foxglove.websocket.v1"]):
            with connect(live.url, subprotocols=offer, ssl=ctx, open_timeout=10) as ws:
                assert ws.subprotocol == offer[0]
                assert json.loads(ws.recv(10))["op"] == "serverInfo"
        with pytest.raises(OSError):  # plain ws:// to a wss:// server: no handshake
            RawClient("127.0.0.1", live.port, timeout=5.0)
    finally:
        live.close()


def test_replay_and_fleet_serve_behind_the_same_door():
    """`replay --foxglove` (serve_foxglove) and `fleet --foxglove` (serve_fleet) stand behind the
    door `run` uses: the older subprotocol name alone is answered under it, as the newer one."""
    from app.services.foxglove_attach import FoxglovePlan, serve_fleet, serve_foxglove

    said: list[str] = []
    replay = serve_foxglove(FoxglovePlan("127.0.0.1", 0), said.append)
    _, fleet = serve_fleet(FoxglovePlan("127.0.0.1", 0), None, said.append)
    try:
        for live in (replay, fleet):
            assert f":{live.door.port}" in live.url and live.door.port != live.server.server.port
            for offer in ("foxglove.websocket.v1", "foxglove.sdk.v1"):
                c = RawClient("127.0.0.1", live.door.port, offer)
                assert c.protocol == offer and c.recv_json("serverInfo")["op"] == "serverInfo"
                c.close()
        assert all("Foxglove live at ws://127.0.0.1:" in line for line in said)
    finally:
        replay.close()
        fleet.close()
