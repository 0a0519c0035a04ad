/* omniformation reference follower firmware: see omni_follower.h and docs/follower-protocol.md. */
#include "omni_follower.h"

#include <string.h>

uint16_t of_crc16(const uint8_t *data, size_t n) {
    uint16_t crc = 0xFFFFu;
    while (n--) {
        crc ^= (uint16_t)((uint16_t)(*data++) << 8);
        for (int k = 0; k < 8; k++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

/* SipHash-2-4 (Aumasson and Bernstein): 64-bit additions, rotations and XORs only. */
#define OF_ROTL(x, b) (uint64_t)(((x) << (b)) | ((x) >> (64 - (b))))
#define OF_SIPROUND                                                              \
    do {                                                                         \
        v0 += v1; v1 = OF_ROTL(v1, 13); v1 ^= v0; v0 = OF_ROTL(v0, 32);          \
        v2 += v3; v3 = OF_ROTL(v3, 16); v3 ^= v2;                                \
        v0 += v3; v3 = OF_ROTL(v3, 21); v3 ^= v0;                                \
        v2 += v1; v1 = OF_ROTL(v1, 17); v1 ^= v2; v2 = OF_ROTL(v2, 32);          \
    } while (0)

static uint64_t get_u64(const uint8_t *p, size_t n) {
    uint64_t v = 0;
    while (n--) v = (v << 8) | p[n];
    return v;
}

uint64_t of_siphash24(const uint8_t key[16], const uint8_t *data, size_t n) {
    uint64_t k0 = get_u64(key, 8), k1 = get_u64(key + 8, 8);
    uint64_t v0 = k0 ^ 0x736f6d6570736575ULL, v1 = k1 ^ 0x646f72616e646f6dULL;
    uint64_t v2 = k0 ^ 0x6c7967656e657261ULL, v3 = k1 ^ 0x7465646279746573ULL;
    uint64_t m;
    size_t i, end = n - (n % 8u);
    for (i = 0; i < end; i += 8) {
        m = get_u64(data + i, 8);
        v3 ^= m;
        OF_SIPROUND; OF_SIPROUND;
        v0 ^= m;
    }
    m = get_u64(data + end, n - end) | ((uint64_t)(n & 0xFFu) << 56);
    v3 ^= m;
    OF_SIPROUND; OF_SIPROUND;
    v0 ^= m;
    v2 ^= 0xFFu;
    OF_SIPROUND; OF_SIPROUND; OF_SIPROUND; OF_SIPROUND;
    return v0 ^ v1 ^ v2 ^ v3;
}

static void put_u16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)(v & 0xFF); p[1] = (uint8_t)(v >> 8); }
static void put_u32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)(v & 0xFF); p[1] = (uint8_t)((v >> 8) & 0xFF);
    p[2] = (uint8_t)((v >> 16) & 0xFF); p[3] = (uint8_t)(v >> 24);
}
static int16_t get_i16(const uint8_t *p) { return (int16_t)(uint16_t)(p[0] | ((uint16_t)p[1] << 8)); }

static int16_t to_i16(float x) {
    if (x > 32767.0f) return 32767;
    if (x < -32767.0f) return -32767;
    return (int16_t)(x < 0 ? x - 0.5f : x + 0.5f);
}

static uint8_t payload_len(uint8_t type) {
    if (type & OF_AUTH) {
        uint8_t base = (uint8_t)(type & ~OF_AUTH);
        uint8_t n = (base & OF_AUTH) ? 0xFFu : payload_len(base);
        if (n == 0xFF) return 0xFF;
        return (uint8_t)(n + OF_TRAILER_LEN + (base == OF_MSG_STATUS ? 8u : 0u));
    }
    switch (type) {
    case OF_MSG_SET_VELOCITY: return 4;
    case OF_MSG_STOP: return 0;
    case OF_MSG_PING: return 0;
    case OF_MSG_ACK: return 13;
    case OF_MSG_STATUS: return 9;
    case OF_MSG_CLAIM: return 3;
    case OF_MSG_HANDOVER: return 4;
    case OF_MSG_DRIVE: return 7;
    case OF_MSG_OWNER: return 4;
    case OF_MSG_NACK: return 5;
    case OF_MSG_DRIVEN: return 14;
    default: return 0xFF;
    }
}

/* The request being answered, when it was authenticated: the reply is sealed with its key, its
 * sender as the asker and its counter (so the reply proves it answers that very frame). */
