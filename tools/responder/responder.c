/* Drives' stand-in for the paced CANopen benchmark: answers every SYNC with the drives' TPDOs.

   The benchmark (gearbench.benchmarks.drives_can --paced, stand-in "responder") measures the
   master, so what answers its SYNCs must not lose anything itself: hardware answers within
   microseconds whatever the PC does. This program does only that, compiled, at SCHED_FIFO above
   the master, with its memory locked. It speaks python-can's udp_multicast wire format: one UDP
   datagram per CAN frame, a msgpack map with the keys of can.interfaces.udp_multicast.utils.
   pack_message (timestamp, arbitration_id, is_extended_id, is_remote_frame, is_error_frame,
   channel, dlc, data, is_fd, bitrate_switch, error_state_indicator), in that order.

   The Python emulator configures the drives (SDO, NMT, heartbeats) and then stops sending PDOs
   (fixture command {"cmd": "pdo", "on": false}); this program takes over with the TPDO payloads
   the emulator sent last, the SYNC counter echo byte rewritten per SYNC (CiA 301 0x1019 counter).

   usage: responder [-s STAMPS] GROUP PORT PERIOD_S LATE_LIMIT_S FIFO_PRIORITY COBID:HEXPAYLOAD:ECHO_OFFSET ...
          (ECHO_OFFSET -1: no echo byte in that TPDO; STAMPS: a file that receives, at exit, the
          kernel receive time of every SYNC heard as int64 ns and its counter as int64, for the
          benchmark's SYNC jitter: this process is the bus's other end, apart from the master)
   stdin: "status" -> one JSON line of counters; EOF -> counters, exit.
   Counters: syncs_heard; syncs_missed (counter values skipped: a SYNC sent and never heard);
   frames_sent; late_answers (answers sent later than PERIOD_S after the SYNC was received by
   the kernel, SO_TIMESTAMPNS); too_late (answers later than LATE_LIMIT_S: the master no longer
   takes them); answer_delay_max_s; send_errors. */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <netinet/in.h>
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

#define MAX_STAMPS (1 << 20)      /* 17 min of SYNCs at 1 kHz (16 MB, locked) */

#define MAX_TPDO 16
#define SYNC_ID 0x80

typedef struct { uint32_t cob_id; uint8_t payload[8]; int len; int echo; } Tpdo;

static Tpdo tpdo[MAX_TPDO];
static int n_tpdo;
static long long syncs_heard, syncs_missed, frames_sent, late_answers, too_late, send_errors, no_counter;
static double delay_max_s;
static char granted[64] = "normal";
static int64_t *stamps;           /* pairs: receive time ns, counter (-1: none) */
static long n_stamps;

/* ---- msgpack: the few types python-can's pack_message produces ---- */
static int skip(const uint8_t *p, int n, int i);   /* index after the object at i, -1 if malformed */

static int str_at(const uint8_t *p, int n, int i, const char **s, int *len) {
    if (i >= n) return -1;
    uint8_t t = p[i];
    if ((t & 0xE0) == 0xA0) { *len = t & 0x1F; *s = (const char *)p + i + 1; return i + 1 + *len <= n ? i + 1 + *len : -1; }
    if (t == 0xD9 && i + 1 < n) { *len = p[i + 1]; *s = (const char *)p + i + 2; return i + 2 + *len <= n ? i + 2 + *len : -1; }
    return -1;
}

static int uint_at(const uint8_t *p, int n, int i, uint64_t *v) {
    if (i >= n) return -1;
    uint8_t t = p[i];
    if (t < 0x80) { *v = t; return i + 1; }
    int k = t == 0xCC ? 1 : t == 0xCD ? 2 : t == 0xCE ? 4 : t == 0xCF ? 8 : 0;
    if (!k || i + 1 + k > n) return -1;
    *v = 0;
    for (int j = 0; j < k; j++) *v = (*v << 8) | p[i + 1 + j];
    return i + 1 + k;
}

static int skip(const uint8_t *p, int n, int i) {
    if (i >= n) return -1;
    uint8_t t = p[i];
    if (t < 0x80 || t >= 0xE0 || t == 0xC0 || t == 0xC2 || t == 0xC3) return i + 1;
    if ((t & 0xE0) == 0xA0) return i + 1 + (t & 0x1F);
    switch (t) {
    case 0xCC: case 0xD0: return i + 2;
    case 0xCD: case 0xD1: return i + 3;
    case 0xCE: case 0xD2: case 0xCA: return i + 5;
    case 0xCF: case 0xD3: case 0xCB: return i + 9;
    case 0xC4: case 0xD9: return i + 1 < n ? i + 2 + p[i + 1] : -1;
    default: return -1;     /* maps, arrays, ext: not in a CAN frame */
    }
}

