/* Unit tests of the portable firmware core against a fake board (run under ASan/UBSan). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "core.h"

#include "check.h" /* CHECK, failures */

/* ---------------------------------------------------------------- fake board */
static struct {
    uint32_t now;
    bool busy;
    int arms, disarms;
    uint8_t wire[1 << 20];
    size_t wire_len;
    int locks;      /* sync_lock(true) minus sync_lock(false): 0 between polls */
    int max_locks;
} B;

static void arm_capture(void *ctx, const struct dmdsm_set_config *cfg)
{
    (void)ctx;
    (void)cfg;
    B.arms++;
}
static void disarm_capture(void *ctx) { (void)ctx; B.disarms++; }
static uint32_t now_ticks(void *ctx) { (void)ctx; return B.now; }
static bool tx_busy(void *ctx) { (void)ctx; return B.busy; }
static void tx_start(void *ctx, const uint8_t *p, size_t n)
{
    (void)ctx;
    if (B.wire_len + n <= sizeof B.wire) {
        memcpy(B.wire + B.wire_len, p, n);
        B.wire_len += n;
    }
}

static void sync_lock(void *ctx, bool locked)
{
    (void)ctx;
    B.locks += locked ? 1 : -1;
    if (B.locks > B.max_locks)
        B.max_locks = B.locks;
}

static const struct dmdsm_board_ops ops = {NULL,      arm_capture, disarm_capture, now_ticks,
                                           tx_start, tx_busy,     sync_lock};
static const struct dmdsm_board_info info = {"test board", 1000000u, 3333333u, 8192u, 0, 0};
static struct dmdsm_core core;

/* ---------------------------------------------------------------- host side */
#define MAX_MSGS 256
static struct msg {
    uint8_t type, flags;
    uint16_t seq;
    uint8_t payload[DMDSM_MAX_PAYLOAD];
    size_t len;
} msgs[MAX_MSGS];
static size_t n_msgs;
static uint8_t host_buf[DMDSM_MAX_ENCODED];

static void reset(void)
{
    memset(&B, 0, sizeof B);
    dmdsm_core_init(&core, &ops, &info);
}

/* run the core until its queues are empty, then decode what it sent */
static void drain(void)
{
    for (int i = 0; i < 100 && (core.ctl_count || core.wave_count); i++)
        dmdsm_core_poll(&core);
    struct dmdsm_decoder d;
    struct dmdsm_frame f;
    dmdsm_decoder_init(&d, host_buf, sizeof host_buf);
    n_msgs = 0;
    for (size_t i = 0; i < B.wire_len; i++) {
        if (dmdsm_decoder_feed(&d, B.wire[i], &f) == DMDSM_RX_FRAME && n_msgs < MAX_MSGS) {
            struct msg *m = &msgs[n_msgs++];
            m->type = f.type;
            m->flags = f.flags;
            m->seq = f.seq;
            m->len = f.len;
            memcpy(m->payload, f.payload, f.len);
        }
    }
    CHECK(d.stats.crc_errors == 0 && d.stats.malformed == 0);
    B.wire_len = 0;
}

static void send(uint8_t type, uint16_t seq, uint8_t flags, const uint8_t *p, size_t n)
{
    uint8_t frame[256];
    size_t len = dmdsm_frame_encode(frame, sizeof frame, type, flags, seq, p, n);
    dmdsm_core_rx(&core, frame, len);
}

static void set_config(uint16_t seq, const struct dmdsm_set_config *c)
{
    uint8_t p[DMDSM_SET_CONFIG_FIXED_SIZE];
    send(DMDSM_MSG_SET_CONFIG, seq, 0, p, dmdsm_pack_set_config(c, p));
}

static void arm(uint16_t seq, uint32_t n)
{
    struct dmdsm_arm m = {.n_shots = n};
    uint8_t p[4];
    send(DMDSM_MSG_ARM, seq, 0, p, dmdsm_pack_arm(&m, p));
}

static struct dmdsm_status status(uint16_t seq)
{
    struct dmdsm_status s;
    memset(&s, 0, sizeof s);
    send(DMDSM_MSG_GET_STATUS, seq, 0, NULL, 0);
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_STATUS);
    dmdsm_unpack_status(msgs[0].payload, msgs[0].len, &s);
    return s;
}

/* expect exactly one NAK with this error and detail */
static void expect_nak(uint8_t error, uint16_t detail, uint16_t seq)
{
    drain();
    struct dmdsm_nak n = {0, 0, 0};
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_NAK);
    CHECK(dmdsm_unpack_nak(msgs[0].payload, msgs[0].len, &n));
    CHECK(n.error == error && n.detail == detail && msgs[0].seq == seq);
    CHECK(msgs[0].flags & DMDSM_FLAG_RESPONSE);
}