static const uint8_t *reply_key;
static const uint8_t *request_tag;  /* the tag of the request answered: the reply's tag covers it too */
static uint8_t reply_id;
static uint64_t reply_counter;

static void put_counts(uint8_t *p, uint32_t v) {
    put_u16(p, (uint16_t)(v > 65535u ? 65535u : v));
}

static void send(of_follower *f, uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t n) {
    uint8_t out[OF_MAX_FRAME];
    uint8_t extra = 0;
    out[0] = OF_SYNC0; out[1] = OF_SYNC1; out[2] = f->address; out[3] = seq; out[4] = type; out[5] = n;
    memcpy(out + OF_HEADER_LEN, payload, n);
    if (reply_key != NULL) {
        uint8_t *t = out + OF_HEADER_LEN + n;
        uint64_t tag;
        int k;
        if (type == OF_MSG_STATUS) {  /* an authenticated STATUS reports the refusals */
            put_counts(t, f->count.bad_mac); put_counts(t + 2, f->count.unknown_sender);
            put_counts(t + 4, f->count.replayed); put_counts(t + 6, f->count.unauthenticated);
            t += 8; extra = 8;
        }
        t[0] = reply_id;
        for (k = 0; k < 6; k++) t[1 + k] = (uint8_t)((reply_counter >> (8 * k)) & 0xFFu);
        n = (uint8_t)(n + extra + OF_TRAILER_LEN);
        out[4] = (uint8_t)(type | OF_AUTH);
        out[5] = n;
        {
            uint8_t signed_bytes[OF_MAX_FRAME + OF_TAG_LEN];
            size_t m = (size_t)(4 + n - OF_TAG_LEN);
            memcpy(signed_bytes, out + 2, m);
            memcpy(signed_bytes + m, request_tag, OF_TAG_LEN);
            tag = of_siphash24(reply_key + 16, signed_bytes, m + OF_TAG_LEN);
        }
        for (k = 0; k < 8; k++) out[OF_HEADER_LEN + n - OF_TAG_LEN + k] = (uint8_t)((tag >> (8 * k)) & 0xFFu);
    }
    put_u16(out + OF_HEADER_LEN + n, of_crc16(out + 2, (size_t)(4 + n)));
    hal_uart_write(f->ctx, out, (size_t)(OF_HEADER_LEN + n + 2));
}

static void set_targets(of_follower *f, float left, float right) {
    f->target_left_mps = left;
    f->target_right_mps = right;
    hal_set_wheel_targets(f->ctx, left, right);
}

static void update_battery_flag(of_follower *f) {
    if (hal_battery_mv(f->ctx) < f->hw.low_battery_mv) f->flags |= OF_FLAG_LOW_BATTERY;
    else f->flags &= (uint8_t)~OF_FLAG_LOW_BATTERY;
}

static uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | ((uint16_t)p[1] << 8)); }

static void set_velocity(of_follower *f, const uint8_t *vw) {
    float v = (float)get_i16(vw) / 1000.0f;      /* mm/s */
    float w = (float)get_i16(vw + 2) / 1000.0f;  /* mrad/s, counter-clockwise */
    float half = w * f->hw.wheel_base_m / 2.0f;
    float left = v - half, right = v + half;
    float big = left < 0 ? -left : left;
    float r = right < 0 ? -right : right;
    if (r > big) big = r;
    if (big > f->hw.wheel_speed_max_mps) {  /* both together: the path keeps its curvature */
        float k = f->hw.wheel_speed_max_mps / big;
        left *= k; right *= k;
    }
    set_targets(f, left, right);
    f->last_command_ms = f->last_byte_ms;
    f->commanded = 1;
    f->flags &= (uint8_t)~(OF_FLAG_WATCHDOG | OF_FLAG_STOPPED);
}

/* ACK's payload, and for protocol 2 (asker != 0) DRIVEN's: the same with the leader answered. */
static void send_odometry(of_follower *f, uint8_t seq, uint8_t asker) {
    uint8_t p[14];
    int32_t lt, rt;
    float lv, rv;
    update_battery_flag(f);
    hal_read_encoders(f->ctx, &lt, &rt);
    hal_measured_wheel_speeds(f->ctx, &lv, &rv);
    put_u32(p, (uint32_t)lt);
    put_u32(p + 4, (uint32_t)rt);
    put_u16(p + 8, (uint16_t)to_i16((lv + rv) / 2.0f * 1000.0f));
    put_u16(p + 10, (uint16_t)to_i16((rv - lv) / f->hw.wheel_base_m * 1000.0f));
    p[12] = f->flags;
    if (asker == 0) {
        send(f, seq, OF_MSG_ACK, p, 13);
    } else {
        p[13] = asker;
        send(f, seq, OF_MSG_DRIVEN, p, 14);
    }
}

