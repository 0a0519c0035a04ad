/*
 * The reference firmware driven by a script, for the conformance test that holds it and the
 * Python follower (core/link/follower.py) to one behaviour (tests/app/test_firmware.py).
 *
 *   conformance ADDRESS [--key HEX64]... [--leaders 1,2,..] [--leader-key ID HEX64]...
 *               [--stop-authenticated] < script
 *   conformance --siphash < vectors      (lines "KEY_HEX MESSAGE_HEX": prints each tag as 16 hex digits)
 *
 * With --key (the current key, then the next one) the robot speaks protocol 3 (authenticated
 * frames); --leaders lists the senders it knows (default: any); the STOP policy is fail-safe
 * unless --stop-authenticated. With --leader-key instead, a key per leader (per_leader): each
 * ID's current key, then its next one (every leader the same number of keys).
 *
 * Each input line is "T_MS HEX": at T_MS (ms, not decreasing) the bytes HEX reach the robot
 * (of_tick first, then of_receive). For each line it prints every frame the robot sent, as
 * "> HEX", then its state after the frame:
 *   "= OWNER LEASE_LEFT_MS TARGET_LEFT_MMPS TARGET_RIGHT_MMPS FLAGS NACKS TWO_OWNERS
 *      BAD_MAC UNKNOWN_SENDER REPLAYED UNAUTHENTICATED"
 * The HAL here is still: no motors (encoders 0, wheels still), a full battery.
 */
#include "omni_follower.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static float target_left, target_right;

void hal_uart_write(void *ctx, const uint8_t *data, size_t n) {
    (void)ctx;
    printf(">");
    for (size_t i = 0; i < n; i++) printf(" %02x", data[i]);
    printf("\n");
}
void hal_set_wheel_targets(void *ctx, float left_mps, float right_mps) {
    (void)ctx;
    target_left = left_mps;
    target_right = right_mps;
}
void hal_read_encoders(void *ctx, int32_t *left_ticks, int32_t *right_ticks) {
    (void)ctx;
    *left_ticks = 0;
    *right_ticks = 0;
}
void hal_measured_wheel_speeds(void *ctx, float *left_mps, float *right_mps) {
    (void)ctx;
    *left_mps = 0.0f;
    *right_mps = 0.0f;
}
uint16_t hal_battery_mv(void *ctx) {
    (void)ctx;
    return 7400u;
}
void hal_event(void *ctx, const char *what) {
    (void)ctx;
    (void)what;
}

static long mm(float x) { return (long)(x * 1000.0f + (x < 0 ? -0.5f : 0.5f)); }

static int hex_bytes(const char *text, uint8_t *out, size_t max) {
    size_t n = 0;
    while (text[0] && text[1] && n < max) {
        char pair[3] = {text[0], text[1], 0};
        char *end;
        out[n++] = (uint8_t)strtoul(pair, &end, 16);
        if (*end) return -1;
        text += 2;
    }
    return (int)n;
}

static int siphash_vectors(void) {
    char line[1024];
    while (fgets(line, sizeof line, stdin)) {
        uint8_t key[16], msg[256];
        char *space = strchr(line, ' ');
        int n;
        if (space == NULL) continue;
        *space = 0;
        space[strcspn(space + 1, "\r\n") + 1] = 0;
        if (hex_bytes(line, key, 16) != 16 || (n = hex_bytes(space + 1, msg, sizeof msg)) < 0) return 2;
        printf("%016llx\n", (unsigned long long)of_siphash24(key, msg, (size_t)n));
    }
    return 0;
}