static void expect_ack(uint8_t command, uint16_t seq)
{
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_ACK && msgs[0].seq == seq &&
          msgs[0].payload[0] == command);
}

static const struct dmdsm_set_config good = {1024, 1, 1, 0, 0, 0, 0, 1000};

static void shot(uint16_t value, uint32_t edge)
{
    static uint16_t s[DMDSM_CORE_MAX_SAMPLES];
    for (size_t i = 0; i < DMDSM_CORE_MAX_SAMPLES; i++)
        s[i] = (uint16_t)(value + (i & 1));
    dmdsm_core_capture_done(&core, s, edge, 10, DMDSM_CAPTURE_OK);
}

/* ---------------------------------------------------------------- tests */
static void test_ping_identify(void)
{
    reset();
    uint8_t p[4] = {1, 2, 3, 4};
    send(DMDSM_MSG_PING, 7, 0, p, 4);
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_PONG && msgs[0].seq == 7 &&
          memcmp(msgs[0].payload, p, 4) == 0 && msgs[0].flags == DMDSM_FLAG_RESPONSE);
    send(DMDSM_MSG_IDENTIFY, 8, 0, NULL, 0);
    drain();
    struct dmdsm_identify_reply r;
    CHECK(n_msgs == 1 && dmdsm_unpack_identify_reply(msgs[0].payload, msgs[0].len, &r));
    CHECK(r.spec_hash == DMDSM_SPEC_HASH && r.protocol_version == DMDSM_PROTOCOL_VERSION);
    CHECK(r.board_len == strlen("test board") && memcmp(r.board, "test board", 10) == 0);
    CHECK(r.tick_hz == 1000000u && r.max_samples == 8192);
}

static void test_config_validation(void)
{
    reset();
    set_config(1, &good);
    expect_ack(DMDSM_MSG_SET_CONFIG, 1);
    struct { struct dmdsm_set_config c; uint16_t detail; } bad[] = {
        {{8, 1, 1, 0, 0, 0, 0, 0}, 1},        /* too few samples */
        {{9000, 1, 1, 0, 0, 0, 0, 0}, 1},     /* too many */
        {{1024, 0, 1, 0, 0, 0, 0, 0}, 2},     /* rate divider 0 */
        {{1024, 1, 0, 0, 0, 0, 0, 0}, 3},     /* no shots averaged */
        {{1024, 1, 5000, 0, 0, 0, 0, 0}, 3},  /* accumulator bound */
        {{1024, 1, 1, 1024, 0, 0, 0, 0}, 4},  /* pretrigger >= n_samples */
        {{1024, 1, 1, 0, 2, 0, 0, 0}, 5},     /* trigger edge */
        {{1024, 1, 1, 0, 0, 9, 0, 0}, 6},     /* modality */
        {{1024, 1, 1, 0, 0, 0, 3, 0}, 7},     /* sample format */
        {{8192, 1, 1, 0, 0, 0, 1, 0}, 7},     /* u32 sums of 8192 samples exceed a frame */
    };
    for (size_t i = 0; i < sizeof bad / sizeof bad[0]; i++) {
        set_config((uint16_t)(10 + i), &bad[i].c);
        expect_nak(DMDSM_ERROR_OUT_OF_RANGE, bad[i].detail, (uint16_t)(10 + i));
    }
    send(DMDSM_MSG_GET_CONFIG, 30, 0, NULL, 0);
    drain();
    struct dmdsm_config now;
    memset(&now, 0, sizeof now); /* padding compares equal in the memcmp below */
    CHECK(n_msgs == 1 && dmdsm_unpack_config(msgs[0].payload, msgs[0].len, &now));
    CHECK(memcmp(&now, &good, sizeof now) == 0); /* NAKs changed nothing */
    arm(31, 0);
    expect_ack(DMDSM_MSG_ARM, 31);
    set_config(32, &good);
    expect_nak(DMDSM_ERROR_BUSY, 0, 32);
    arm(33, 0);
    expect_nak(DMDSM_ERROR_BUSY, 0, 33);
}