/* ---- protocol 2: ownership (docs/follower-protocol.md, "Ownership") ---- */
static int lease_lives(const of_follower *f) {
    return f->owner != 0 && (int32_t)(f->lease_until_ms - f->last_byte_ms) > 0;
}

static void send_ownership(of_follower *f, uint8_t seq, uint8_t reason, uint8_t asker) {
    uint8_t p[5];
    uint32_t left = lease_lives(f) ? f->lease_until_ms - f->last_byte_ms : 0u;
    p[0] = f->owner;
    put_u16(p + 1, (uint16_t)(left > 65535u ? 65535u : left));
    if (reason == 0) {
        p[3] = asker;
        send(f, seq, OF_MSG_OWNER, p, 4);
    } else {
        p[3] = reason;
        p[4] = asker;
        f->count.nacks++;
        send(f, seq, OF_MSG_NACK, p, 5);
    }
}

static void grant(of_follower *f, uint8_t seq, uint8_t leader, uint16_t lease, uint8_t asker) {
    if (lease < OF_LEASE_MIN_MS) lease = OF_LEASE_MIN_MS;
    if (lease > OF_LEASE_MAX_MS) lease = OF_LEASE_MAX_MS;
    if (leader != f->owner) set_targets(f, 0.0f, 0.0f);  /* a new owner starts from rest */
    f->owner = leader;
    f->lease_ms = lease;
    f->lease_until_ms = f->last_byte_ms + lease;
    send_ownership(f, seq, 0, asker);
}

static void ownership(of_follower *f, uint8_t seq, uint8_t type, const uint8_t *payload) {
    uint8_t asker = type == OF_MSG_SET_VELOCITY ? 0u : payload[0];  /* the leader (or, HANDOVER, the giver) */
    if (type == OF_MSG_SET_VELOCITY) {  /* protocol 1 to a robot someone holds */
        send_ownership(f, seq, OF_NACK_NOT_OWNER, asker);
    } else if (type == OF_MSG_CLAIM) {
        uint8_t leader = payload[0];
        if (leader == 0 || leader > OF_MAX_LEADER) send_ownership(f, seq, OF_NACK_NOT_OWNER, asker);
        else if (lease_lives(f) && f->owner != leader) send_ownership(f, seq, OF_NACK_OWNED, asker);
        else grant(f, seq, leader, get_u16(payload + 1), asker);
    } else if (type == OF_MSG_HANDOVER) {
        uint8_t from = payload[0], to = payload[1];
        if (f->owner == 0 || from != f->owner || to == 0 || to > OF_MAX_LEADER)
            send_ownership(f, seq, OF_NACK_NOT_OWNER, asker);
        else grant(f, seq, to, get_u16(payload + 2), asker);
    } else {  /* DRIVE */
        uint8_t leader = payload[0];
        if (!lease_lives(f) || leader != f->owner) {
            send_ownership(f, seq, OF_NACK_NOT_OWNER, asker);
        } else if (get_u16(payload + 1) > OF_MAX_OBSERVATION_AGE_MS) {
            set_targets(f, 0.0f, 0.0f);  /* what it was computed from is gone: stand still */
            send_ownership(f, seq, OF_NACK_STALE, asker);
        } else {
            if (f->driven_by != 0 && f->driven_by != leader && f->last_byte_ms - f->driven_ms < OF_TWO_OWNERS_MS)
                f->count.two_owners++;
            set_velocity(f, payload + 3);
            f->lease_until_ms = f->last_byte_ms + f->lease_ms;
            f->driven_by = leader;
            f->driven_ms = f->last_byte_ms;
            send_odometry(f, seq, leader);
        }
    }
}

static void stop_robot(of_follower *f) {
    set_targets(f, 0.0f, 0.0f);
    if (!(f->flags & OF_FLAG_STOPPED)) hal_event(f->ctx, "STOP");
    f->flags |= OF_FLAG_STOPPED;  /* the watchdog's clock runs on: STOP does not feed it */
}

