/*
 * The reference firmware on this machine: POSIX stand-ins for the HAL (motors with a
 * first-order lag, wheel encoders, a battery) and a main loop serving several robots on
 * one pseudo-terminal, as robots share one radio line. The tests build it with `cc` and
 * drive it from the service (docs/follower-protocol.md, "The reference firmware").
 *
 *   follower_sim [--addresses 1,2,3] [--link-path PATH] [--battery-mv 7400]
 *                [--radio-record FILE.bin | --protocol 2]
 *
 * The robots speak protocol 3 (authenticated frames): with --radio-record (written by
 * `omniformation radio-provision --record`) they hold each leader's key (or one key for the
 * fleet, an older record) and the leaders, as a flashed robot does; without it the open key (any leader); --protocol 2 makes them older robots.
 *
 * Prints "firmware followers 1,2,3 on /dev/pts/N", then one line per event
 * ("robot 2: moving", "robot 2: still", "robot 2: STOP", "robot 2: watchdog").
 * SIGINT / SIGTERM end it (the link path it made is removed; an existing file is never
 * touched: it refuses to start instead).
 */
#define _XOPEN_SOURCE 700
#include "omni_follower.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#define MAX_ROBOTS 16
#define WHEEL_RADIUS_M 0.03
#define TICKS_PER_REV 360.0
#define MOTOR_TAU_S 0.12
#define STEP_MS 2u

typedef struct {
    of_follower f;
    double target_l, target_r, wl, wr, dist_l, dist_r;
    int moving;
    uint16_t battery_mv;
} robot;

static int master_fd = -1;
static volatile sig_atomic_t running = 1;
static uint32_t start_ms;
static robot robots[MAX_ROBOTS];
static int n_robots = 0;

static uint32_t now_ms(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint32_t)((uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u) - start_ms;
}

/* ---- the HAL ---- */
void hal_uart_write(void *ctx, const uint8_t *data, size_t n) {
    (void)ctx;
    while (n > 0) {
        ssize_t k = write(master_fd, data, n);
        if (k < 0) {
            if (errno == EINTR) continue;
            return;  /* nobody reads the line: the reply is lost, as on a radio */
        }
        data += k;
        n -= (size_t)k;
    }
}

void hal_set_wheel_targets(void *ctx, float left_mps, float right_mps) {
    robot *r = ctx;
    r->target_l = left_mps;
    r->target_r = right_mps;
}

void hal_read_encoders(void *ctx, int32_t *left_ticks, int32_t *right_ticks) {
    robot *r = ctx;
    double per_tick = 2.0 * M_PI * WHEEL_RADIUS_M / TICKS_PER_REV;
    *left_ticks = (int32_t)(int64_t)floor(r->dist_l / per_tick);
    *right_ticks = (int32_t)(int64_t)floor(r->dist_r / per_tick);
}

void hal_measured_wheel_speeds(void *ctx, float *left_mps, float *right_mps) {
    robot *r = ctx;
    *left_mps = (float)r->wl;
    *right_mps = (float)r->wr;
}

uint16_t hal_battery_mv(void *ctx) { return ((robot *)ctx)->battery_mv; }

void hal_event(void *ctx, const char *what) {
    robot *r = ctx;
    printf("%u ms robot %u: %s\n", (unsigned)now_ms(), (unsigned)r->f.address, what);
    fflush(stdout);
}

/* ---- the motors, between HAL calls ---- */
static void step_motors(robot *r, double dt) {
    double k = 1.0 - exp(-dt / MOTOR_TAU_S);
    double wl = r->wl + k * (r->target_l - r->wl), wr = r->wr + k * (r->target_r - r->wr);
    if (r->target_l == 0.0 && fabs(wl) < 1e-4) wl = 0.0;
    if (r->target_r == 0.0 && fabs(wr) < 1e-4) wr = 0.0;
    r->dist_l += (r->wl + wl) / 2.0 * dt;
    r->dist_r += (r->wr + wr) / 2.0 * dt;
    r->wl = wl;
    r->wr = wr;
    int moving = fabs(wl) > 1e-3 || fabs(wr) > 1e-3;
    if (moving != r->moving) {
        r->moving = moving;
        hal_event(r, moving ? "moving" : "still");
    }
}