static void test_bad_frames(void)
{
    reset();
    send(0x7E, 1, 0, NULL, 0);
    expect_nak(DMDSM_ERROR_UNKNOWN_TYPE, 0, 1);
    uint8_t p[4] = {0};
    send(DMDSM_MSG_PONG, 2, 0, p, 4); /* a device-to-host type */
    expect_nak(DMDSM_ERROR_UNKNOWN_TYPE, 0, 2);
    send(DMDSM_MSG_PING, 3, 0, p, 3);
    expect_nak(DMDSM_ERROR_BAD_LENGTH, 0, 3);
    /* another protocol version: hand-built frame */
    uint8_t raw[13] = {9, DMDSM_MSG_PING, 0, 4, 0, 0, 0, 0, 0};
    uint32_t crc = dmdsm_crc32(0, raw, 9);
    for (int i = 0; i < 4; i++)
        raw[9 + i] = (uint8_t)(crc >> (8 * i));
    size_t k = 0;
    uint8_t enc[40];
    enc[k++] = 0;
    size_t code_at = k++;
    uint8_t code = 1;
    for (int i = 0; i < 13; i++) {
        if (raw[i] == 0) {
            enc[code_at] = code;
            code_at = k++;
            code = 1;
        } else {
            enc[k++] = raw[i];
            code++;
        }
    }
    enc[code_at] = code;
    enc[k++] = 0;
    dmdsm_core_rx(&core, enc, k);
    expect_nak(DMDSM_ERROR_BAD_VERSION, 0, 4);
    /* garbage and damaged frames are counted, never answered */
    const uint8_t junk[] = {0, 5, 1, 2, 3, 4, 0, 0x03, 0x41, 0x41, 0, 7, 7, 7, 0};
    dmdsm_core_rx(&core, junk, sizeof junk);
    uint8_t frame[32];
    size_t n = dmdsm_frame_encode(frame, sizeof frame, DMDSM_MSG_PING, 0, 9, p, 4);
    frame[3] ^= 0x40;
    dmdsm_core_rx(&core, frame, n);
    drain();
    CHECK(n_msgs == 0);
    struct dmdsm_status s = status(5);
    CHECK(s.rx_crc_errors == 1);
    CHECK(s.rx_malformed == 3 + 1 + 1); /* junk, bad length, bad version */
    CHECK(s.rx_frames == 4 + 1);        /* four NAKed commands and get_status */
}

static void test_retransmission_executes_once(void)
{
    reset();
    struct dmdsm_arm m = {.n_shots = 3};
    uint8_t p[4];
    arm(9, 3);
    /* the same command again after a lost ack */
    send(DMDSM_MSG_ARM, 9, DMDSM_FLAG_RETRANSMIT, p, dmdsm_pack_arm(&m, p));
    drain();
    CHECK(n_msgs == 2 && msgs[0].type == DMDSM_MSG_ACK && msgs[1].type == DMDSM_MSG_ACK);
    CHECK(B.arms == 1);
}

static void test_a_new_client_never_gets_an_old_answer(void)
{
    reset();
    uint8_t p[4] = {1, 2, 3, 4};
    send(DMDSM_MSG_PING, 1, 0, p, 4); /* e.g. the stage client probing the wrong port */
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_PONG);
    send(DMDSM_MSG_IDENTIFY, 1, 0, NULL, 0); /* a new sensor client, also at seq 1 */
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_IDENTIFY_REPLY && msgs[0].seq == 1);
    /* a retransmission of another type at the last seq is executed, not answered stale */
    send(DMDSM_MSG_PING, 1, DMDSM_FLAG_RETRANSMIT, p, 4);
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_PONG);
}

static void test_averaging_and_shot_ids(void)
{
    reset();
    struct dmdsm_set_config c = good;
    c.n_average = 4;
    c.n_samples = 64;
    set_config(1, &c);
    expect_ack(DMDSM_MSG_SET_CONFIG, 1);
    arm(2, 2);
    expect_ack(DMDSM_MSG_ARM, 2);
    uint16_t values[8] = {100, 101, 101, 101, 65535, 65535, 65534, 65535};
    for (int i = 0; i < 8; i++) {
        B.now += 100;
        shot(values[i], B.now - 5);
    }
    drain();
    CHECK(n_msgs == 2);
    struct dmdsm_waveform w;
    CHECK(dmdsm_unpack_waveform(msgs[0].payload, msgs[0].len, &w));
    CHECK(w.shot_id == 0 && w.n_average == 4 && w.samples_len == 128);
    /* mean of 100,101,101,101 = 100.75 -> 101; odd samples +1 -> 101.75 -> 102 */
    CHECK(w.samples[0] == 101 && w.samples[2] == 102);
    CHECK(w.timestamp == 95 && w.trigger_phase == 10);
    CHECK(dmdsm_unpack_waveform(msgs[1].payload, msgs[1].len, &w));
    CHECK(w.shot_id == 1 && msgs[1].seq == 1);
    CHECK((w.samples[0] | w.samples[1] << 8) == 65535); /* 65534.75 rounds up, no wrap */
    CHECK(core.state == DMDSM_STATE_IDLE && B.disarms == 1);
}