static void handle(of_follower *f, uint8_t address, uint8_t seq, uint8_t type, const uint8_t *payload) {
    if (address != f->address && address != OF_BROADCAST) return;
    if (type == OF_MSG_CLAIM || type == OF_MSG_HANDOVER || type == OF_MSG_DRIVE ||
        (type == OF_MSG_SET_VELOCITY && lease_lives(f))) {
        if (address != OF_BROADCAST) ownership(f, seq, type, payload);  /* one robot's business */
        return;
    }
    if (type == OF_MSG_SET_VELOCITY) {
        set_velocity(f, payload);
    } else if (type == OF_MSG_STOP) {
        stop_robot(f);
    } else if (type != OF_MSG_PING) {
        return;  /* another robot's reply on a shared line */
    }
    if (address == OF_BROADCAST) return;  /* obeyed, never answered */
    if (type == OF_MSG_PING) {
        update_battery_flag(f);
        uint8_t p[9];
        uint32_t age = f->last_byte_ms - f->last_command_ms;
        put_u16(p, hal_battery_mv(f->ctx));
        p[2] = f->flags;
        put_u16(p + 3, (uint16_t)((!f->commanded || age > 65534u) ? 65535u : age));
        put_u32(p + 5, f->last_byte_ms);
        send(f, seq, OF_MSG_STATUS, p, 9);
    } else {
        send_odometry(f, seq, 0);
    }
}

/* Protocol 3: one frame as received (buf: address, seq, type, length, payload; n the payload's length). */
static void handle_auth(of_follower *f, const uint8_t *buf, uint8_t n) {
    const of_radio_auth *a = f->auth;
    uint8_t address = buf[0], seq = buf[1], type = buf[2];
    uint8_t kind = (uint8_t)(type & ~OF_AUTH);
    int fail_safe = kind == OF_MSG_STOP && a->stop_policy == OF_STOP_ANYONE;
    const uint8_t *payload = buf + 4;
    uint32_t *why = NULL;
    uint8_t k, key = 0, ok = 0, ident, slot, n_keys;
    const uint8_t (*keys)[OF_KEY_LEN];
    uint64_t counter = 0;
    if ((address != f->address && address != OF_BROADCAST) || (type & 0x80u)) return;
    if (!(type & OF_AUTH)) {
        if (fail_safe) stop_robot(f);  /* obeyed, never answered */
        else if (kind == OF_MSG_SET_VELOCITY || kind == OF_MSG_CLAIM || kind == OF_MSG_HANDOVER ||
                 kind == OF_MSG_DRIVE || kind == OF_MSG_STOP)
            f->count.unauthenticated++;
        return;
    }
    ident = payload[n - OF_TRAILER_LEN];
    counter = get_u64(payload + n - OF_TRAILER_LEN + 1, 6);
    keys = a->keys;
    n_keys = a->n_keys;
    if (a->per_leader) {  /* only the keys of the id the frame carries */
        for (k = 0; k < a->n_leaders && a->leaders[k] != ident; k++) {}
        if (k < a->n_leaders) keys = a->leader_keys[k];
        else n_keys = 0;
    }
    for (k = 0; k < n_keys && !ok; k++) {
        uint64_t want = of_siphash24(keys[k], buf, (size_t)(4 + n - OF_TAG_LEN));
        uint64_t got = get_u64(payload + n - OF_TAG_LEN, 8);
        if (want == got) { ok = 1; key = k; }
    }
    for (slot = 0; slot < f->n_senders && f->sender_id[slot] != ident; slot++) {}
    if (!ok) {
        why = &f->count.bad_mac;  /* with a key per leader, an id with none: no key of the robot's verifies it */
    } else {
        int known = 0, names_other;
        if (a->n_leaders == 0) known = ident >= 1 && ident <= OF_MAX_LEADER;
        for (k = 0; k < a->n_leaders; k++) known |= a->leaders[k] == ident;
        names_other = (kind == OF_MSG_CLAIM || kind == OF_MSG_HANDOVER || kind == OF_MSG_DRIVE) && payload[0] != ident;
        if (!known || names_other || (slot == f->n_senders && f->n_senders >= OF_MAX_SENDERS))
            why = &f->count.unknown_sender;
        else if (slot < f->n_senders && counter <= f->sender_counter[slot])
            why = &f->count.replayed;
    }
    if (why != NULL) {
        (*why)++;
        if (fail_safe) stop_robot(f);
        return;
    }
    if (slot == f->n_senders) { f->sender_id[slot] = ident; f->n_senders++; }
    f->sender_counter[slot] = counter;
    reply_key = keys[key];
    request_tag = payload + n - OF_TAG_LEN;
    reply_id = ident;
    reply_counter = counter;
    handle(f, address, seq, kind, payload);
    reply_key = NULL;
}

