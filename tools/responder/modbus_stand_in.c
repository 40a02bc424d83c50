/* Drives' stand-in for the free-running Modbus TCP benchmark: two servo drives (unit ids 1, 2)
   laid out as drivers/generic-modbus-servo.yaml, answering every request at once.

   The benchmark (gearbench.benchmarks drives_modbus, stand-in "compiled") measures the master,
   so what answers must not lose anything itself: a drive's cycle never slips, whatever the PC
   does. This program keeps no world that must be stepped: the sample counter is the monotonic
   clock read when a request is answered (+1 per COUNTER_PERIOD_S), and position/velocity/
   current are functions of that instant (velocity mode: velocity = target, position its
   integral; torque mode: current = target), taken at the kernel's receive time of the request
   (SO_TIMESTAMPNS): a stand-in the host does not run for a while still answers with the instant
   the request reached it, as drive hardware would. It listens on two loopback ports (both
   answer both unit ids): a bench with one IP per drive has one connection per drive. It runs at SCHED_FIFO above the master with its
   memory locked, single-threaded on poll(). Function codes 0x03, 0x06, 0x10, 0x17; CiA 402
   control word 6/7/15 -> READY TO SWITCH ON / SWITCHED ON / OPERATION ENABLED, 0 / 2 / 128 ->
   SWITCH ON DISABLED; the comm_timeout register arms a watchdog that quick-stops a unit no
   request reached for that long (a real drive whose master died).

   History (optional HISTORY_ADDRESS DEPTH): a ring of the last DEPTH samples, one per counter
   period, entry j = counter mod DEPTH at HISTORY_ADDRESS + 9*j, laid out like the sample block
   (status, counter, position, velocity, current), as drivers/generic-modbus-servo.yaml's
   `history:`. An entry holds the newest counter n <= now with n mod DEPTH = j, its values those of
   the instant n (the motion is a function of time; the status is today's), so a master that was
   not run for less than DEPTH counter periods reads back every sample it missed.

   usage: modbus_stand_in COUNTER_PERIOD_S CELL_COUNTS LATE_S FIFO_PRIORITY [HISTORY_ADDRESS DEPTH]
          (CELL_COUNTS: counter periods per sampling period of the master: a "cell" is the span
          of one sample index; LATE_S: an answer sent later than this after the kernel received
          the request (SO_TIMESTAMPNS) is counted late). Prints "ready PORT1 PORT2 PRIORITY".
   stdin: "status" -> one JSON line of counters; EOF -> counters, exit.
   Counters: requests; block_reads (reads that include the sample counter); late_answers;
   answer_delay_max_s; cells_unread (per unit, sample cells between two successive block reads
   that no read fell in: the samples the master lost, as the drive sees it); repeat_reads (a
   cell read twice); exceptions; watchdog_trips; connections; history_reads (reads of the ring);
   history_entries (cell samples the ring delivered for the first time). */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#define UNITS 2
#define NREG 32
#define MAX_CONN 8
enum { CONTROL = 0, MODE = 1, TARGET_VEL = 2, TARGET_CUR = 4, COMM_TIMEOUT = 7, STATUS = 10, COUNTER = 11,
       POSITION = 13, VELOCITY = 15, CURRENT = 17 };
static const double POS_SCALE = 2 * M_PI / 10000, VEL_SCALE = 0.001, CUR_SCALE = 0.0001, TIMEOUT_SCALE = 0.001;

typedef struct {
    uint16_t reg[NREG];
    double pos_rad, vel_rad_s, since_s;     /* position at `since_s`, velocity since then */
    double last_request_s;
    long long last_cell;
} Unit;

typedef struct { int fd; uint8_t buf[1024]; int len; } Conn;

static Unit unit[UNITS + 1];
static Conn conn[MAX_CONN];
static double counter_period_s, late_s, t0_s, delay_max_s;
static long long hist_addr = -1, hist_depth, history_reads, history_entries;
static long long cell_counts, requests, block_reads, late_answers, cells_unread, repeat_reads, exceptions,
    watchdog_trips, connections;
static char granted[64] = "normal";

