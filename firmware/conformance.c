/*
 * The reference firmware driven by a script, for the conformance test that holds it and the
 * Python follower (core/link/follower.py) to one behaviour (tests/app/test_firmware.py).
 *
 *   conformance ADDRESS < script
 *
 * Each input line is "T_MS HEX": at T_MS (ms, not decreasing) the bytes HEX reach the robot
 * (of_tick first, then of_receive). For each line it prints every frame the robot sent, as
 * "> HEX", then its state after the frame:
 *   "= OWNER LEASE_LEFT_MS TARGET_LEFT_MMPS TARGET_RIGHT_MMPS FLAGS NACKS TWO_OWNERS"
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

int main(int argc, char **argv) {
    of_follower f;
    of_hardware hw = {0.12f, 0.45f, 6800u};
    char line[512];
    if (argc != 2) {
        fprintf(stderr, "usage: conformance ADDRESS < script\n");
        return 2;
    }
    of_init(&f, (uint8_t)atoi(argv[1]), &hw, NULL, 0u);
    while (fgets(line, sizeof line, stdin)) {
        char *p = line, *end;
        uint8_t bytes[OF_MAX_FRAME * 2];
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
            printf("= %u %lu %ld %ld %u %lu %lu\n", (unsigned)f.owner, (unsigned long)left, mm(target_left),
                   mm(target_right), (unsigned)f.flags, (unsigned long)f.count.nacks,
                   (unsigned long)f.count.two_owners);
        }
        fflush(stdout);
    }
    return 0;
}