int main(int argc, char **argv) {
    of_follower f;
    of_hardware hw = {0.12f, 0.45f, 6800u};
    of_radio_auth auth;
    int i, authenticated = 0;
    uint8_t per_leader_keys[OF_MAX_SENDERS] = {0};
    char line[512];
    memset(&auth, 0, sizeof auth);
    if (argc == 2 && strcmp(argv[1], "--siphash") == 0) return siphash_vectors();
    if (argc < 2) {
        fprintf(stderr, "usage: conformance ADDRESS [--key HEX]... [--leaders 1,2] [--stop-authenticated] < script\n");
        return 2;
    }
    for (i = 2; i < argc; i++) {
        if (strcmp(argv[i], "--key") == 0 && i + 1 < argc && auth.n_keys < OF_MAX_KEYS) {
            if (hex_bytes(argv[++i], auth.keys[auth.n_keys], OF_KEY_LEN) != (int)OF_KEY_LEN) return 2;
            auth.n_keys++;
            authenticated = 1;
        } else if (strcmp(argv[i], "--leaders") == 0 && i + 1 < argc) {
            char *p = argv[++i], *end;
            while (*p && auth.n_leaders < OF_MAX_SENDERS) {
                auth.leaders[auth.n_leaders++] = (uint8_t)strtoul(p, &end, 10);
                p = *end == ',' ? end + 1 : end;
                if (end == p && *p) return 2;
            }
        } else if (strcmp(argv[i], "--leader-key") == 0 && i + 2 < argc) {
            uint8_t id = (uint8_t)atoi(argv[++i]);
            uint8_t at;
            for (at = 0; at < auth.n_leaders && auth.leaders[at] != id; at++) {}
            if (at == auth.n_leaders) {
                if (auth.n_leaders >= OF_MAX_SENDERS) return 2;
                auth.leaders[auth.n_leaders++] = id;
                per_leader_keys[at] = 0;
            }
            if (per_leader_keys[at] >= OF_MAX_KEYS ||
                hex_bytes(argv[++i], auth.leader_keys[at][per_leader_keys[at]], OF_KEY_LEN) != (int)OF_KEY_LEN)
                return 2;
            per_leader_keys[at]++;
            auth.per_leader = 1;
            auth.n_keys = per_leader_keys[0];
            authenticated = 1;
        } else if (strcmp(argv[i], "--stop-authenticated") == 0) {
            auth.stop_policy = OF_STOP_AUTHENTICATED;
        } else {
            fprintf(stderr, "conformance: unknown argument %s\n", argv[i]);
            return 2;
        }
    }
    for (i = 0; auth.per_leader && i < auth.n_leaders; i++)
        if (per_leader_keys[i] != auth.n_keys) return 2;  /* every leader the same number of keys */
    of_init(&f, (uint8_t)atoi(argv[1]), &hw, NULL, 0u);
    if (authenticated) of_set_auth(&f, &auth);
    while (fgets(line, sizeof line, stdin)) {
        char *p = line, *end;
        uint8_t bytes[OF_MAX_FRAME * 4];
        size_t n = 0;
        unsigned long t = strtoul(p, &end, 10);
        if (end == p) continue;
        p = end;
        for (;;) {
            unsigned long b = strtoul(p, &end, 16);
            if (end == p || n == sizeof bytes) break;
            bytes[n++] = (uint8_t)b;
            p = end;
        }
        of_tick(&f, (uint32_t)t);
        of_receive(&f, bytes, n, (uint32_t)t);
        {
            uint32_t left = (f.owner != 0 && (int32_t)(f.lease_until_ms - (uint32_t)t) > 0)
                                ? f.lease_until_ms - (uint32_t)t : 0u;
            printf("= %u %lu %ld %ld %u %lu %lu %lu %lu %lu %lu\n", (unsigned)f.owner, (unsigned long)left,
                   mm(target_left), mm(target_right), (unsigned)f.flags, (unsigned long)f.count.nacks,
                   (unsigned long)f.count.two_owners, (unsigned long)f.count.bad_mac,
                   (unsigned long)f.count.unknown_sender, (unsigned long)f.count.replayed,
                   (unsigned long)f.count.unauthenticated);
        }
        fflush(stdout);
    }
    return 0;
}
