/*
 * omniformation reference follower firmware: the follower protocol of
 * docs/follower-protocol.md (protocol 2: ownership by one leader at a time, with a
 * lease; protocol 3: every frame authenticated with SipHash-2-4 under its leader's own radio
 * key, fresh by a per-sender counter, replies bound to the request they answer), the
 * watchdog and differential-drive odometry, in portable C99 for a small microcontroller.
 *
 * One `of_follower` is one robot. The firmware calls:
 *   of_init()     once, with the robot's address and its hardware numbers;
 *   of_receive()  with every byte (or run of bytes) the UART received;
 *   of_tick()     often (every 1-10 ms) from the main loop.
 *   of_set_auth() after of_init(), with the provisioned key(s) and leaders (the header
 *                 `omniformation radio-provision --header` writes); without it: protocol 2.
 * and provides the functions under "HAL" below (hardware access); nothing else
 * touches the hardware. No dynamic memory, no floating-point printf, no OS.
 */
#ifndef OMNI_FOLLOWER_H
#define OMNI_FOLLOWER_H

#include <stddef.h>
#include <stdint.h>

#define OF_SYNC0 0xA5u
#define OF_SYNC1 0x5Au
#define OF_BROADCAST 0xFFu
#define OF_MAX_PAYLOAD 32u
#define OF_HEADER_LEN 6u
#define OF_MAX_FRAME (OF_HEADER_LEN + OF_MAX_PAYLOAD + 2u)

#define OF_MSG_SET_VELOCITY 0x01u
#define OF_MSG_STOP 0x02u
#define OF_MSG_PING 0x03u
#define OF_MSG_CLAIM 0x04u     /* protocol 2: uint8 leader, uint16 lease ms */
#define OF_MSG_HANDOVER 0x05u  /* protocol 2: uint8 from, uint8 to, uint16 lease ms */
#define OF_MSG_DRIVE 0x06u     /* protocol 2: uint8 leader, uint16 observation age ms, int16 v, int16 w */
#define OF_MSG_ACK 0x81u
#define OF_MSG_STATUS 0x82u
#define OF_MSG_OWNER 0x83u     /* protocol 2: uint8 owner, uint16 lease left ms, uint8 asker */
#define OF_MSG_NACK 0x84u      /* protocol 2: uint8 owner, uint16 lease left ms, uint8 reason, uint8 asker */
#define OF_MSG_DRIVEN 0x85u    /* protocol 2: an ACK's 13 bytes, uint8 asker: a DRIVE obeyed */

#define OF_PROTOCOL_VERSION 2u
#define OF_NACK_OWNED 1u       /* another leader's lease lives */
#define OF_NACK_NOT_OWNER 2u   /* the sender is not the owner (or the robot is owned and SET_VELOCITY came) */
#define OF_NACK_STALE 3u       /* DRIVE from an observation older than OF_MAX_OBSERVATION_AGE_MS: stopped */
#define OF_MAX_OBSERVATION_AGE_MS 300u
#define OF_LEASE_MIN_MS 100u
#define OF_LEASE_MAX_MS 10000u
#define OF_MAX_LEADER 250u
#define OF_TWO_OWNERS_MS 100u  /* DRIVEs of two leaders obeyed closer than this: counted (never expected) */

#define OF_FLAG_WATCHDOG 0x01u
#define OF_FLAG_STOPPED 0x02u
#define OF_FLAG_LOW_BATTERY 0x04u

/* protocol 3: authenticated frames (docs/follower-protocol.md, "Authenticated frames") */
#define OF_AUTH 0x40u            /* type bit: the payload ends with id, counter (48 bits), SipHash-2-4 tag */
#define OF_TRAILER_LEN 15u
#define OF_TAG_LEN 8u
#define OF_KEY_LEN 32u           /* bytes 0..15 sign requests, 16..31 replies */
#define OF_MAX_KEYS 2u           /* the current key, and the next one during a rotation */
#define OF_MAX_SENDERS 16u       /* leaders the robot keeps a counter for */
#define OF_STOP_ANYONE 0u        /* every STOP heard stops the robot (fail-safe; the default) */
#define OF_STOP_AUTHENTICATED 1u /* only an authenticated, fresh STOP from a known leader */

#define OF_WATCHDOG_MS 500u      /* no SET_VELOCITY for this long: wheels to zero, WATCHDOG */
#define OF_PARTIAL_FRAME_MS 20u  /* a frame not complete this long after its last byte is dropped */