/* Drop the first byte of the buffer (a sync byte that began no good frame) and search again. */
static void drop_first(of_follower *f) {
    size_t k = 1;
    while (k < f->len && f->buf[k] != OF_SYNC0) k++;
    f->count.skipped_bytes += (uint32_t)k;
    memmove(f->buf, f->buf + k, f->len - k);
    f->len -= k;
}

static void parse(of_follower *f) {
    for (;;) {
        if (f->len == 0) return;
        if (f->buf[0] != OF_SYNC0) { drop_first(f); continue; }
        if (f->len < 2) return;
        if (f->buf[1] != OF_SYNC1) { drop_first(f); continue; }
        if (f->len < OF_HEADER_LEN) return;
        uint8_t n = f->buf[5];
        if (n > OF_MAX_PAYLOAD) {  /* the length is checked first: no waiting for a frame that cannot be */
            f->count.length_errors++;
            drop_first(f);
            continue;
        }
        size_t total = OF_HEADER_LEN + n + 2u;
        if (f->len < total) return;  /* the rest of the frame is still on its way */
        uint16_t crc = (uint16_t)(f->buf[total - 2] | ((uint16_t)f->buf[total - 1] << 8));
        if (crc != of_crc16(f->buf + 2, (size_t)(4 + n))) {
            f->count.crc_errors++;
            drop_first(f);  /* the real next frame may begin inside this one */
            continue;
        }
        uint8_t type = f->buf[4];
        uint8_t want = payload_len(type);
        if (want == 0xFF) f->count.type_errors++;
        else if (want != n) f->count.length_errors++;
        else {
            f->count.frames_ok++;
            if (f->auth != NULL) handle_auth(f, f->buf + 2, n);
            else handle(f, f->buf[2], f->buf[3], type, f->buf + OF_HEADER_LEN);
        }
        memmove(f->buf, f->buf + total, f->len - total);
        f->len -= total;
    }
}

void of_init(of_follower *f, uint8_t address, const of_hardware *hw, void *ctx, uint32_t now_ms) {
    memset(f, 0, sizeof(*f));
    f->address = address;
    f->hw = *hw;
    f->ctx = ctx;
    f->flags = OF_FLAG_WATCHDOG;  /* nothing commanded yet */
    f->last_byte_ms = now_ms;
    f->last_command_ms = now_ms;
    set_targets(f, 0.0f, 0.0f);
}

void of_set_auth(of_follower *f, const of_radio_auth *auth) {
    f->auth = auth;
    f->n_senders = 0;
}

void of_receive(of_follower *f, const uint8_t *data, size_t n, uint32_t now_ms) {
    if (f->len > 0 && now_ms - f->last_byte_ms > OF_PARTIAL_FRAME_MS) {  /* a frame cut off: forget it */
        f->count.partial_dropped++;
        f->count.skipped_bytes += (uint32_t)f->len;
        f->len = 0;
    }
    f->last_byte_ms = now_ms;
    while (n > 0) {
        size_t room = sizeof(f->buf) - f->len;
        size_t take = n < room ? n : room;
        memcpy(f->buf + f->len, data, take);
        f->len += take;
        data += take;
        n -= take;
        parse(f);
    }
}

void of_tick(of_follower *f, uint32_t now_ms) {
    if (f->len > 0 && now_ms - f->last_byte_ms > OF_PARTIAL_FRAME_MS) {
        f->count.partial_dropped++;
        f->count.skipped_bytes += (uint32_t)f->len;
        f->len = 0;
    }
    if (!(f->flags & OF_FLAG_WATCHDOG) && now_ms - f->last_command_ms > OF_WATCHDOG_MS) {
        set_targets(f, 0.0f, 0.0f);
        f->flags |= OF_FLAG_WATCHDOG;
        hal_event(f->ctx, "watchdog");
    }
}