static void test_u32_sums_do_not_overflow(void)
{
    reset();
    struct dmdsm_set_config c = good;
    c.n_average = 4096;
    c.n_samples = 16;
    c.sample_format = DMDSM_SAMPLE_FORMAT_U32_SUM;
    set_config(1, &c);
    arm(2, 1);
    drain();
    for (int i = 0; i < 4096; i++)
        shot(65534, 0); /* odd samples are 65535 */
    drain();
    struct dmdsm_waveform w;
    CHECK(n_msgs == 1 && dmdsm_unpack_waveform(msgs[0].payload, msgs[0].len, &w));
    const uint8_t *s = w.samples;
    uint32_t s1 = (uint32_t)s[4] | (uint32_t)s[5] << 8 | (uint32_t)s[6] << 16 |
                  (uint32_t)s[7] << 24;
    CHECK(s1 == 4096u * 65535u && w.samples_len == 64);
}

static void test_busy_link_skips_triggers_and_never_drops_a_waveform(void)
{
    reset();
    struct dmdsm_set_config c = good;
    c.n_samples = 256;
    set_config(1, &c);
    arm(2, 0);
    drain();
    B.busy = true; /* the link is stuck on one frame */
    dmdsm_core_log(&core, 1, 0, "x"); /* occupies the link */
    for (int i = 0; i < 10; i++)
        shot(1000, 0);
    CHECK(core.count.triggers_skipped == 8); /* two slots filled, eight triggers skipped */
    B.busy = false;
    drain();
    CHECK(n_msgs == 3); /* log + two whole waveforms */
    struct dmdsm_waveform w;
    CHECK(dmdsm_unpack_waveform(msgs[2].payload, msgs[2].len, &w) && w.shot_id == 1);
    shot(1000, 0);
    drain();
    CHECK(n_msgs == 1 && dmdsm_unpack_waveform(msgs[0].payload, msgs[0].len, &w));
    CHECK(w.shot_id == 2 && w.triggers_skipped == 8); /* no gap: ids count waveforms sent */
    struct dmdsm_status s = status(3);
    CHECK(s.triggers_skipped == 8 && s.shots_sent == 3 && s.triggers == 11);
    CHECK(s.last_error == DMDSM_ERROR_NONE); /* a skip is not an error */
}

/* a board that knows its link's rate: 1 MHz ticks, 1 kHz laser, 100 kB/s (10 us a byte) */
static const struct dmdsm_board_info timed = {"test board", 1000000u, 3333333u, 8192u, 0,
                                              100000u};

/* 300 ms of a 1 kHz laser on a link that takes 10 us a byte, the main loop polling every
 * 100 us: the waveform frames sent, the wire's idle time and the longest a waveform waited
 * on the board between its burst's end and the wire (us) */
static void run_busy_link(const struct dmdsm_board_info *board, uint32_t *frames_out,
                          uint32_t *idle_out, uint32_t *max_wait_out)
{
    memset(&B, 0, sizeof B);
    dmdsm_core_init(&core, &ops, board);
    struct dmdsm_set_config c = good;
    c.n_samples = 512; /* a 1 kB frame: ~10.3 ms on the wire; a burst is 154 us */
    set_config(1, &c);
    arm(2, 0);
    drain();
    uint32_t wire_end = 0;           /* the fake wire is busy until then (us) */
    uint32_t queued[4], n_queued = 0; /* edges of the shots taken, not yet on the wire */
    uint32_t frames = 0, max_wait = 0, idle = 0;
    for (uint32_t t = 100; t <= 300000; t += 100) { /* the main loop polls every 100 us */
        B.now = t;
        B.busy = t < wire_end;
        for (int event = 0; event < 2; event++) {
            size_t before = B.wire_len;
            uint32_t skipped = core.count.triggers_skipped;
            if (event == 0) {
                dmdsm_core_poll(&core);
            } else if (t % 1000 == 0) { /* the laser, 1 kHz */
                /* what the core says before the shot (an emulator computes samples only
                 * for the shots it takes) is what it then does */
                bool takes = dmdsm_core_takes_shot(&core, t);
                shot(1000, t);
                CHECK(takes == (core.count.triggers_skipped == skipped));
                if (core.count.triggers_skipped == skipped && n_queued < 4)
                    queued[n_queued++] = t;
            }
            if (B.wire_len == before)
                continue;
            /* a waveform frame went on the wire now: how long it waited since its burst */
            CHECK(n_queued > 0);
            uint32_t wait = t - (queued[0] + 154u > t ? t : queued[0] + 154u);
            if (frames > 0 && wait > max_wait)
                max_wait = wait;
            memmove(queued, queued + 1, sizeof queued[0] * --n_queued);
            if (frames > 0 && t > wire_end)
                idle += t - wire_end;
            frames++;
            wire_end = t + (uint32_t)(B.wire_len - before) * 10u;
            B.busy = true;
            B.wire_len = 0;
        }
    }
    *frames_out = frames;
    *idle_out = idle;
    *max_wait_out = max_wait;
}