/* What the robot is: set by the builder. */
typedef struct {
    float wheel_base_m;         /* distance between the wheels */
    float wheel_speed_max_mps;  /* the faster wheel is never asked for more (both scaled together) */
    uint16_t low_battery_mv;    /* LOW_BATTERY below this (e.g. 6800 for a 2S Li-ion pack) */
} of_hardware;

typedef struct {
    uint32_t frames_ok;
    uint32_t crc_errors;
    uint32_t length_errors;
    uint32_t type_errors;
    uint32_t partial_dropped;   /* frames cut off (OF_PARTIAL_FRAME_MS of silence inside one) */
    uint32_t skipped_bytes;
    uint32_t nacks;             /* protocol 2: refusals sent */
    uint32_t two_owners;        /* DRIVEs obeyed from a leader within OF_TWO_OWNERS_MS of another's */
    uint32_t bad_mac;           /* protocol 3 refusals: no key verified the tag, */
    uint32_t unknown_sender;    /* a sender not provisioned (or a frame naming another leader), */
    uint32_t replayed;          /* a counter not above the last taken from that sender, */
    uint32_t unauthenticated;   /* a plain motion, claim or handover frame */
} of_counters;

/* What a robot is provisioned with for protocol 3 (`omniformation radio-provision` writes it). */
typedef struct {
    uint8_t keys[OF_MAX_KEYS][OF_KEY_LEN];  /* one key for every sender (unless per_leader) */
    uint8_t n_keys;             /* 1, or 2 during a rotation */
    uint8_t leaders[OF_MAX_SENDERS];
    uint8_t n_leaders;          /* 0: any leader 1..250 (the first OF_MAX_SENDERS heard) */
    uint8_t stop_policy;        /* OF_STOP_ANYONE or OF_STOP_AUTHENTICATED */
    /* 1: a key per leader: a frame is checked only against leader_keys[i] of the id it carries
     * (leaders[i]), so a leader's key signs as its own id alone; an id with no keys here is an
     * unknown sender. keys[] is then unused (the robot never holds the fleet's secret). */
    uint8_t per_leader;
    uint8_t leader_keys[OF_MAX_SENDERS][OF_MAX_KEYS][OF_KEY_LEN];
} of_radio_auth;

typedef struct {
    uint8_t address;
    of_hardware hw;
    void *ctx;                  /* handed to every HAL call: the builder's own state */
    uint8_t buf[OF_MAX_FRAME];
    size_t len;
    uint32_t last_byte_ms;
    uint32_t last_command_ms;
    int commanded;              /* a SET_VELOCITY was ever received */
    uint8_t flags;
    float target_left_mps;
    float target_right_mps;
    uint8_t owner;              /* protocol 2: the leader that owns the robot, 0 nobody */
    uint16_t lease_ms;          /* the lease granted; each DRIVE of the owner renews it */
    uint32_t lease_until_ms;
    uint8_t driven_by;          /* the leader whose DRIVE was obeyed last, 0 none */
    uint32_t driven_ms;
    const of_radio_auth *auth;  /* NULL: protocol 2 (no key); else protocol 3 */
    uint8_t sender_id[OF_MAX_SENDERS];  /* protocol 3: the senders heard, and the last counter taken */
    uint64_t sender_counter[OF_MAX_SENDERS];
    uint8_t n_senders;
    of_counters count;
} of_follower;

/* ---- HAL: the builder provides these (firmware/host_sim.c has POSIX ones) ---- */
void hal_uart_write(void *ctx, const uint8_t *data, size_t n);
void hal_set_wheel_targets(void *ctx, float left_mps, float right_mps);
void hal_read_encoders(void *ctx, int32_t *left_ticks, int32_t *right_ticks);
void hal_measured_wheel_speeds(void *ctx, float *left_mps, float *right_mps);
uint16_t hal_battery_mv(void *ctx);
/* optional: told when the robot stops by itself or by STOP (a LED, a log line) */
void hal_event(void *ctx, const char *what);

/* ---- the firmware ---- */
uint16_t of_crc16(const uint8_t *data, size_t n);
uint64_t of_siphash24(const uint8_t key[16], const uint8_t *data, size_t n);
/* protocol 3 from now on (auth must outlive the robot; NULL: back to protocol 2) */
void of_set_auth(of_follower *f, const of_radio_auth *auth);
void of_init(of_follower *f, uint8_t address, const of_hardware *hw, void *ctx, uint32_t now_ms);
void of_receive(of_follower *f, const uint8_t *data, size_t n, uint32_t now_ms);
void of_tick(of_follower *f, uint32_t now_ms);

#endif
