/* Generated from protocol/messages.toml by protocol/gen_c.py: do not edit. */
/* The dmdsm protocol: constants, enums, message structs and codecs. */
#ifndef DMDSM_SPEC_H
#define DMDSM_SPEC_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define DMDSM_PROTOCOL_VERSION 1u
#define DMDSM_SPEC_HASH UINT64_C(0xd3ea52681c7f7efb)
#define DMDSM_MAX_PAYLOAD 16448u
#define DMDSM_MAX_COMMAND_PAYLOAD 64u
#define DMDSM_SYNC_QUIET_MS 20u
#define DMDSM_HEADER_SIZE 5u
#define DMDSM_CRC_SIZE 4u
/* largest un-stuffed frame and largest COBS frame between delimiters */
#define DMDSM_MAX_RAW 16457u
#define DMDSM_MAX_ENCODED 16522u
#define DMDSM_ENCODED_SIZE(raw) ((raw) + (raw) / 254u + 1u)

#define DMDSM_FLAG_RESPONSE 0x01u /* this frame answers the command with the same seq */
#define DMDSM_FLAG_RETRANSMIT 0x02u /* the host re-sends a command after a timeout (same seq) */

/* NAK and log codes */
enum dmdsm_error {
    DMDSM_ERROR_NONE = 0, /* no error */
    DMDSM_ERROR_UNKNOWN_TYPE = 1, /* the command type is not known to this firmware */
    DMDSM_ERROR_BAD_LENGTH = 2, /* the payload length does not match the command */
    DMDSM_ERROR_OUT_OF_RANGE = 3, /* a field is outside its documented range; nothing was changed */
    DMDSM_ERROR_BUSY = 4, /* not allowed while armed: disarm first */
    DMDSM_ERROR_BAD_VERSION = 5, /* the frame's protocol version is not this firmware's */
    DMDSM_ERROR_NOT_ARMED = 6, /* the command needs an armed acquisition */
    DMDSM_ERROR_NO_TRIGGER = 7, /* no photodiode edge within trigger_timeout_ms */
    DMDSM_ERROR_TX_OVERFLOW = 8, /* not raised since firmware 0.2 (a trigger with no free waveform slot is skipped, not dropped); kept so that the codes keep their values */
    DMDSM_ERROR_ADC_OVERRUN = 9, /* the ADC or its DMA overran during a burst */
    DMDSM_ERROR_INTERNAL = 10, /* firmware fault; the message text says where */
    DMDSM_ERROR_SAMPLE_INTEGRITY = 11, /* a burst was dropped: the DMA's write position disagreed with the timer (a missed or late ADC trigger) */
    DMDSM_ERROR_CLOCK_FAILURE = 12, /* HSE, PLL or the clock switch did not become ready; the board runs on HSI 64 MHz without acquisition */
    DMDSM_ERROR_POWER_FAILURE = 13, /* the voltage scale (VOS0/VOS1) was not confirmed; the board runs at a safe lower clock (the log says which) */
    DMDSM_ERROR_ADC_FAILURE = 14, /* ADC calibration or ready timed out at boot; acquisition is unavailable */
};

/* acquisition state machine */
enum dmdsm_state {
    DMDSM_STATE_IDLE = 0, /* not armed; configuration may change */
    DMDSM_STATE_ARMED = 1, /* waiting for a photodiode edge */
    DMDSM_STATE_CAPTURING = 2, /* DMA burst in progress */
    DMDSM_STATE_SENDING = 3, /* averaging done, waveform queued for the link */
};

/* photodiode edge that starts a burst */
enum dmdsm_trigger_edge {
    DMDSM_TRIGGER_EDGE_RISING = 0, /* rising edge */
    DMDSM_TRIGGER_EDGE_FALLING = 1, /* falling edge */
};

/* which sensing path the laser shot uses (paper III-1) */
enum dmdsm_modality {
    DMDSM_MODALITY_OA = 0, /* optoacoustic: laser on the target, one-way acoustic path */
    DMDSM_MODALITY_US = 1, /* pulse-echo ultrasound: laser drives the transmitter, round trip */
};