static void test_a_busy_link_takes_the_shot_that_is_ready_as_the_wire_frees(void)
{
    uint32_t frames, idle, max_wait;
    run_busy_link(&timed, &frames, &idle, &max_wait);
    /* the wire is kept full (one frame per ~10.4 ms, idle only for the poll's grain) and no
     * waveform waits longer than one laser period */
    CHECK(frames >= 28 && idle <= frames * 200u);
    CHECK(max_wait <= 1000u + 100u);
    CHECK(core.count.triggers_skipped > 250);
    /* a board that does not know its link's rate fills both slots: the same frames, each
     * waiting about one frame time */
    run_busy_link(&info, &frames, &idle, &max_wait);
    CHECK(frames >= 28 && max_wait > 9000u);
}

static void test_an_arm_for_n_sends_n_waveforms_over_a_slow_link(void)
{
    reset();
    struct dmdsm_set_config c = good;
    c.n_samples = 256;
    c.n_average = 3;
    set_config(1, &c);
    arm(2, 5);
    drain();
    uint32_t sent = 0, next_id = 0;
    for (int i = 0; i < 200 && core.state != DMDSM_STATE_IDLE; i++) {
        B.busy = (i % 7) != 0; /* the link frees a slot now and then */
        bool takes = dmdsm_core_takes_shot(&core, 0);
        uint32_t skipped = core.count.triggers_skipped, triggers = core.count.triggers;
        shot(1000, 0); /* averaged: counted as a trigger and not as a skipped one */
        CHECK(takes == (core.count.triggers > triggers &&
                        core.count.triggers_skipped == skipped));
        if (!B.busy) {
            drain();
            for (size_t k = 0; k < n_msgs; k++) {
                struct dmdsm_waveform w;
                if (msgs[k].type == DMDSM_MSG_WAVEFORM &&
                    dmdsm_unpack_waveform(msgs[k].payload, msgs[k].len, &w)) {
                    CHECK(w.shot_id == next_id++ && w.n_average == 3);
                    sent++;
                }
            }
        }
    }
    B.busy = false;
    drain();
    for (size_t k = 0; k < n_msgs; k++)
        if (msgs[k].type == DMDSM_MSG_WAVEFORM)
            sent++;
    CHECK(sent == 5 && core.state == DMDSM_STATE_IDLE);
    struct dmdsm_status s = status(3);
    CHECK(s.shots_sent == 5 && s.triggers_skipped > 0);
    CHECK(s.triggers == 5u * 3u + s.triggers_skipped); /* every trigger averaged or skipped */
}

static void test_disarm_discards_partial_average(void)
{
    reset();
    struct dmdsm_set_config c = good;
    c.n_average = 10;
    set_config(1, &c);
    arm(2, 0);
    drain();
    for (int i = 0; i < 5; i++)
        shot(7, 0);
    send(DMDSM_MSG_DISARM, 3, 0, NULL, 0);
    expect_ack(DMDSM_MSG_DISARM, 3);
    shot(7, 0); /* a late burst is ignored */
    drain();
    CHECK(n_msgs == 0 && core.state == DMDSM_STATE_IDLE && core.count.triggers == 5);
}

static void test_trigger_timeout(void)
{
    reset();
    set_config(1, &good); /* 1000 ms at 1 MHz ticks */
    arm(2, 5);
    drain();
    B.now += 999000;
    dmdsm_core_poll(&core);
    CHECK(core.state == DMDSM_STATE_ARMED);
    B.now += 2000;
    dmdsm_core_poll(&core);
    drain();
    CHECK(core.state == DMDSM_STATE_IDLE && core.count.no_trigger_timeouts == 1);
    struct dmdsm_log l;
    CHECK(n_msgs == 1 && dmdsm_unpack_log(msgs[0].payload, msgs[0].len, &l));
    CHECK(l.code == DMDSM_ERROR_NO_TRIGGER && !(msgs[0].flags & DMDSM_FLAG_RESPONSE));
}

