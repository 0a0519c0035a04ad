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

static void send(of_follower *f, uint8_t seq, uint8_t type, const uint8_t *payload, uint8_t n) {
    uint8_t out[OF_MAX_FRAME];
    out[0] = OF_SYNC0; out[1] = OF_SYNC1; out[2] = f->address; out[3] = seq; out[4] = type; out[5] = n;
    memcpy(out + OF_HEADER_LEN, payload, n);
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
        set_targets(f, 0.0f, 0.0f);
        if (!(f->flags & OF_FLAG_STOPPED)) hal_event(f->ctx, "STOP");
        f->flags |= OF_FLAG_STOPPED;  /* the watchdog's clock runs on: STOP does not feed it */
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
            handle(f, f->buf[2], f->buf[3], type, f->buf + OF_HEADER_LEN);
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