/* element type of a waveform's samples */
enum dmdsm_sample_format {
    DMDSM_SAMPLE_FORMAT_U16_MEAN = 0, /* u16 ADC counts, mean of n_average shots rounded to nearest */
    DMDSM_SAMPLE_FORMAT_U32_SUM = 1, /* u32 sum of n_average shots of u16 counts (keeps sub-LSB precision) */
};

/* which of the stage's STEP lines a motion-sync input is wired to (docs/firmware.md) */
enum dmdsm_sync_input {
    DMDSM_SYNC_INPUT_X = 0, /* the X stepper's STEP line (PB3, TIM2 CH2): the fly lines' axis */
    DMDSM_SYNC_INPUT_A = 1, /* the turntable's STEP line (the former E0 driver; PB10, TIM2 CH3): the table's turn */
};

/* severity of a log message */
enum dmdsm_log_level {
    DMDSM_LOG_LEVEL_DEBUG = 0, /* debug */
    DMDSM_LOG_LEVEL_INFO = 1, /* info */
    DMDSM_LOG_LEVEL_WARNING = 2, /* warning */
    DMDSM_LOG_LEVEL_ERROR = 3, /* error */
};

enum dmdsm_msg_type {
    DMDSM_MSG_PING = 0x01,
    DMDSM_MSG_IDENTIFY = 0x02,
    DMDSM_MSG_GET_CONFIG = 0x03,
    DMDSM_MSG_SET_CONFIG = 0x04,
    DMDSM_MSG_ARM = 0x05,
    DMDSM_MSG_DISARM = 0x06,
    DMDSM_MSG_GET_STATUS = 0x07,
    DMDSM_MSG_CLOCK_SYNC = 0x08,
    DMDSM_MSG_PONG = 0x81,
    DMDSM_MSG_IDENTIFY_REPLY = 0x82,
    DMDSM_MSG_CONFIG = 0x83,
    DMDSM_MSG_STATUS = 0x87,
    DMDSM_MSG_CLOCK_SYNC_REPLY = 0x88,
    DMDSM_MSG_ACK = 0xf0,
    DMDSM_MSG_NAK = 0xf1,
    DMDSM_MSG_WAVEFORM = 0xa0,
    DMDSM_MSG_LOG = 0xa1,
    DMDSM_MSG_MOTION_SYNC = 0xa2,
};

/* ping: liveness check and round-trip time (host -> device) */
#define DMDSM_PING_FIXED_SIZE 4u
struct dmdsm_ping {
    uint32_t nonce; /* echoed back in pong */
};
size_t dmdsm_pack_ping(const struct dmdsm_ping *m, uint8_t *out);
bool dmdsm_unpack_ping(const uint8_t *p, size_t len, struct dmdsm_ping *m);

/* identify: ask for firmware and protocol versions and the spec hash (handshake) (host -> device) */
#define DMDSM_IDENTIFY_FIXED_SIZE 0u
struct dmdsm_identify {
    uint8_t unused_; /* no fields */
};
size_t dmdsm_pack_identify(const struct dmdsm_identify *m, uint8_t *out);
bool dmdsm_unpack_identify(const uint8_t *p, size_t len, struct dmdsm_identify *m);

/* get_config: read the acquisition configuration (host -> device) */
#define DMDSM_GET_CONFIG_FIXED_SIZE 0u
struct dmdsm_get_config {
    uint8_t unused_; /* no fields */
};
size_t dmdsm_pack_get_config(const struct dmdsm_get_config *m, uint8_t *out);
bool dmdsm_unpack_get_config(const uint8_t *p, size_t len, struct dmdsm_get_config *m);

/* set_config: write the acquisition configuration; only while idle; all-or-nothing (host -> device) */
#define DMDSM_SET_CONFIG_FIXED_SIZE 15u
struct dmdsm_set_config {
    uint16_t n_samples; /* samples per shot [samples] */
    uint16_t sample_rate_div; /* sample rate = adc_rate_hz / sample_rate_div */
    uint16_t n_average; /* shots averaged on board per waveform */
    uint16_t pretrigger; /* samples kept from before the edge; < n_samples [samples] */
    uint8_t trigger_edge; /* photodiode edge */
    uint8_t modality; /* sensing path, recorded in each waveform */
    uint8_t sample_format; /* u32_sum needs n_samples <= 4096 */
    uint32_t trigger_timeout_ms; /* no-trigger timeout while armed; 0 waits forever [ms] */
};
size_t dmdsm_pack_set_config(const struct dmdsm_set_config *m, uint8_t *out);
bool dmdsm_unpack_set_config(const uint8_t *p, size_t len, struct dmdsm_set_config *m);
/* 0 if every field is within its range, else 1 + index of the first that is not */
unsigned dmdsm_check_set_config(const struct dmdsm_set_config *m);