static void test_timestamps_survive_wrap(void)
{
    reset();
    B.now = 0xFFFFFF00u;
    dmdsm_core_poll(&core);
    set_config(1, &good);
    arm(2, 3);
    drain();
    B.now = 0xFFFFFFF8u;
    shot(1, 0xFFFFFFF0u);
    B.now = 0x00000100u; /* the 32-bit counter wrapped */
    shot(1, 0x00000080u);
    shot(1, 0x000000F0u);
    drain();
    struct dmdsm_waveform w[3];
    memset(w, 0, sizeof w);
    CHECK(n_msgs == 3);
    for (size_t i = 0; i < 3 && i < n_msgs; i++)
        dmdsm_unpack_waveform(msgs[i].payload, msgs[i].len, &w[i]);
    CHECK(w[0].timestamp == 0xFFFFFFF0u);
    CHECK(w[1].timestamp == 0x100000080ull && w[2].timestamp == 0x1000000F0ull);
}

/* one extension of 32-bit ticks for the laser edges and the sync edges: at most one wrap old */
static void test_tick_extension(void)
{
    const uint64_t now = 0x300000005ull;
    CHECK(dmdsm_core_extend(now, 0x00000005u) == now);
    CHECK(dmdsm_core_extend(now, 0x00000001u) == 0x300000001ull);
    CHECK(dmdsm_core_extend(now, 0xFFFFFFFEu) == 0x2FFFFFFFEull); /* before the wrap */
    CHECK(dmdsm_core_extend(now, 0x00000006u) == 0x200000006ull); /* a whole wrap old */
    CHECK(dmdsm_core_extend(0x10ull, 0x00000008u) == 0x8ull);
}

static void test_overrun_is_counted_not_averaged(void)
{
    reset();
    set_config(1, &good);
    arm(2, 1);
    drain();
    static uint16_t s[DMDSM_CORE_MAX_SAMPLES];
    dmdsm_core_capture_done(&core, s, 0, 0, DMDSM_CAPTURE_OVERRUN);
    drain();
    CHECK(n_msgs == 0 && core.count.adc_overruns == 1 && core.state == DMDSM_STATE_ARMED);
    shot(5, 0);
    drain();
    struct dmdsm_waveform w;
    CHECK(n_msgs == 1 && dmdsm_unpack_waveform(msgs[0].payload, msgs[0].len, &w));
    CHECK(w.adc_overruns == 1 && w.samples[0] == 5);
}

static void test_integrity_fault_is_counted_not_averaged(void)
{
    reset();
    struct dmdsm_set_config cfg = good;
    cfg.n_average = 2;
    set_config(1, &cfg);
    arm(2, 1);
    drain();
    static uint16_t stale[DMDSM_CORE_MAX_SAMPLES];
    for (size_t i = 0; i < DMDSM_CORE_MAX_SAMPLES; i++)
        stale[i] = 60000u; /* what a stalled ring would hold: must not reach the average */
    B.now = 1000;
    shot(4, 0);
    int arms = B.arms;
    dmdsm_core_capture_done(&core, stale, 100, 3, DMDSM_CAPTURE_INTEGRITY);
    drain();
    CHECK(n_msgs == 0 && core.count.integrity_faults == 1 && core.count.adc_overruns == 0);
    CHECK(core.state == DMDSM_STATE_ARMED && B.arms == arms + 1 && core.n_in_avg == 1);
    CHECK(core.count.triggers == 2);
    struct dmdsm_status s = status(3);
    CHECK(s.integrity_faults == 1 && s.adc_overruns == 0);
    CHECK(s.last_error == DMDSM_ERROR_SAMPLE_INTEGRITY);
    shot(6, 200);
    drain();
    struct dmdsm_waveform w;
    CHECK(n_msgs == 1 && dmdsm_unpack_waveform(msgs[0].payload, msgs[0].len, &w));
    CHECK(w.integrity_faults == 1 && w.adc_overruns == 0 && w.n_average == 2);
    /* little-endian u16 means: (4 + 6) / 2 and (5 + 7) / 2, no 60000 from the dropped burst */
    CHECK(w.samples[0] == 5 && w.samples[1] == 0 && w.samples[2] == 6 && w.samples[3] == 0);
    CHECK(w.timestamp == 0); /* the first good edge, not the dropped one */
}

