"""XXH3-128 (xxHash 0.8, default secret, seed 0), portable and pure: rmw_zenoh makes an entity's
16-byte GID from its liveliness token with it (liveliness_utils.cpp, ``Entity::Entity``: the
low 64 bits then the high 64 bits, little-endian). Slow and simple; a GID is made once per entity.
tests/core/test_rmw_zenoh.py checks it against the xxHash library where one is installed."""

from __future__ import annotations

M = (1 << 64) - 1
P32_1, P32_2, P32_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D
P64_1, P64_2, P64_3, P64_4, P64_5 = (0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9,
                                     0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5)
MX1, MX2 = 0x165667919E3779F9, 0x9FB21C651E98DF25
SECRET = bytes.fromhex(  # XXH3's default secret (XXH3_kSecret), 192 bytes
    "b8fe6c3923a44bbe7c01812cf721ad1cded46de9839097db7240a4a4b7b3671fcb79e64eccc0e578825ad07dccff7221"
    "b8084674f743248ee03590e6813a264c3c2852bb91c300cb88d0658b1b532ea371644897a20df94e3819ef46a9deacd8"
    "a8fa763fe39c343ff9dcbbc7c70b4f1d8a51e04bcdb45931c89f7ec9d9787364eac5ac8334d3ebc3c581a0fffa1363eb"
    "170ddd51b7f0da49d316552629d4689e2b16be587d47a1fc8ff8b8d17ad031ce45cb3a8f95160428afd7fbcabb4b407e")
STRIPE, RATE, ACCS = 64, 8, 8


def _r64(b: bytes, i: int) -> int:
    return int.from_bytes(b[i:i + 8], "little")


def _r32(b: bytes, i: int) -> int:
    return int.from_bytes(b[i:i + 4], "little")


def _mul128(a: int, b: int) -> tuple[int, int]:
    p = a * b
    return p & M, p >> 64


def _fold(a: int, b: int) -> int:
    lo, hi = _mul128(a, b)
    return lo ^ hi


def _avalanche(h: int) -> int:
    h ^= h >> 37
    h = (h * MX1) & M
    return h ^ (h >> 32)


def _avalanche64(h: int) -> int:  # XXH64's
    h ^= h >> 33
    h = (h * P64_2) & M
    h ^= h >> 29
    h = (h * P64_3) & M
    return h ^ (h >> 32)


def _mix16(d: bytes, i: int, s: int) -> int:
    return _fold(_r64(d, i) ^ _r64(SECRET, s), _r64(d, i + 8) ^ _r64(SECRET, s + 8))


def _mix32(acc: tuple[int, int], d: bytes, i1: int, i2: int, s: int) -> tuple[int, int]:
    lo = (acc[0] + _mix16(d, i1, s)) & M
    lo ^= (_r64(d, i2) + _r64(d, i2 + 8)) & M
    hi = (acc[1] + _mix16(d, i2, s + 16)) & M
    hi ^= (_r64(d, i1) + _r64(d, i1 + 8)) & M
    return lo, hi


def _finish(acc: tuple[int, int], n: int) -> tuple[int, int]:
    lo = _avalanche((acc[0] + acc[1]) & M)
    hi = (acc[0] * P64_1 + acc[1] * P64_4 + n * P64_2) & M
    return lo, (-_avalanche(hi)) & M