/* arm: start acquiring: n_shots waveforms (each averaging n_average edges), or continuous (host -> device) */
#define DMDSM_ARM_FIXED_SIZE 4u
struct dmdsm_arm {
    uint32_t n_shots; /* waveforms to send; 0 = continuous until disarm */
};
size_t dmdsm_pack_arm(const struct dmdsm_arm *m, uint8_t *out);
bool dmdsm_unpack_arm(const uint8_t *p, size_t len, struct dmdsm_arm *m);

/* disarm: stop acquiring now; a partial average is discarded, never sent (host -> device) */
#define DMDSM_DISARM_FIXED_SIZE 0u
struct dmdsm_disarm {
    uint8_t unused_; /* no fields */
};
size_t dmdsm_pack_disarm(const struct dmdsm_disarm *m, uint8_t *out);
bool dmdsm_unpack_disarm(const uint8_t *p, size_t len, struct dmdsm_disarm *m);

/* get_status: read state, counters and uptime (host -> device) */
#define DMDSM_GET_STATUS_FIXED_SIZE 0u
struct dmdsm_get_status {
    uint8_t unused_; /* no fields */
};
size_t dmdsm_pack_get_status(const struct dmdsm_get_status *m, uint8_t *out);
bool dmdsm_unpack_get_status(const uint8_t *p, size_t len, struct dmdsm_get_status *m);

/* clock_sync: one clock-sync exchange: device tick at reception vs host send/receive times (host -> device) */
#define DMDSM_CLOCK_SYNC_FIXED_SIZE 8u
struct dmdsm_clock_sync {
    uint64_t host_time_ns; /* host clock when sent; echoed [ns] */
};
size_t dmdsm_pack_clock_sync(const struct dmdsm_clock_sync *m, uint8_t *out);
bool dmdsm_unpack_clock_sync(const uint8_t *p, size_t len, struct dmdsm_clock_sync *m);

/* pong: reply to ping (device -> host) */
#define DMDSM_PONG_FIXED_SIZE 4u
struct dmdsm_pong {
    uint32_t nonce; /* the ping's nonce */
};
size_t dmdsm_pack_pong(const struct dmdsm_pong *m, uint8_t *out);
bool dmdsm_unpack_pong(const uint8_t *p, size_t len, struct dmdsm_pong *m);

/* identify_reply: firmware identity; the host refuses a protocol_version or spec_hash mismatch (device -> host) */
#define DMDSM_IDENTIFY_REPLY_FIXED_SIZE 24u
struct dmdsm_identify_reply {
    uint8_t protocol_version; /* protocol.version the firmware was built with */
    uint8_t fw_major; /* firmware version major */
    uint8_t fw_minor; /* firmware version minor */
    uint8_t fw_patch; /* firmware version patch */
    uint64_t spec_hash; /* first 8 bytes of SHA-256 of this file, big-endian number */
    uint32_t tick_hz; /* rate of device timestamps [Hz] */
    uint32_t adc_rate_hz; /* sample rate at sample_rate_div = 1 [Hz] */
    uint16_t max_samples; /* largest n_samples this build accepts [samples] */
    uint16_t max_payload; /* largest payload this build sends [bytes] */
    const uint8_t *board; /* board and silicon revision, e.g. NUCLEO-H743ZI rev V */
    size_t board_len; /* bytes */
};
size_t dmdsm_pack_identify_reply(const struct dmdsm_identify_reply *m, uint8_t *out);
bool dmdsm_unpack_identify_reply(const uint8_t *p, size_t len, struct dmdsm_identify_reply *m);