/* arbitration id and data of one datagram; 0 when it is a data frame, -1 otherwise */
static int parse(const uint8_t *p, int n, uint32_t *id, const uint8_t **data, int *len) {
    if (n < 1 || (p[0] & 0xF0) != 0x80) return -1;
    int entries = p[0] & 0x0F, i = 1, have_id = 0, bad = 0;
    *len = 0;
    for (int e = 0; e < entries && i >= 0; e++) {
        const char *key; int klen;
        i = str_at(p, n, i, &key, &klen);
        if (i < 0) return -1;
        if (klen == 14 && !memcmp(key, "arbitration_id", 14)) {
            uint64_t v = 0; i = uint_at(p, n, i, &v); *id = (uint32_t)v; have_id = 1;
        } else if (klen == 4 && !memcmp(key, "data", 4)) {
            if (i + 1 >= n || p[i] != 0xC4) return -1;
            *len = p[i + 1]; *data = p + i + 2; i = i + 2 + *len;
        } else if ((klen == 15 && !memcmp(key, "is_remote_frame", 15)) ||
                   (klen == 14 && !memcmp(key, "is_error_frame", 14))) {
            bad |= p[i] == 0xC3; i = skip(p, n, i);
        } else {
            i = skip(p, n, i);
        }
    }
    return i > 0 && i <= n && have_id && !bad ? 0 : -1;
}

static const char *KEYS[] = {"timestamp", "arbitration_id", "is_extended_id", "is_remote_frame",
                             "is_error_frame", "channel", "dlc", "data", "is_fd", "bitrate_switch",
                             "error_state_indicator"};

static int put_key(uint8_t *o, int i, int k) {
    int len = (int)strlen(KEYS[k]);
    o[i++] = 0xA0 | len;
    memcpy(o + i, KEYS[k], len);
    return i + len;
}

/* python-can's pack_message of a standard data frame */
static int pack(uint8_t *o, uint32_t id, const uint8_t *data, int len, double stamp) {
    int i = 0;
    o[i++] = 0x80 | 11;
    i = put_key(o, i, 0);
    o[i++] = 0xCB;
    uint64_t bits; memcpy(&bits, &stamp, 8);
    for (int j = 7; j >= 0; j--) o[i++] = (uint8_t)(bits >> (8 * j));
    i = put_key(o, i, 1);
    if (id < 0x80) o[i++] = (uint8_t)id;
    else if (id < 0x100) { o[i++] = 0xCC; o[i++] = (uint8_t)id; }
    else { o[i++] = 0xCD; o[i++] = (uint8_t)(id >> 8); o[i++] = (uint8_t)id; }
    for (int k = 2; k <= 4; k++) { i = put_key(o, i, k); o[i++] = 0xC2; }
    i = put_key(o, i, 5); o[i++] = 0xC0;
    i = put_key(o, i, 6); o[i++] = (uint8_t)len;
    i = put_key(o, i, 7); o[i++] = 0xC4; o[i++] = (uint8_t)len; memcpy(o + i, data, len); i += len;
    for (int k = 8; k <= 10; k++) { i = put_key(o, i, k); o[i++] = 0xC2; }
    return i;
}

static void print_counters(void) {
    printf("{\"syncs_heard\": %lld, \"syncs_missed\": %lld, \"frames_sent\": %lld, \"late_answers\": %lld, "
           "\"too_late\": %lld, \"answer_delay_max_s\": %.6f, \"send_errors\": %lld, "
           "\"syncs_without_counter\": %lld, \"priority\": \"%s\"}\n", syncs_heard, syncs_missed, frames_sent,
           late_answers, too_late, delay_max_s, send_errors, no_counter, granted);
    fflush(stdout);
}

static int hexbytes(const char *s, uint8_t *out, int max) {
    int n = 0;
    while (s[0] && s[1] && n < max) { unsigned v; if (sscanf(s, "%2x", &v) != 1) return -1; out[n++] = (uint8_t)v; s += 2; }
    return s[0] ? -1 : n;
}

