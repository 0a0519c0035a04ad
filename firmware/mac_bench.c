/*
 * What authentication costs the reference firmware on this machine (`make bench` builds and runs
 * it; nothing asserts a time): SipHash-2-4 over what a DRIVE, a DRIVEN and the longest frame sign,
 * and a whole authenticated DRIVE received, checked, obeyed and answered (of_receive), in ns per
 * frame (the median of 15 runs). Then the radio's load at 30 Hz with 8 robots, plain and
 * authenticated.
 */
#define _POSIX_C_SOURCE 199309L
#include "omni_follower.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static volatile uint64_t sink;
static uint8_t reply_bytes;

void hal_uart_write(void *ctx, const uint8_t *data, size_t n) { (void)ctx; (void)data; reply_bytes = (uint8_t)n; }
void hal_set_wheel_targets(void *ctx, float l, float r) { (void)ctx; (void)l; (void)r; }
void hal_read_encoders(void *ctx, int32_t *l, int32_t *r) { (void)ctx; *l = 0; *r = 0; }
void hal_measured_wheel_speeds(void *ctx, float *l, float *r) { (void)ctx; *l = 0.0f; *r = 0.0f; }
uint16_t hal_battery_mv(void *ctx) { (void)ctx; return 7400u; }
void hal_event(void *ctx, const char *what) { (void)ctx; (void)what; }

static double now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec * 1e9 + (double)ts.tv_nsec;
}

static int cmp(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double median_mac_ns(size_t n) {
    uint8_t key[16] = {0}, msg[64];
    double runs[15];
    int r;
    long i, reps = 200000;
    for (i = 0; i < 64; i++) msg[i] = (uint8_t)i;
    for (r = 0; r < 15; r++) {
        double t = now_ns();
        for (i = 0; i < reps; i++) {
            msg[0] = (uint8_t)i;
            sink ^= of_siphash24(key, msg, n);
        }
        runs[r] = (now_ns() - t) / (double)reps;
    }
    qsort(runs, 15, sizeof runs[0], cmp);
    return runs[7];
}

static uint16_t crc(const uint8_t *d, size_t n) { return of_crc16(d, n); }

static void put_le(uint8_t *p, uint64_t v, int n) {
    int k;
    for (k = 0; k < n; k++) p[k] = (uint8_t)((v >> (8 * k)) & 0xFFu);
}

/* An authenticated DRIVE from leader 1 (counter c) to robot 1 under the open key. */
static size_t drive_frame(uint8_t *out, uint64_t c) {
    static const uint8_t key[32] = {0};
    uint8_t p[7] = {1, 10, 0, 100, 0, 0, 0};
    size_t n = 7 + OF_TRAILER_LEN;
    out[0] = OF_SYNC0; out[1] = OF_SYNC1; out[2] = 1; out[3] = 7; out[4] = (uint8_t)(OF_MSG_DRIVE | OF_AUTH);
    out[5] = (uint8_t)n;
    memcpy(out + 6, p, 7);
    out[13] = 1;
    put_le(out + 14, c, 6);
    put_le(out + 20, of_siphash24(key, out + 2, 4 + n - OF_TAG_LEN), 8);
    put_le(out + 6 + n, crc(out + 2, 4 + n), 2);
    return 6 + n + 2;
}

int main(void) {
    of_follower f;
    of_hardware hw = {0.12f, 0.45f, 6800u};
    of_radio_auth auth;
    uint8_t frame[OF_MAX_FRAME];
    double runs[15];
    int r;
    long i, reps = 20000;
    uint64_t c = 1;
    memset(&auth, 0, sizeof auth);
    auth.n_keys = 1;
    printf("SipHash-2-4 on this machine (median of 15 runs):\n");
    printf("  a DRIVE's 18 signed bytes:                     %6.1f ns\n", median_mac_ns(18));
    printf("  a DRIVEN's 27 signed bytes + the request's tag: %6.1f ns\n", median_mac_ns(35));
    printf("  the longest frame (32 + request's tag):         %6.1f ns\n", median_mac_ns(40));
    for (r = 0; r < 15; r++) {
        double t, spent = 0.0;
        of_init(&f, 1, &hw, NULL, 0u);
        of_set_auth(&f, &auth);
        for (i = 0; i < reps; i++) {
            size_t n = drive_frame(frame, c++);
            if (i == 0) { uint8_t claim_owner = 1; f.owner = claim_owner; f.lease_ms = 60000u; }
            f.lease_until_ms = 60000u;
            t = now_ns();
            of_receive(&f, frame, n, 1u);
            spent += now_ns() - t;
        }
        runs[r] = spent / (double)reps;
    }
    qsort(runs, 15, sizeof runs[0], cmp);
    printf("  a whole authenticated DRIVE received, checked, obeyed and answered (of_receive): %.0f ns"
           " (reply %u bytes, refusals %lu)\n", runs[7], (unsigned)reply_bytes,
           (unsigned long)(f.count.bad_mac + f.count.replayed + f.count.unknown_sender));
    {
        /* per robot per tick: DRIVE + DRIVEN; per robot per second: PING + STATUS */
        double plain = 30.0 * 8 * (15 + 22) + 8 * (8 + 17), authd = 30.0 * 8 * (30 + 37) + 8 * (23 + 40);
        printf("radio load at 30 Hz x 8 robots (8N1: 10 bits a byte): plain %.0f B/s (%.0f%% of 115200 baud),"
               " authenticated %.0f B/s (%.0f%% of 115200, %.0f%% of 230400 baud, %.1f%% of a 1 Mbit/s nRF24)\n",
               plain, plain * 10 / 115200 * 100, authd, authd * 10 / 115200 * 100, authd * 10 / 230400 * 100,
               authd * 8 / 1e6 * 100);
    }
    return 0;
}