/* config: reply to get_config; same fields as set_config (device -> host) */
#define DMDSM_CONFIG_FIXED_SIZE 15u
struct dmdsm_config {
    uint16_t n_samples; /* samples per shot [samples] */
    uint16_t sample_rate_div; /* sample rate = adc_rate_hz / sample_rate_div */
    uint16_t n_average; /* shots averaged on board per waveform */
    uint16_t pretrigger; /* samples kept from before the edge [samples] */
    uint8_t trigger_edge; /* photodiode edge */
    uint8_t modality; /* sensing path */
    uint8_t sample_format; /* waveform element type */
    uint32_t trigger_timeout_ms; /* no-trigger timeout; 0 waits forever [ms] */
};
size_t dmdsm_pack_config(const struct dmdsm_config *m, uint8_t *out);
bool dmdsm_unpack_config(const uint8_t *p, size_t len, struct dmdsm_config *m);

/* status: reply to get_status: state and cumulative counters since boot (device -> host) */
#define DMDSM_STATUS_FIXED_SIZE 50u
struct dmdsm_status {
    uint8_t state; /* acquisition state */
    uint8_t last_error; /* last error raised by the firmware */
    uint32_t uptime_ms; /* time since boot [ms] */
    uint32_t shots_remaining; /* waveforms still to send in this arm; 0 if continuous or idle */
    uint32_t triggers; /* photodiode edges seen while armed */
    uint32_t shots_sent; /* waveform frames queued to the link */
    uint32_t triggers_skipped; /* laser shots not captured because every waveform slot was waiting for the link (the link is slower than the laser at these settings): by design, not a loss; an arm still sends its n_shots waveforms */
    uint32_t adc_overruns; /* ADC/DMA overruns */
    uint32_t no_trigger_timeouts; /* arms that ended in a no-trigger timeout */
    uint32_t rx_frames; /* command frames accepted */
    uint32_t rx_crc_errors; /* received frames with a bad CRC */
    uint32_t rx_malformed; /* received frames with bad COBS, length or version */
    uint32_t rx_oversize; /* received frames longer than the maximum */
    uint32_t integrity_faults; /* bursts dropped because the DMA's write position disagreed with the timer: a missed or late ADC trigger */
};
size_t dmdsm_pack_status(const struct dmdsm_status *m, uint8_t *out);
bool dmdsm_unpack_status(const uint8_t *p, size_t len, struct dmdsm_status *m);

/* clock_sync_reply: reply to clock_sync (device -> host) */
#define DMDSM_CLOCK_SYNC_REPLY_FIXED_SIZE 16u
struct dmdsm_clock_sync_reply {
    uint64_t host_time_ns; /* echo of the request [ns] */
    uint64_t device_ticks; /* device clock when the request was decoded [ticks] */
};
size_t dmdsm_pack_clock_sync_reply(const struct dmdsm_clock_sync_reply *m, uint8_t *out);
bool dmdsm_unpack_clock_sync_reply(const uint8_t *p, size_t len, struct dmdsm_clock_sync_reply *m);

/* ack: the command with this seq was executed (device -> host) */
#define DMDSM_ACK_FIXED_SIZE 1u
struct dmdsm_ack {
    uint8_t command; /* type id of the acknowledged command */
};
size_t dmdsm_pack_ack(const struct dmdsm_ack *m, uint8_t *out);
bool dmdsm_unpack_ack(const uint8_t *p, size_t len, struct dmdsm_ack *m);

/* nak: the command with this seq was refused and changed nothing (device -> host) */
#define DMDSM_NAK_FIXED_SIZE 4u
struct dmdsm_nak {
    uint8_t command; /* type id of the refused command */
    uint8_t error; /* why */
    uint16_t detail; /* index of the offending field, or 0 */
};
size_t dmdsm_pack_nak(const struct dmdsm_nak *m, uint8_t *out);
bool dmdsm_unpack_nak(const uint8_t *p, size_t len, struct dmdsm_nak *m);