int main(int argc, char **argv) {
    const char *stamps_path = NULL;
    if (argc > 2 && !strcmp(argv[1], "-s")) { stamps_path = argv[2]; argv += 2; argc -= 2; }
    if (argc < 7) {
        fprintf(stderr, "usage: %s GROUP PORT PERIOD_S LATE_LIMIT_S FIFO_PRIORITY COBID:HEXPAYLOAD:ECHO_OFFSET ...\n", argv[0]);
        return 2;
    }
    const char *group = argv[1];
    int port = atoi(argv[2]);
    double period_s = atof(argv[3]);
    double late_limit_s = atof(argv[4]);
    int prio = atoi(argv[5]);
    for (int a = 6; a < argc && n_tpdo < MAX_TPDO; a++) {
        char hex[64]; unsigned cob; int echo;
        if (sscanf(argv[a], "%x:%63[0-9a-fA-F]:%d", &cob, hex, &echo) != 3) { fprintf(stderr, "bad TPDO %s\n", argv[a]); return 2; }
        Tpdo *t = &tpdo[n_tpdo++];
        t->cob_id = cob; t->echo = echo; t->len = hexbytes(hex, t->payload, 8);
        if (t->len < 0 || echo >= t->len) { fprintf(stderr, "bad TPDO %s\n", argv[a]); return 2; }
    }

    if (stamps_path && !(stamps = calloc(2 * MAX_STAMPS, sizeof *stamps))) { perror("calloc"); return 1; }
    struct sched_param sp = {.sched_priority = prio};
    if (prio > 0 && sched_setscheduler(0, SCHED_FIFO, &sp) == 0) snprintf(granted, sizeof granted, "SCHED_FIFO %d", prio);
    if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) strncat(granted, ", mlockall", sizeof granted - strlen(granted) - 1);

    int s = socket(AF_INET, SOCK_DGRAM, 0), one = 1, rcvbuf = 4 << 20;
    setsockopt(s, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    setsockopt(s, SOL_SOCKET, SO_REUSEPORT, &one, sizeof one);
    setsockopt(s, SOL_SOCKET, SO_TIMESTAMPNS, &one, sizeof one);
    if (setsockopt(s, SOL_SOCKET, SO_RCVBUFFORCE, &rcvbuf, sizeof rcvbuf))   /* root: above rmem_max */
        setsockopt(s, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    unsigned char ttl = 0;   /* multicast that stays on this host (ip_mc_output): no frame to the NIC */
    setsockopt(s, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl);
    struct sockaddr_in addr = {.sin_family = AF_INET, .sin_port = htons(port), .sin_addr.s_addr = htonl(INADDR_ANY)};
    if (bind(s, (struct sockaddr *)&addr, sizeof addr)) { perror("bind"); return 1; }
    struct ip_mreq mreq;
    inet_pton(AF_INET, group, &mreq.imr_multiaddr);
    mreq.imr_interface.s_addr = htonl(INADDR_ANY);
    if (setsockopt(s, IPPROTO_IP, IP_ADD_MEMBERSHIP, &mreq, sizeof mreq)) { perror("IP_ADD_MEMBERSHIP"); return 1; }
    struct sockaddr_in dest = {.sin_family = AF_INET, .sin_port = htons(port)};
    inet_pton(AF_INET, group, &dest.sin_addr);
    printf("ready %s\n", granted);
    fflush(stdout);

    uint8_t buf[4096], out[256], ctrl[256];
    char line[256];
    int last_counter = -1, overflow = 240;   /* CiA 301 0x1019 as gearbench sets it */
    struct pollfd fds[2] = {{.fd = s, .events = POLLIN}, {.fd = 0, .events = POLLIN}};
    for (;;) {
        if (poll(fds, 2, -1) < 0) { if (errno == EINTR) continue; break; }
        if (fds[1].revents) {
            ssize_t r = read(0, line, sizeof line - 1);
            if (r <= 0) break;
            print_counters();
        }
        if (!(fds[0].revents & POLLIN)) continue;
        for (;;) {   /* every datagram waiting: the SYNCs in order */
            struct iovec iov = {buf, sizeof buf};
            struct msghdr msg = {.msg_iov = &iov, .msg_iovlen = 1, .msg_control = ctrl, .msg_controllen = sizeof ctrl};
            ssize_t n = recvmsg(s, &msg, MSG_DONTWAIT);
            if (n < 0) break;
            uint32_t id = 0; const uint8_t *data = NULL; int len = 0;
            if (parse(buf, (int)n, &id, &data, &len) || id != SYNC_ID) continue;
            struct timespec rx = {0, 0}, now;
            for (struct cmsghdr *c = CMSG_FIRSTHDR(&msg); c; c = CMSG_NXTHDR(&msg, c))
                if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SO_TIMESTAMPNS) memcpy(&rx, CMSG_DATA(c), sizeof rx);
            syncs_heard++;
            int counter = len > 0 ? data[0] : -1;
            if (stamps && n_stamps < MAX_STAMPS && rx.tv_sec) {
                stamps[2 * n_stamps] = (int64_t)rx.tv_sec * 1000000000LL + rx.tv_nsec;
                stamps[2 * n_stamps++ + 1] = counter;
            }
            if (counter < 0) no_counter++;
            else {
                if (last_counter >= 0) syncs_missed += ((counter - last_counter - 1) % overflow + overflow) % overflow;
                last_counter = counter;
            }
            clock_gettime(CLOCK_REALTIME, &now);
            double stamp = now.tv_sec + now.tv_nsec * 1e-9;
            for (int k = 0; k < n_tpdo; k++) {
                Tpdo *t = &tpdo[k];
                if (t->echo >= 0 && counter >= 0) t->payload[t->echo] = (uint8_t)counter;
                int m = pack(out, t->cob_id, t->payload, t->len, stamp);
                if (sendto(s, out, m, 0, (struct sockaddr *)&dest, sizeof dest) == m) frames_sent++;
                else send_errors++;
            }
            if (rx.tv_sec) {
                clock_gettime(CLOCK_REALTIME, &now);
                double delay = (now.tv_sec - rx.tv_sec) + (now.tv_nsec - rx.tv_nsec) * 1e-9;
                if (delay > delay_max_s) delay_max_s = delay;
                late_answers += delay > period_s;
                too_late += delay > late_limit_s;
            }
        }
    }
    if (stamps) {
        FILE *f = fopen(stamps_path, "wb");
        if (!f || fwrite(stamps, 2 * sizeof *stamps, n_stamps, f) != (size_t)n_stamps) perror(stamps_path);
        if (f) fclose(f);
    }
    print_counters();
    return 0;
}