static void test_unavailable_capture_naks_arm(void)
{
    static const struct dmdsm_board_info broken = {"test board", 1000000u, 3333333u, 8192u,
                                                   DMDSM_ERROR_ADC_FAILURE, 0};
    memset(&B, 0, sizeof B);
    dmdsm_core_init(&core, &ops, &broken);
    dmdsm_core_log(&core, DMDSM_LOG_LEVEL_ERROR, DMDSM_ERROR_ADC_FAILURE,
                   "boot: ADC calibration did not finish after 100 ms; acquisition unavailable");
    drain();
    struct dmdsm_log l;
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_LOG && dmdsm_unpack_log(msgs[0].payload,
                                                                         msgs[0].len, &l));
    CHECK(l.level == DMDSM_LOG_LEVEL_ERROR && l.code == DMDSM_ERROR_ADC_FAILURE);
    CHECK(status(1).last_error == DMDSM_ERROR_ADC_FAILURE);
    arm(2, 1);
    expect_nak(DMDSM_ERROR_ADC_FAILURE, 0, 2);
    CHECK(B.arms == 0 && core.state == DMDSM_STATE_IDLE);
    set_config(3, &good); /* everything else still works */
    expect_ack(DMDSM_MSG_SET_CONFIG, 3);
    /* a warning does not become last_error */
    reset();
    dmdsm_core_log(&core, DMDSM_LOG_LEVEL_WARNING, DMDSM_ERROR_NO_TRIGGER, "w");
    drain();
    CHECK(status(4).last_error == DMDSM_ERROR_NONE);
}

static void test_clock_sync(void)
{
    reset();
    B.now = 12345;
    struct dmdsm_clock_sync m = {.host_time_ns = 0x1122334455667788ull};
    uint8_t p[8];
    send(DMDSM_MSG_CLOCK_SYNC, 4, 0, p, dmdsm_pack_clock_sync(&m, p));
    drain();
    struct dmdsm_clock_sync_reply r;
    CHECK(n_msgs == 1 && dmdsm_unpack_clock_sync_reply(msgs[0].payload, msgs[0].len, &r));
    CHECK(r.host_time_ns == m.host_time_ns && r.device_ticks == 12345);
}

/* a burst of step edges is one motion_sync once quiet for DMDSM_SYNC_QUIET_MS, across a wrap */
static void test_motion_sync_bursts(void)
{
    reset();
    const uint32_t ms = info.tick_hz / 1000u;
    B.now = 0xFFFFFF00u - 30u * ms;
    dmdsm_core_poll(&core);
    uint32_t t = B.now + 1000u;
    for (int i = 0; i < 500; i++, t += 123u) /* 500 steps, crossing the 32-bit wrap */
        dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_X, t);
    uint32_t last = t - 123u;
    B.now = last + (DMDSM_SYNC_QUIET_MS - 1u) * ms; /* not quiet long enough yet */
    dmdsm_core_poll(&core);
    drain();
    CHECK(n_msgs == 0);
    B.now = last + DMDSM_SYNC_QUIET_MS * ms;
    dmdsm_core_poll(&core);
    drain();
    CHECK(n_msgs == 1 && msgs[0].type == DMDSM_MSG_MOTION_SYNC);
    struct dmdsm_motion_sync m;
    memset(&m, 0, sizeof m);
    CHECK(dmdsm_unpack_motion_sync(msgs[0].payload, msgs[0].len, &m));
    uint64_t first = 0xFFFFFF00u - 30u * ms + 1000u;
    CHECK(m.burst_id == 0 && m.edges == 500 && m.first_edge == first &&
          m.input == DMDSM_SYNC_INPUT_X);
    CHECK(m.last_edge == first + 499u * 123u && m.last_edge > 0xFFFFFFFFull);
    CHECK(B.locks == 0 && B.max_locks == 1);
    /* the next move is the next burst */
    dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_X, B.now + 5u);
    dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_X, B.now + 9u);
    B.now += 9u + 25u * ms;
    dmdsm_core_poll(&core);
    drain();
    CHECK(n_msgs == 1 && dmdsm_unpack_motion_sync(msgs[0].payload, msgs[0].len, &m));
    CHECK(m.burst_id == 1 && m.edges == 2 && m.last_edge - m.first_edge == 4u);
    dmdsm_core_poll(&core);
    drain();
    CHECK(n_msgs == 0); /* reported once */
}

/* each waveform counts the sync edges before each of its shots' laser edges, even when the
 * capture completes after later edges came in, and across the 32-bit wrap */