/* waveform: one averaged shot; seq counts waveform frames so the host sees gaps (device -> host) */
#define DMDSM_WAVEFORM_FIXED_SIZE 42u
struct dmdsm_waveform {
    uint32_t shot_id; /* counts waveforms since arm, from 0, one per waveform sent (skipped triggers take no id): a gap is a frame lost on the link */
    uint64_t timestamp; /* device clock at the first averaged shot's edge [ticks] */
    uint16_t trigger_phase; /* edge to first sample, for sub-sample start jitter removal [ticks] */
    uint16_t n_average; /* shots in this average */
    uint16_t pretrigger; /* samples before the edge [samples] */
    uint16_t sample_rate_div; /* sample rate = adc_rate_hz / sample_rate_div */
    uint8_t sample_format; /* element type of samples */
    uint8_t modality; /* sensing path */
    uint32_t triggers_skipped; /* device's cumulative skipped-trigger counter (status.triggers_skipped) */
    uint32_t adc_overruns; /* device's cumulative ADC overrun counter */
    uint32_t integrity_faults; /* device's cumulative sample-integrity fault counter (bursts dropped: DMA position disagreed with the timer) */
    uint32_t sync_steps; /* sum over the averaged shots of the motion-sync edges counted in the open burst before each shot's edge: / n_average, the mean X steps made since the burst began (0 with no burst open) [steps] */
    uint32_t sync_steps_a; /* the same for the A (turntable) sync input: / n_average, the mean A steps made since its burst began (0 with no burst open) [steps] */
    const uint8_t *samples; /* the waveform; element type from sample_format */
    size_t samples_len; /* bytes */
};
size_t dmdsm_pack_waveform(const struct dmdsm_waveform *m, uint8_t *out);
bool dmdsm_unpack_waveform(const uint8_t *p, size_t len, struct dmdsm_waveform *m);

/* log: a firmware log line or asynchronous error (e.g. no_trigger) (device -> host) */
#define DMDSM_LOG_FIXED_SIZE 2u
struct dmdsm_log {
    uint8_t level; /* severity */
    uint8_t code; /* error code, or none */
    const uint8_t *text; /* UTF-8 text, at most 200 bytes */
    size_t text_len; /* bytes */
};
size_t dmdsm_pack_log(const struct dmdsm_log *m, uint8_t *out);
bool dmdsm_unpack_log(const uint8_t *p, size_t len, struct dmdsm_log *m);

/* motion_sync: one burst of step pulses on a motion-sync input (the stage's X or A STEP line), sent once that input has been quiet for sync_quiet_ms; timestamps in the waveforms' clock (device -> host) */
#define DMDSM_MOTION_SYNC_FIXED_SIZE 25u
struct dmdsm_motion_sync {
    uint32_t burst_id; /* counts bursts of both inputs since boot, from 0; gaps = lost reports */
    uint64_t first_edge; /* device clock at the burst's first rising edge [ticks] */
    uint64_t last_edge; /* device clock at the burst's last rising edge [ticks] */
    uint32_t edges; /* rising edges in the burst (steps of the input's axis) */
    uint8_t input; /* the input, so the axis, the burst came on */
};
size_t dmdsm_pack_motion_sync(const struct dmdsm_motion_sync *m, uint8_t *out);
bool dmdsm_unpack_motion_sync(const uint8_t *p, size_t len, struct dmdsm_motion_sync *m);

/* static facts about one message type */
struct dmdsm_msg_info {
    uint8_t id;
    uint8_t from_host;   /* 1: host -> device command, 0: device -> host */
    uint8_t tail_kind;   /* 0 none, 1 bytes, 2 str, 3 samples */
    uint16_t fixed_size; /* bytes of fixed fields */
    uint8_t reply;       /* type id of the success reply (commands), else 0 */
    const char *name;
};

/* info for a type id, or NULL if the type is not in the spec */
const struct dmdsm_msg_info *dmdsm_msg_info(uint8_t type);
/* true if a payload of this length (and sample_format) fits the message type */
bool dmdsm_payload_ok(uint8_t type, const uint8_t *payload, size_t len);
/* writes "field=value ..." (tails as name:len=N:crc=8 hex digits); returns chars
 * that a large enough buffer needs, like snprintf */
int dmdsm_msg_format(uint8_t type, const uint8_t *payload, size_t len,
                     char *out, size_t cap);
/* zlib/IEEE CRC-32 table, reflected polynomial 0xEDB88320 */
extern const uint32_t dmdsm_crc32_table[256];

#endif /* DMDSM_SPEC_H */
