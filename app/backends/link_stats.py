"""What the serial link counts per follower (app.backends.serial_link): every command written is
exactly one of answered, late, lost or pending, beside the round trip, the odometry, the status
and, on a shared radio, ownership and authentication."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from core.link import protocol as p

QUALITY_WINDOW = 30  # recent commands a follower's loss share is taken over (1 s at 30 Hz)


@dataclass
class FollowerLinkStats:
    """One follower's counts: ``sent == answered + late + lost + pending`` (pending: written and
    not yet answered nor given up, see SerialLink.pending)."""

    address: int
    sent: int = 0  # SET_VELOCITY frames written to the port
    answered: int = 0  # ... answered by a matching ACK within REPLY_TIMEOUT_S
    late: int = 0  # ... answered after it
    lost: int = 0  # ... never answered (so far)
    crc_errors: int = 0  # refused frames (bad CRC, length, type) whose address byte named this follower
    echoes: int = 0  # our own frames to this address that came back (an echoing line)
    unmatched: int = 0  # well-formed replies from this address that answer nothing we sent
    recent: deque[bool] = field(default_factory=lambda: deque(maxlen=QUALITY_WINDOW))  # answered in time?
    rtt_ms: float = math.nan  # last round trip
    rtt_mean_ms: float = math.nan  # running mean
    last_reply: float = -math.inf  # monotonic time of the last answer in time (see module doc)
    prev_reply: float = -math.inf  # ... and of the one before it
    v_meas: float = 0.0
    w_meas: float = 0.0
    left_ticks: int = 0
    right_ticks: int = 0
    flags: int = 0
    battery_mv: int = 0
    # protocol 2 (a radio id given): whether this leader owns the robot, who does as far as it said
    owned: bool = False
    owner: int = 0
    next_claim: float = -math.inf
    stale: int = 0  # DRIVEs the robot refused as computed from too old an observation
    # protocol 3
    authenticated: int = 0  # authenticated replies taken (it speaks protocol 3 with our key)
    legacy: bool = False  # answered a plain PING and nothing authenticated: protocol 1 or 2
    forged: int = 0  # replies from this address whose tag did not verify under our key
    refusals: p.RadioCounts = field(default_factory=p.RadioCounts)  # what the robot refused (its STATUS)