static void on_signal(int sig) { (void)sig; running = 0; }

static int open_pty(char *name, size_t size, int *slave_fd) {
    int fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (fd < 0 || grantpt(fd) != 0 || unlockpt(fd) != 0) return -1;
    const char *path = ptsname(fd);
    if (path == NULL) return -1;
    snprintf(name, size, "%s", path);
    *slave_fd = open(name, O_RDWR | O_NOCTTY);  /* held open: the line stays up between the host's opens */
    if (*slave_fd < 0) return -1;
    struct termios t;
    if (tcgetattr(*slave_fd, &t) == 0) {
        t.c_iflag &= (tcflag_t)~(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON);  /* raw */
        t.c_oflag &= (tcflag_t)~OPOST;
        t.c_lflag &= (tcflag_t)~(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
        t.c_cflag &= (tcflag_t)~(CSIZE | PARENB);
        t.c_cflag |= CS8;
        tcsetattr(*slave_fd, TCSANOW, &t);
    }
    fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
    return fd;
}

static of_radio_auth auth;  /* the open key unless a record is given */

/* The record radio-provision writes: "OFR3", n keys, keys, n leaders, ids, STOP policy, CRC-16
 * (one key for the fleet); or "OFR4", n keys, n leaders, then per leader its id and its n keys
 * (current, next), STOP policy, CRC-16 (a key per leader: each signs as its own id alone). */
static int load_record(const char *path) {
    static uint8_t b[4 + 2 + OF_MAX_SENDERS * (1 + OF_MAX_KEYS * OF_KEY_LEN) + 1 + 2 + 1];
    size_t n, k = 4, i;
    FILE *f = fopen(path, "rb");
    if (f == NULL) return -1;
    n = fread(b, 1, sizeof b, f);
    fclose(f);
    if (n < 4 + 1 + 1 + 1 + 2 || n == sizeof b) return -1;
    if (of_crc16(b, n - 2) != (uint16_t)(b[n - 2] | (b[n - 1] << 8))) return -1;
    if (memcmp(b, "OFR4", 4) == 0) {
        auth.per_leader = 1;
        auth.n_keys = b[k++];
        auth.n_leaders = b[k++];
        if (auth.n_keys < 1 || auth.n_keys > OF_MAX_KEYS || auth.n_leaders < 1 || auth.n_leaders > OF_MAX_SENDERS ||
            k + auth.n_leaders * (1u + auth.n_keys * OF_KEY_LEN) + 1 != n - 2) return -1;
        for (i = 0; i < auth.n_leaders; i++) {
            auth.leaders[i] = b[k++];
            memcpy(auth.leader_keys[i], b + k, (size_t)auth.n_keys * OF_KEY_LEN);
            k += (size_t)auth.n_keys * OF_KEY_LEN;
        }
        auth.stop_policy = b[k];
        return auth.stop_policy <= OF_STOP_AUTHENTICATED ? 0 : -1;
    }
    if (memcmp(b, "OFR3", 4) != 0 || n < 4 + 1 + OF_KEY_LEN + 1 + 1 + 2) return -1;
    auth.n_keys = b[k++];
    if (auth.n_keys < 1 || auth.n_keys > OF_MAX_KEYS || k + auth.n_keys * OF_KEY_LEN + 1 > n - 2) return -1;
    memcpy(auth.keys, b + k, (size_t)auth.n_keys * OF_KEY_LEN);
    k += (size_t)auth.n_keys * OF_KEY_LEN;
    auth.n_leaders = b[k++];
    if (auth.n_leaders > OF_MAX_SENDERS || k + auth.n_leaders + 1 != n - 2) return -1;
    memcpy(auth.leaders, b + k, auth.n_leaders);
    k += auth.n_leaders;
    auth.stop_policy = b[k];
    return auth.stop_policy <= OF_STOP_AUTHENTICATED ? 0 : -1;
}

int main(int argc, char **argv) {
    const char *addresses = "1,2,3", *link_path = NULL;
    unsigned battery = 7400;
    int protocol = 3;
    auth.n_keys = 1;  /* the open key: all zeros, any leader, STOP from anyone */
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--addresses") == 0 && i + 1 < argc) addresses = argv[++i];
        else if (strcmp(argv[i], "--protocol") == 0 && i + 1 < argc) protocol = atoi(argv[++i]);
        else if (strcmp(argv[i], "--radio-record") == 0 && i + 1 < argc) {
            if (load_record(argv[++i]) != 0) {
                fprintf(stderr, "follower_sim: %s: not a radio record (omniformation radio-provision --record)\n",
                        argv[i]);
                return 2;
            }
        }
        else if (strcmp(argv[i], "--link-path") == 0 && i + 1 < argc) link_path = argv[++i];
        else if (strcmp(argv[i], "--battery-mv") == 0 && i + 1 < argc) battery = (unsigned)strtoul(argv[++i], NULL, 10);
        else {
            fprintf(stderr, "follower_sim: unknown argument %s (allowed: --addresses A,B,.. --link-path PATH"
                            " --battery-mv MV --radio-record FILE --protocol 2|3)\n", argv[i]);
            return 2;
        }
    }
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    start_ms = (uint32_t)((uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u);
    of_hardware hw = {0.12f, 0.45f, 6800};
    char list[128];
    snprintf(list, sizeof list, "%s", addresses);
    for (char *tok = strtok(list, ","); tok != NULL && n_robots < MAX_ROBOTS; tok = strtok(NULL, ",")) {
        long a = strtol(tok, NULL, 10);
        if (a < 1 || a > 250) {
            fprintf(stderr, "follower_sim: address %s: must be 1..250\n", tok);
            return 2;
        }
        robot *r = &robots[n_robots++];
        memset(r, 0, sizeof *r);
        r->battery_mv = (uint16_t)battery;
        of_init(&r->f, (uint8_t)a, &hw, r, now_ms());
        if (protocol != 2) of_set_auth(&r->f, &auth);
    }
    char name[128];
    int slave_fd = -1;
    master_fd = open_pty(name, sizeof name, &slave_fd);
    if (master_fd < 0) {
        fprintf(stderr, "follower_sim: cannot open a pseudo-terminal: %s\n", strerror(errno));
        return 1;
    }
    if (link_path != NULL) {
        struct stat st;
        if (lstat(link_path, &st) == 0) {
            fprintf(stderr, "follower_sim: %s exists; give a new --link-path (an existing file is never replaced)\n",
                    link_path);
            return 2;
        }
        if (symlink(name, link_path) != 0) {
            fprintf(stderr, "follower_sim: cannot make %s: %s\n", link_path, strerror(errno));
            return 1;
        }
    }
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    printf("firmware followers %s on %s\n", addresses, link_path ? link_path : name);
    fflush(stdout);
    uint32_t last = now_ms();
    while (running) {
        struct pollfd p = {master_fd, POLLIN, 0};
        int ready = poll(&p, 1, (int)STEP_MS);
        uint32_t t = now_ms();
        if (ready > 0 && (p.revents & POLLIN)) {
            uint8_t buf[256];
            ssize_t k = read(master_fd, buf, sizeof buf);
            if (k > 0)
                for (int i = 0; i < n_robots; i++) of_receive(&robots[i].f, buf, (size_t)k, t);  /* one shared line */
        }
        if (t - last >= STEP_MS) {
            double dt = (double)(t - last) / 1000.0;
            last = t;
            for (int i = 0; i < n_robots; i++) {
                step_motors(&robots[i], dt);
                of_tick(&robots[i].f, t);
            }
        }
    }
    for (int i = 0; i < n_robots; i++) {
        of_counters *c = &robots[i].f.count;
        printf("robot %u: %u frames, %u CRC errors, %u length errors, %u partial frames dropped\n",
               (unsigned)robots[i].f.address, (unsigned)c->frames_ok, (unsigned)c->crc_errors,
               (unsigned)c->length_errors, (unsigned)c->partial_dropped);
    }
    if (link_path != NULL) {
        char target[128];
        ssize_t k = readlink(link_path, target, sizeof target - 1);
        if (k >= 0) {
            target[k] = '\0';
            if (strcmp(target, name) == 0) unlink(link_path);  /* ours: gone with us */
        }
    }
    close(slave_fd);
    close(master_fd);
    return 0;
}
