"""SipHash-2-4 with a 64-bit tag (Aumasson and Bernstein, 2012): the radio frames' MAC (pure).

Chosen for the followers' small microcontrollers: a 128-bit key, 64-bit additions, rotations and
XORs only (no tables, no multiplications), 2 rounds per 8-byte word and 4 to finish, so a 40-byte
frame costs about 20 rounds. firmware/omni_follower.c has the same in C99; both are checked
against the algorithm's published test vectors (tests/core/link/test_radio_auth.py).
"""

from __future__ import annotations

import struct

_MASK = 0xFFFFFFFFFFFFFFFF


def _rotl(x: int, b: int) -> int:
    return ((x << b) | (x >> (64 - b))) & _MASK


def _rounds(v0: int, v1: int, v2: int, v3: int, n: int) -> tuple[int, int, int, int]:
    for _ in range(n):
        v0 = (v0 + v1) & _MASK
        v1 = _rotl(v1, 13) ^ v0
        v0 = _rotl(v0, 32)
        v2 = (v2 + v3) & _MASK
        v3 = _rotl(v3, 16) ^ v2
        v0 = (v0 + v3) & _MASK
        v3 = _rotl(v3, 21) ^ v0
        v2 = (v2 + v1) & _MASK
        v1 = _rotl(v1, 17) ^ v2
        v2 = _rotl(v2, 32)
    return v0, v1, v2, v3


def siphash24(key: bytes, message: bytes) -> int:
    """The 64-bit SipHash-2-4 of ``message`` under the 16-byte ``key`` (as an integer; on the wire
    it is written little-endian, as the reference implementation writes it)."""
    if len(key) != 16:
        raise ValueError(f"a SipHash key is 16 bytes, not {len(key)}")
    k0, k1 = struct.unpack("<QQ", key)
    v0, v1 = k0 ^ 0x736F6D6570736575, k1 ^ 0x646F72616E646F6D
    v2, v3 = k0 ^ 0x6C7967656E657261, k1 ^ 0x7465646279746573
    n = len(message)
    end = n - n % 8
    for i in range(0, end, 8):
        (m,) = struct.unpack_from("<Q", message, i)
        v3 ^= m
        v0, v1, v2, v3 = _rounds(v0, v1, v2, v3, 2)
        v0 ^= m
    last = int.from_bytes(message[end:], "little") | ((n & 0xFF) << 56)
    v3 ^= last
    v0, v1, v2, v3 = _rounds(v0, v1, v2, v3, 2)
    v0 ^= last
    v2 ^= 0xFF
    v0, v1, v2, v3 = _rounds(v0, v1, v2, v3, 4)
    return v0 ^ v1 ^ v2 ^ v3


def tag(key: bytes, message: bytes) -> bytes:
    """The 8-byte tag on the wire: the SipHash-2-4 value, little-endian."""
    return struct.pack("<Q", siphash24(key, message))