def _short(d: bytes, n: int) -> tuple[int, int]:
    if n > 8:
        lo_in, hi_in = _r64(d, 0), _r64(d, n - 8)
        m_lo, m_hi = _mul128(lo_in ^ hi_in ^ (_r64(SECRET, 32) ^ _r64(SECRET, 40)), P64_1)
        m_lo = (m_lo + ((n - 1) << 54)) & M
        hi_in ^= _r64(SECRET, 48) ^ _r64(SECRET, 56)
        m_hi = (m_hi + hi_in + (hi_in & 0xFFFFFFFF) * (P32_2 - 1)) & M
        m_lo ^= int.from_bytes(m_hi.to_bytes(8, "little"), "big")
        h_lo, h_hi = _mul128(m_lo, P64_2)
        h_hi = (h_hi + m_hi * P64_2) & M
        return _avalanche(h_lo), _avalanche(h_hi)
    if n >= 4:
        keyed = (_r32(d, 0) + (_r32(d, n - 4) << 32)) ^ (_r64(SECRET, 16) ^ _r64(SECRET, 24))
        m_lo, m_hi = _mul128(keyed, (P64_1 + (n << 2)) & M)
        m_hi = (m_hi + (m_lo << 1)) & M
        m_lo ^= m_hi >> 3
        m_lo ^= m_lo >> 35
        m_lo = (m_lo * MX2) & M
        m_lo ^= m_lo >> 28
        return m_lo, _avalanche(m_hi)
    if n:
        lo32 = (d[0] << 16) | (d[n >> 1] << 24) | d[n - 1] | (n << 8)
        swapped = int.from_bytes(lo32.to_bytes(4, "little"), "big")
        hi32 = ((swapped << 13) | (swapped >> 19)) & 0xFFFFFFFF
        return (_avalanche64(lo32 ^ (_r32(SECRET, 0) ^ _r32(SECRET, 4))),
                _avalanche64(hi32 ^ (_r32(SECRET, 8) ^ _r32(SECRET, 12))))
    return (_avalanche64(_r64(SECRET, 64) ^ _r64(SECRET, 72)), _avalanche64(_r64(SECRET, 80) ^ _r64(SECRET, 88)))


def _accumulate(acc: list[int], d: bytes, at: int, s: int) -> None:
    for lane in range(ACCS):
        v = _r64(d, at + 8 * lane)
        k = v ^ _r64(SECRET, s + 8 * lane)
        acc[lane ^ 1] = (acc[lane ^ 1] + v) & M
        acc[lane] = (acc[lane] + (k & 0xFFFFFFFF) * (k >> 32)) & M


def _long(d: bytes, n: int) -> tuple[int, int]:
    acc = [P32_3, P64_1, P64_2, P64_3, P64_4, P32_2, P64_5, P32_1]
    per_block = (len(SECRET) - STRIPE) // RATE
    block = STRIPE * per_block
    blocks = (n - 1) // block
    for b in range(blocks):
        for k in range(per_block):
            _accumulate(acc, d, b * block + k * STRIPE, k * RATE)
        for lane in range(ACCS):  # scramble
            a = acc[lane] ^ (acc[lane] >> 47) ^ _r64(SECRET, len(SECRET) - STRIPE + 8 * lane)
            acc[lane] = (a * P32_1) & M
    for k in range(((n - 1) - block * blocks) // STRIPE):
        _accumulate(acc, d, blocks * block + k * STRIPE, k * RATE)
    _accumulate(acc, d, n - STRIPE, len(SECRET) - STRIPE - 7)

    def merge(s: int, start: int) -> int:
        r = start
        for i in range(4):
            r += _fold(acc[2 * i] ^ _r64(SECRET, s + 16 * i), acc[2 * i + 1] ^ _r64(SECRET, s + 16 * i + 8))
        return _avalanche(r & M)

    return merge(11, (n * P64_1) & M), merge(len(SECRET) - 64 - 11, ~(n * P64_2) & M)


def xxh3_128(data: bytes) -> tuple[int, int]:
    """(low 64 bits, high 64 bits) of XXH3-128 of ``data``."""
    n = len(data)
    if n <= 16:
        return _short(data, n)
    if n <= 128:
        acc = ((n * P64_1) & M, 0)
        for k in range((n - 1) // 32, 0, -1):  # from the middle outwards: 96, 64, 32 as the length allows
            acc = _mix32(acc, data, 16 * k, n - 16 * (k + 1), 32 * k)
        return _finish(_mix32(acc, data, 0, n - 16, 0), n)
    if n <= 240:
        acc = ((n * P64_1) & M, 0)
        for i in range(32, 160, 32):
            acc = _mix32(acc, data, i - 32, i - 16, i - 32)
        acc = (_avalanche(acc[0]), _avalanche(acc[1]))
        for i in range(160, n + 1, 32):
            acc = _mix32(acc, data, i - 32, i - 16, 3 + i - 160)
        acc = _mix32(acc, data, n - 16, n - 32, 136 - 17 - 16)
        return _finish(acc, n)
    return _long(data, n)
