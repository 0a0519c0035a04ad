"""The whole fleet in one MCAP (``omniformation fleet --record FILE.mcap``): a channel per
leader and kind (``/fleet/<id>/state``, ``/fleet/<id>/events``) and the arena's
(``/fleet/arena/truth``, ``/fleet/arena/events``), each message the JSON payload as it came
over the bus (docs/fleet-protocol.md), logged at the time it arrived.

Each leader still records its own session as before; this is the fleet's view. Messages go
through a bounded queue to a writer thread (the bus's threads never wait on the disk); a
full queue drops the newest and counts it; a disk error ends the recording, closes what was
written so far, and says why in ``status()``.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from pathlib import Path
from typing import Any

from app.recording.mcap_out import SessionWriter
from app.recording.schema import CHUNK_BYTES, CHUNK_SECONDS

QUEUE_MAX = 4096
_JSON_SCHEMA = json.dumps({"type": "object", "description": "as in docs/fleet-protocol.md"}).encode()


class FleetRecorder:
    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = open(path, "xb")  # noqa: SIM115 - open for the session's life; never over an existing file
        self._writer = SessionWriter(self._file, CHUNK_BYTES, CHUNK_SECONDS)  # the sessions' own writer
        self._writer.start(library="omniformation fleet")
        self._schema = self._writer.register_schema("omniformation.FleetMessage", "jsonschema", _JSON_SCHEMA)
        self._channels: dict[str, int] = {}
        self._queue: queue.Queue[tuple[str, int, bytes] | None] = queue.Queue(QUEUE_MAX)
        self.written = 0
        self.dropped = 0
        self.failure = ""
        self._thread = threading.Thread(target=self._run, name="omniformation-fleet-recorder", daemon=True)
        self._thread.start()

    def write(self, topic: str, msg: dict[str, Any]) -> None:
        """From any thread: ``topic`` as ``<id>/state``, ``arena/truth``, …"""
        if self.failure:
            return
        try:
            self._queue.put_nowait((topic, time.time_ns(), json.dumps(msg, separators=(",", ":")).encode()))
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            topic, t_ns, data = item
            if self.failure:
                continue
            try:
                channel = self._channels.get(topic)
                if channel is None:
                    channel = self._writer.register_channel(f"/fleet/{topic}", "json", self._schema)
                    self._channels[topic] = channel
                self._writer.add_message(channel, log_time=t_ns, data=data, publish_time=t_ns)
                self.written += 1
            except OSError as exc:
                self.failure = f"recording stopped: {exc.strerror or exc}"

    def status(self) -> str:
        if self.failure:
            return f"{self.failure} ({self.written} messages in {self.path.name})"
        lost = f", {self.dropped} dropped (disk too slow)" if self.dropped else ""
        return f"recording {self.path.name}: {self.written} messages, {len(self._channels)} channels{lost}"

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(30.0)
        try:
            self._writer.finish()
        except OSError as exc:
            self.failure = self.failure or f"recording not finished: {exc.strerror or exc}"
        finally:
            self._file.close()