static void test_waveforms_count_the_steps_before_their_shots(void)
{
    reset();
    struct dmdsm_set_config c = good;
    c.n_average = 3;
    c.n_samples = 16;
    set_config(1, &c);
    expect_ack(DMDSM_MSG_SET_CONFIG, 1);
    arm(2, 2);
    expect_ack(DMDSM_MSG_ARM, 2);
    B.now = 0xFFFFF000u;
    uint32_t step = 0xFFFFF000u; /* X steps every 150 ticks from here */
    uint32_t counts[6], counts_a[6];
    for (int i = 0; i < 6; i++) {
        uint32_t laser = 0xFFFFF000u + 700u * (uint32_t)i + 75u; /* between two steps */
        /* the capture completes 4 steps (600 ticks) after its laser edge */
        while ((int32_t)(step - (laser + 600u)) <= 0) {
            dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_X, step);
            if (((step - 0xFFFFF000u) / 150u) % 3u == 0) /* the table steps a third as often */
                dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_A, step + 7u);
            step += 150u;
        }
        B.now = laser + 600u;
        counts[i] = (laser - 0xFFFFF000u) / 150u + 1u; /* edges at or before the laser's */
        counts_a[i] = (laser - 0xFFFFF000u - 7u) / 450u + 1u; /* A: 7 ticks later, 450 apart */
        shot(100, laser);
    }
    drain();
    CHECK(n_msgs == 2);
    struct dmdsm_waveform w;
    CHECK(dmdsm_unpack_waveform(msgs[0].payload, msgs[0].len, &w));
    CHECK(w.sync_steps == counts[0] + counts[1] + counts[2]);
    CHECK(w.sync_steps_a == counts_a[0] + counts_a[1] + counts_a[2]);
    CHECK(dmdsm_unpack_waveform(msgs[1].payload, msgs[1].len, &w));
    CHECK(w.sync_steps == counts[3] + counts[4] + counts[5] && counts[5] == 24u);
    CHECK(w.sync_steps_a == counts_a[3] + counts_a[4] + counts_a[5] && counts_a[5] == 8u);
    CHECK(B.locks == 0);
    CHECK(dmdsm_core_sync_count_at(&core, DMDSM_SYNC_INPUT_X, step + 1000u) ==
          core.sync[DMDSM_SYNC_INPUT_X].edges);
    /* an input the core does not have counts nothing and takes no edge */
    dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUTS, step);
    CHECK(dmdsm_core_sync_count_at(&core, DMDSM_SYNC_INPUTS, step + 1000u) == 0);
}

/* the X and A inputs make bursts of their own, each reported with its input once that input
 * is quiet, whatever the other does meanwhile (the table turning on while X has stopped) */
static void test_two_inputs_burst_apart(void)
{
    reset();
    const uint32_t ms = info.tick_hz / 1000u;
    B.now = 1000u;
    dmdsm_core_poll(&core);
    uint32_t t = B.now;
    for (int i = 0; i < 40; i++, t += ms) { /* X steps 10 ms, A steps through 40 ms */
        if (i < 10)
            dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_X, t);
        dmdsm_core_sync_edge(&core, DMDSM_SYNC_INPUT_A, t + 3u);
        B.now = t + 3u;
        dmdsm_core_poll(&core);
    }
    drain();
    /* X's 10 edges ended 30 ms ago: reported; A still steps */
    CHECK(n_msgs == 1);
    struct dmdsm_motion_sync m;
    memset(&m, 0, sizeof m);
    CHECK(dmdsm_unpack_motion_sync(msgs[0].payload, msgs[0].len, &m));
    CHECK(m.input == DMDSM_SYNC_INPUT_X && m.edges == 10 && m.burst_id == 0);
    CHECK(m.first_edge == 1000u && m.last_edge == 1000u + 9u * ms);
    B.now += DMDSM_SYNC_QUIET_MS * ms;
    dmdsm_core_poll(&core);
    drain();
    CHECK(n_msgs == 1 && dmdsm_unpack_motion_sync(msgs[0].payload, msgs[0].len, &m));
    CHECK(m.input == DMDSM_SYNC_INPUT_A && m.edges == 40 && m.burst_id == 1);
    CHECK(m.first_edge == 1003u && m.last_edge == 1003u + 39u * ms);
    CHECK(B.locks == 0);
}

int main(void)
{
    test_ping_identify();
    test_config_validation();
    test_bad_frames();
    test_retransmission_executes_once();
    test_a_new_client_never_gets_an_old_answer();
    test_averaging_and_shot_ids();
    test_u32_sums_do_not_overflow();
    test_busy_link_skips_triggers_and_never_drops_a_waveform();
    test_a_busy_link_takes_the_shot_that_is_ready_as_the_wire_frees();
    test_an_arm_for_n_sends_n_waveforms_over_a_slow_link();
    test_disarm_discards_partial_average();
    test_trigger_timeout();
    test_timestamps_survive_wrap();
    test_tick_extension();
    test_overrun_is_counted_not_averaged();
    test_integrity_fault_is_counted_not_averaged();
    test_unavailable_capture_naks_arm();
    test_clock_sync();
    test_motion_sync_bursts();
    test_waveforms_count_the_steps_before_their_shots();
    test_two_inputs_burst_apart();
    if (failures) {
        fprintf(stderr, "test_core: %d check(s) failed\n", failures);
        return 1;
    }
    printf("test_core: all checks passed\n");
    return 0;
}