static double now_s(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

static int32_t get32(const uint16_t *r, int a) { return (int32_t)((uint32_t)r[a] << 16 | r[a + 1]); }
static void put32(uint16_t *r, int a, uint32_t v) { r[a] = v >> 16; r[a + 1] = v & 0xFFFF; }

static void move_to(Unit *u, double t) {        /* position integrated up to t at the current velocity */
    u->pos_rad += u->vel_rad_s * (t - u->since_s);
    u->since_s = t;
}

static void update_motion(Unit *u, double t) {  /* velocity follows the target while enabled in mode 3 */
    move_to(u, t);
    int enabled = (u->reg[STATUS] & 0x6F) == 0x27;
    u->vel_rad_s = enabled && u->reg[MODE] == 3 ? get32(u->reg, TARGET_VEL) * VEL_SCALE : 0.0;
}

static void write_control(Unit *u, uint16_t v, double t) {
    uint16_t s = u->reg[STATUS];
    if (v == 6) s = 0x21;
    else if (v == 7 && (s == 0x21 || s == 0x23 || s == 0x27)) s = 0x23;
    else if (v == 15 && (s == 0x23 || s == 0x27)) s = 0x27;
    else if (v == 0 || v == 2 || v == 128) s = 0x40;
    u->reg[STATUS] = s;
    update_motion(u, t);
}

static void fill(Unit *u, double t) {           /* the sampled registers at instant t */
    move_to(u, t);
    put32(u->reg, COUNTER, (uint32_t)llround(floor((t - t0_s) / counter_period_s)));
    put32(u->reg, POSITION, (uint32_t)(int32_t)llround(fmod(u->pos_rad / POS_SCALE, 2147483648.0)));
    put32(u->reg, VELOCITY, (uint32_t)(int32_t)llround(u->vel_rad_s / VEL_SCALE));
    int enabled = (u->reg[STATUS] & 0x6F) == 0x27;
    double current_a = enabled ? (u->reg[MODE] == 4 ? get32(u->reg, TARGET_CUR) * CUR_SCALE : 0.05 * u->vel_rad_s / 50) : 0.0;
    put32(u->reg, CURRENT, (uint32_t)(int32_t)llround(current_a / CUR_SCALE));
}

static void count_cell(Unit *u) {
    long long cell = (long long)((uint32_t)get32(u->reg, COUNTER)) / cell_counts;
    if (u->last_cell >= 0) {
        if (cell > u->last_cell + 1) cells_unread += cell - u->last_cell - 1;
        if (cell == u->last_cell) repeat_reads++;
    }
    u->last_cell = cell;
}

/* the history ring's word at address a (>= hist_addr) for instant t: entry j holds counter n */
static uint16_t ring_word(Unit *u, int a, double t) {
    long long j = (a - hist_addr) / 9, w = (a - hist_addr) % 9;
    long long now = (long long)floor((t - t0_s) / counter_period_s);
    long long n = now - (((now - j) % hist_depth) + hist_depth) % hist_depth;
    if (n < 0) return 0;                        /* not written since the start */
    double tn = t0_s + n * counter_period_s, pos = u->pos_rad + u->vel_rad_s * (tn - u->since_s);
    int enabled = (u->reg[STATUS] & 0x6F) == 0x27;
    double current_a = enabled ? (u->reg[MODE] == 4 ? get32(u->reg, TARGET_CUR) * CUR_SCALE : 0.05 * u->vel_rad_s / 50) : 0.0;
    if (w == 0 && n % cell_counts == 0 && n / cell_counts > u->last_cell) {   /* a cell sample first read */
        if (u->last_cell >= 0 && n / cell_counts > u->last_cell + 1) cells_unread += n / cell_counts - u->last_cell - 1;
        u->last_cell = n / cell_counts;
        history_entries++;
    }
    uint32_t v;
    switch (w) {
    case 0: return u->reg[STATUS];
    case 1: case 2: v = (uint32_t)n; break;
    case 3: case 4: v = (uint32_t)(int32_t)llround(fmod(pos / POS_SCALE, 2147483648.0)); break;
    case 5: case 6: v = (uint32_t)(int32_t)llround(u->vel_rad_s / VEL_SCALE); break;
    default: v = (uint32_t)(int32_t)llround(current_a / CUR_SCALE); break;
    }
    return (w % 2 == 1) ? v >> 16 : v & 0xFFFF;      /* odd word: high half (big word order) */
}

static void apply_writes(Unit *u, int addr, const uint8_t *p, int n, double t) {
    for (int i = 0; i < n; i++) {
        int a = addr + i;
        uint16_t v = (uint16_t)(p[2 * i] << 8 | p[2 * i + 1]);
        u->reg[a] = v;
        if (a == CONTROL) write_control(u, v, t);
    }
    if (addr <= TARGET_VEL + 1 && addr + n > TARGET_VEL) update_motion(u, t);
    if (addr <= MODE && addr + n > MODE) update_motion(u, t);
}

/* one request (MBAP + PDU) -> the response in out; its length */
static int answer(const uint8_t *q, int n, uint8_t *out, double t) {
    int id = q[6], fc = q[7], len = 0, err = 0;
    memcpy(out, q, 7);
    out[7] = fc;
    Unit *u = id >= 1 && id <= UNITS ? &unit[id] : NULL;
    if (!u) err = 0x0B;
    else {
        u->last_request_s = t;
        int a = q[8] << 8 | q[9], c = q[10] << 8 | q[11];
        int ra = a, rc = c;                          /* the read part */
        if (fc == 0x10 || fc == 0x17) {
            int wa = fc == 0x17 ? (q[12] << 8 | q[13]) : a, wc = fc == 0x17 ? (q[14] << 8 | q[15]) : c;
            int off = fc == 0x17 ? 17 : 13;
            if (wa + wc > NREG || off + 2 * wc > n) err = 0x02;
            else apply_writes(u, wa, q + off, wc, t);
        } else if (fc == 0x06) {
            if (a >= NREG) err = 0x02;
            else { apply_writes(u, a, q + 10, 1, t); memcpy(out + 8, q + 8, 4); len = 4; }
        } else if (fc != 0x03) err = 0x01;
        if (!err && fc == 0x10) { memcpy(out + 8, q + 8, 4); len = 4; }
        if (!err && (fc == 0x03 || fc == 0x17)) {
            if (hist_addr >= 0 && ra >= hist_addr && ra + rc <= hist_addr + 9 * hist_depth && rc <= 125) {
                history_reads++;
                out[8] = (uint8_t)(2 * rc);
                for (int i = 0; i < rc; i++) { uint16_t v = ring_word(u, ra + i, t); out[9 + 2 * i] = v >> 8; out[10 + 2 * i] = v & 0xFF; }
                len = 1 + 2 * rc;
            } else if (ra + rc > NREG || rc > 125) err = 0x02;
            else {
                fill(u, t);
                if (ra <= COUNTER && ra + rc > COUNTER) { block_reads++; count_cell(u); }
                out[8] = (uint8_t)(2 * rc);
                for (int i = 0; i < rc; i++) { out[9 + 2 * i] = u->reg[ra + i] >> 8; out[10 + 2 * i] = u->reg[ra + i] & 0xFF; }
                len = 1 + 2 * rc;
            }
        }
    }
    if (err) { out[7] = fc | 0x80; out[8] = err; len = 1; exceptions++; }
    out[4] = (uint8_t)((len + 2) >> 8); out[5] = (uint8_t)(len + 2);
    return 8 + len;
}

static void print_counters(void) {
    printf("{\"requests\": %lld, \"block_reads\": %lld, \"late_answers\": %lld, \"answer_delay_max_s\": %.6f, "
           "\"cells_unread\": %lld, \"repeat_reads\": %lld, \"exceptions\": %lld, \"watchdog_trips\": %lld, "
           "\"connections\": %lld, \"history_reads\": %lld, \"history_entries\": %lld, \"priority\": \"%s\"}\n",
           requests, block_reads, late_answers, delay_max_s, cells_unread, repeat_reads, exceptions, watchdog_trips,
           connections, history_reads, history_entries, granted);
    fflush(stdout);
}

static void watchdog(double t) {
    for (int i = 1; i <= UNITS; i++) {
        Unit *u = &unit[i];
        double limit = u->reg[COMM_TIMEOUT] * TIMEOUT_SCALE;
        if (limit > 0 && t - u->last_request_s > limit) {
            u->reg[COMM_TIMEOUT] = 0;               /* tripped once; the master re-arms it */
            watchdog_trips++;
            if ((u->reg[STATUS] & 0x6F) == 0x27) write_control(u, 2, t);
        }
    }
}

int main(int argc, char **argv) {
    if (argc < 5) {
        fprintf(stderr, "usage: %s COUNTER_PERIOD_S CELL_COUNTS LATE_S FIFO_PRIORITY\n", argv[0]);
        return 2;
    }
    counter_period_s = atof(argv[1]);
    cell_counts = atoll(argv[2]);
    late_s = atof(argv[3]);
    int prio = atoi(argv[4]);
    if (counter_period_s <= 0 || cell_counts < 1) { fprintf(stderr, "bad counter period or cell\n"); return 2; }
    if (argc >= 7) {
        hist_addr = atoll(argv[5]);
        hist_depth = atoll(argv[6]);
        if (hist_addr < NREG || hist_depth < 2 || hist_addr + 9 * hist_depth > 65536) {
            fprintf(stderr, "bad history address or depth\n");
            return 2;
        }
    }
    struct sched_param sp = {.sched_priority = prio};
    if (prio > 0 && sched_setscheduler(0, SCHED_FIFO, &sp) == 0) snprintf(granted, sizeof granted, "SCHED_FIFO %d", prio);
    if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) strncat(granted, ", mlockall", sizeof granted - strlen(granted) - 1);

    int ls[2], port[2], one = 1;
    for (int i = 0; i < 2; i++) {
        ls[i] = socket(AF_INET, SOCK_STREAM, 0);
        setsockopt(ls[i], SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
        struct sockaddr_in addr = {.sin_family = AF_INET, .sin_addr.s_addr = htonl(INADDR_LOOPBACK)};
        socklen_t alen = sizeof addr;
        if (bind(ls[i], (struct sockaddr *)&addr, sizeof addr) || listen(ls[i], 4) ||
            getsockname(ls[i], (struct sockaddr *)&addr, &alen)) {
            perror("listen");
            return 1;
        }
        port[i] = ntohs(addr.sin_port);
    }
    t0_s = now_s();
    for (int i = 0; i <= UNITS; i++) { unit[i].reg[STATUS] = 0x40; unit[i].last_cell = -1; unit[i].since_s = t0_s; }
    for (int i = 0; i < MAX_CONN; i++) conn[i].fd = -1;
    printf("ready %d %d %s\n", port[0], port[1], granted);
    fflush(stdout);

    uint8_t out[8192], ctrl[256];
    char line[256];
    for (;;) {
        struct pollfd fds[3 + MAX_CONN];
        int map[3 + MAX_CONN], nf = 0;
        fds[nf] = (struct pollfd){.fd = 0, .events = POLLIN}; map[nf++] = -1;
        fds[nf] = (struct pollfd){.fd = ls[0], .events = POLLIN}; map[nf++] = -2;
        fds[nf] = (struct pollfd){.fd = ls[1], .events = POLLIN}; map[nf++] = -2;
        for (int i = 0; i < MAX_CONN; i++)
            if (conn[i].fd >= 0) { fds[nf] = (struct pollfd){.fd = conn[i].fd, .events = POLLIN}; map[nf++] = i; }
        if (poll(fds, nf, 10) < 0) { if (errno == EINTR) continue; break; }
        watchdog(now_s());
        if (fds[0].revents) {
            ssize_t r = read(0, line, sizeof line - 1);
            if (r <= 0) break;
            print_counters();
        }
        for (int l = 1; l <= 2; l++) {
            if (!(fds[l].revents & POLLIN)) continue;
            int fd = accept(fds[l].fd, NULL, NULL);
            for (int i = 0; fd >= 0 && i < MAX_CONN; i++)
                if (conn[i].fd < 0) {
                    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
                    setsockopt(fd, SOL_SOCKET, SO_TIMESTAMPNS, &one, sizeof one);
                    conn[i].fd = fd; conn[i].len = 0; fd = -1; connections++;
                }
            if (fd >= 0) close(fd);                  /* no free slot */
        }
        for (int k = 3; k < nf; k++) {
            if (!fds[k].revents) continue;
            Conn *c = &conn[map[k]];
            struct iovec iov = {c->buf + c->len, sizeof c->buf - c->len};
            struct msghdr msg = {.msg_iov = &iov, .msg_iovlen = 1, .msg_control = ctrl, .msg_controllen = sizeof ctrl};
            ssize_t r = recvmsg(c->fd, &msg, MSG_DONTWAIT);
            if (r <= 0) {
                if (r < 0 && (errno == EAGAIN || errno == EINTR)) continue;
                close(c->fd); c->fd = -1;
                continue;
            }
            double t = now_s(), rx_delay = 0;
            struct timespec rx = {0, 0}, wall;
            for (struct cmsghdr *m = CMSG_FIRSTHDR(&msg); m; m = CMSG_NXTHDR(&msg, m))
                if (m->cmsg_level == SOL_SOCKET && m->cmsg_type == SO_TIMESTAMPNS) memcpy(&rx, CMSG_DATA(m), sizeof rx);
            if (rx.tv_sec) {   /* the drive's instant is when the request reached it, not when this process ran */
                clock_gettime(CLOCK_REALTIME, &wall);
                double behind = (wall.tv_sec - rx.tv_sec) + (wall.tv_nsec - rx.tv_nsec) * 1e-9;
                if (behind > 0) t -= behind;
            }
            c->len += (int)r;
            int used = 0, olen = 0;
            while (c->len - used >= 8) {             /* every complete request: answered in order, one send */
                const uint8_t *q = c->buf + used;
                int n = 6 + (q[4] << 8 | q[5]);
                if (n < 8 || n > (int)sizeof c->buf) { c->len = used = 0; break; }
                if (c->len - used < n) break;
                if (olen + 8 + 2 * 125 + 4 > (int)sizeof out) break;
                olen += answer(q, n, out + olen, t);
                requests++;
                used += n;
            }
            memmove(c->buf, c->buf + used, c->len - used);
            c->len -= used;
            if (olen && send(c->fd, out, olen, MSG_NOSIGNAL) != olen) { close(c->fd); c->fd = -1; continue; }
            if (rx.tv_sec) {
                clock_gettime(CLOCK_REALTIME, &wall);
                rx_delay = (wall.tv_sec - rx.tv_sec) + (wall.tv_nsec - rx.tv_nsec) * 1e-9;
                if (rx_delay > delay_max_s) delay_max_s = rx_delay;
                late_answers += rx_delay > late_s;
            }
        }
    }
    print_counters();
    return 0;
}
