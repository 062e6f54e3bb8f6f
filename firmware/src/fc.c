#include "fc.h"

#include <stddef.h>

#include "fxmath.h"
#include "sensors.h"

#define BATTERY_MV_PER_COUNT_NUM INT32_C(625) /* 4 x 5 V / 1024 = 19.53125 mV = 625 / 32 */
#define BATTERY_MV_PER_COUNT_SHIFT 5

/* Version: the board replaces sim_sitl's emulated firmware and answers as it does (FC 2.01a, protocol 11.0) */
static const uint8_t k_version[QL_VERSION_LEN] = {2u, 1u, 11u, 0u, 0u, 0u, 0u, 0u, 0u, 0u};

/* analog[0..15] as sim_sitl/board.py's DEBUG_LABELS; 16..20 the firmware's own */
static const char *const k_labels[QL_DEBUG_LABELS] = {
    "Roll 0.1deg", "Pitch 0.1deg", "Yaw 0.1deg", "Thrust %",  "Motor1 cN",    "Motor2 cN",   "Motor3 cN",
    "Motor4 cN",   "Battery 10mV", "Armed",      "Flight state", "Setpoints/s", "Gyro x cnt", "Gyro y cnt",
    "Gyro z cnt",  "Acc z cnt",    "Busy cyc u16", "Busy max u16", "P2 drops",     "P1 rx drops",  "Late ticks",
};

const char *ql_fc_label(uint8_t index) { return index < QL_DEBUG_LABELS ? k_labels[index] : NULL; }

static void send(ql_fc_t *fc, uint8_t port, char cmd, const uint8_t *payload, uint8_t len)
{
    uint8_t frame[QL_MK_MAX_FRAME_LEN];
    uint8_t n = ql_mk_encode(frame, QL_MK_ADDR_FC, cmd, payload, len);
    if (n == 0u || fc->tx == NULL || !fc->tx(fc->tx_ctx, port, frame, n)) {
        fc->tx_dropped[port]++; /* a full ring drops the whole frame */
    }
}

void ql_fc_init(ql_fc_t *fc, const uint8_t *image, uint16_t image_len, ql_tx_fn tx, void *tx_ctx)
{
    uint8_t *raw = (uint8_t *)fc;
    for (size_t i = 0; i < sizeof(*fc); i++) {
        raw[i] = 0;
    }
    fc->params_ok = image != NULL ? ql_params_load(&fc->params, image, image_len) : 0u;
    if (image == NULL) {
        ql_params_defaults(&fc->params);
    }
    ql_attitude_init(&fc->att);
    ql_baro_init(&fc->baro);
    ql_ctrl_init(&fc->ctrl, &fc->params);
    ql_safety_init(&fc->safety, &fc->params);
    ql_mk_decoder_init(&fc->dec);
    fc->tx = tx;
    fc->tx_ctx = tx_ctx;
    fc->reported_armed = 0xFFu;
}

static void stream_request(ql_stream_t *s, uint8_t interval_10ms, uint32_t tick)
{
    s->interval_ticks = (uint16_t)(interval_10ms * QL_TICKS_PER_10MS);
    s->until_tick = tick + QL_STREAM_TIMEOUT_TICKS;
    s->next_tick = tick; /* the first frame at once */
}

static uint8_t stream_due(ql_stream_t *s, uint32_t tick)
{
    if (s->interval_ticks == 0u || (int32_t)(tick - s->until_tick) > 0 || (int32_t)(tick - s->next_tick) < 0) {
        return 0;
    }
    uint32_t next = s->next_tick + s->interval_ticks;
    uint32_t floor_tick = tick - s->interval_ticks; /* do not burst after a stall */
    s->next_tick = (int32_t)(next - floor_tick) > 0 ? next : floor_tick;
    return 1;
}

/* noinline: ql_fc_rx_byte runs per received byte and should not pay this function's register saves */
__attribute__((noinline)) static void on_frame(ql_fc_t *fc, const ql_mk_frame_t *f)
{
    uint8_t out[QL_LABEL_LEN > QL_VERSION_LEN ? QL_LABEL_LEN : QL_VERSION_LEN];
    if (f->address != QL_MK_ADDR_ANY && f->address != QL_MK_ADDR_FC) {
        return; /* another node's request */
    }
    switch (f->command) {
    case QL_CMD_SETPOINT: {
        ql_setpoint_msg_t m;
        if (ql_unpack_setpoint(f->payload, f->len, &m)) {
            if (ql_safety_on_setpoint(&fc->safety, &fc->params, &m, fc->tick)) {
                ql_ctrl_reset(&fc->ctrl);
                fc->motor_test_until = fc->tick; /* arming ends a motor test */
            }
        }
        break;
    }
    case QL_CMD_VERSION_REQ: {
        uint8_t v[QL_VERSION_LEN];
        ql_pack_version(v, k_version);
        v[5] = fc->params_ok ? 0u : QL_HWERR_PARAMS_DEFAULTED;
        send(fc, QL_PORT1, QL_CMD_VERSION, v, QL_VERSION_LEN);
        break;
    }
    case QL_CMD_DEBUG_REQ:
        if (f->len >= 1u) {
            stream_request(&fc->debug, f->payload[0], fc->tick);
        }
        break;
    case QL_CMD_DATA3D_REQ:
        if (f->len >= 1u) {
            stream_request(&fc->data3d, f->payload[0], fc->tick);
        }
        break;
    case QL_CMD_LABEL_REQ:
        if (f->len >= 1u) {
            const char *label = ql_fc_label(f->payload[0]);
            char fallback[16] = "Analog";
            if (label == NULL) { /* as sim_sitl/board.py: "Analog<index>" */
                uint8_t idx = f->payload[0], n = 6;
                if (idx >= 100u) {
                    fallback[n++] = (char)('0' + idx / 100u);
                }
                if (idx >= 10u) {
                    fallback[n++] = (char)('0' + (idx / 10u) % 10u);
                }
                fallback[n++] = (char)('0' + idx % 10u);
                fallback[n] = '\0';
                label = fallback;
            }
            uint8_t len = ql_pack_label(out, f->payload[0], label);
            send(fc, QL_PORT1, QL_CMD_LABEL, out, len);
        }
        break;
    case QL_CMD_EXTERN:
        if (f->len >= QL_EXTERN_LEN) { /* acknowledged, not flown */
            send(fc, QL_PORT1, QL_CMD_EXTERN_ACK, out, ql_pack_u8(out, f->payload[QL_EXTERN_FRAME_INDEX]));
        }
        break;
    case QL_CMD_MOTOR_TEST:
        if (f->len >= QL_MOTOR_TEST_LEN && !fc->safety.armed) {
            for (uint8_t i = 0; i < QL_MOTORS; i++) {
                fc->motor_test[i] = f->payload[i];
            }
            fc->motor_test_until = fc->tick + QL_MOTOR_TEST_TICKS;
        }
        break;
    default:
        break;
    }
}

void ql_fc_rx_byte(ql_fc_t *fc, uint8_t byte)
{
    if (ql_mk_decoder_feed(&fc->dec, byte, &fc->frame)) {
        on_frame(fc, &fc->frame);
    }
}

void ql_fc_rx_bytes(ql_fc_t *fc, const uint8_t *data, uint8_t n)
{
    while (n != 0u) {
        uint8_t got;
        uint8_t used = ql_mk_decoder_feed_buf(&fc->dec, data, n, &got, &fc->frame);
        if (got) {
            on_frame(fc, &fc->frame);
        }
        data += used;
        n = (uint8_t)(n - used);
    }
}

static int16_t sat16u(uint32_t v) { return (int16_t)(v > 32767u ? 32767u : v); }

static uint16_t error_flags(const ql_fc_t *fc)
{
    return (uint16_t)(fc->safety.error_flags | fc->sticky_errors | (fc->battery_low ? QL_ERR_BATTERY_LOW : 0u));
}

static void send_status(ql_fc_t *fc)
{
    uint8_t out[QL_STATUS_LEN];
    ql_status_msg_t m;
    m.flags = (uint8_t)((fc->safety.armed ? QL_STATUS_FLAG_ARMED : 0u) |
                        (fc->safety.failsafe ? QL_STATUS_FLAG_FAILSAFE : 0u));
    m.flight_state = fc->safety.flight_state;
    m.battery_mv = (uint16_t)(fc->battery_q4 >> 4);
    m.error_flags = error_flags(fc);
    m.imu_sample_count = fc->tick + 1u; /* sample fc->tick went out at the start of this tick */
    m.board_time_ms = m.imu_sample_count * 2u;
    m.last_setpoint_seq = fc->safety.seq;
    send(fc, QL_PORT1, QL_CMD_STATUS, out, ql_pack_status(out, &m));
    fc->sticky_errors = 0;
    fc->reported_armed = fc->safety.armed;
}

static void send_baro(ql_fc_t *fc)
{
    uint8_t out[QL_BARO_LEN];
    ql_baro_msg_t m;
    m.altitude_cm = ql_baro_altitude_cm(&fc->baro);
    m.climb_cm_s = ql_baro_climb_cm_s(&fc->baro);
    m.pressure_pa = ql_baro_pressure_pa(&fc->baro);
    m.flags = (uint8_t)((ql_baro_valid(&fc->baro) ? QL_BARO_FLAG_VALID : 0u) |
                        (fc->baro.saturated ? QL_BARO_FLAG_SATURATED : 0u));
    m.seq = fc->baro_seq++;
    send(fc, QL_PORT1, QL_CMD_BARO, out, ql_pack_baro(out, &m));
}

/* Q24 rad -> 0.1 deg, in integers: (a >> 8) * 1800 / (pi 2^16) ~ (a >> 8) * 573 / 2^16 */
static int16_t ddeg(int32_t a_q24) { return (int16_t)QL_RSHIFT(QL_RSHIFT(a_q24, 8) * INT32_C(573), 16); }

/* thrust F (N * 2^16) -> cN */
static int16_t centinewton(int32_t f) { return (int16_t)QL_RSHIFT(f * INT32_C(100), 16); }


static void send_data3d(ql_fc_t *fc)
{
    uint8_t out[QL_DATA3D_LEN];
    ql_data3d_msg_t m = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0, 0, 0}};
    m.angle_ddeg[0] = ddeg(fc->att.pitch_q24);
    m.angle_ddeg[1] = ddeg(fc->att.roll_q24);
    int16_t yaw = ddeg(fc->att.yaw_q24);
    m.angle_ddeg[2] = yaw >= 1800 ? (int16_t)(yaw - 3600) : (yaw < -1800 ? (int16_t)(yaw + 3600) : yaw);
    send(fc, QL_PORT1, QL_CMD_DATA3D, out, ql_pack_data3d(out, &m));
}

static void send_debug(ql_fc_t *fc)
{
    uint8_t out[QL_DEBUG_LEN];
    int16_t a[QL_DEBUG_ANALOGS] = {0};
    uint8_t status[2] = {fc->safety.armed, fc->safety.flight_state};
    a[0] = ddeg(fc->att.roll_q24);
    a[1] = ddeg(fc->att.pitch_q24);
    a[2] = ddeg(fc->att.yaw_q24);
    a[3] = (int16_t)((fc->thrust_flown_f / 4 * 100 + fc->ctrl.max_f / 2) / fc->ctrl.max_f); /* % of max */
    for (uint8_t i = 0; i < QL_MOTORS; i++) {
        a[4 + i] = centinewton(fc->motor_f[i]);
    }
    a[8] = (int16_t)((fc->battery_q4 >> 4) / 10u);
    a[9] = fc->safety.armed;
    a[10] = fc->safety.flight_state;
    a[11] = (int16_t)fc->setpoints_per_s;
    a[12] = (int16_t)fc->last_counts[3];
    a[13] = (int16_t)fc->last_counts[4];
    a[14] = (int16_t)fc->last_counts[5];
    a[15] = (int16_t)fc->last_counts[2];
    /* cycles up to 40 000 (and 80 000 late) do not fit int16: the raw 16 bits, to be read as uint16 */
    a[16] = (int16_t)fc->busy_cycles;
    a[17] = (int16_t)fc->busy_max;
    a[18] = sat16u(fc->tx_dropped[QL_PORT2]);
    a[19] = sat16u(ql_mk_frames_dropped(&fc->dec.stats));
    a[20] = sat16u(fc->late_ticks);
    send(fc, QL_PORT1, QL_CMD_DEBUG, out, ql_pack_debug(out, status, a));
}

static void battery_update(ql_fc_t *fc, uint16_t count)
{
    uint32_t mv16 = (((uint32_t)count * BATTERY_MV_PER_COUNT_NUM) >> BATTERY_MV_PER_COUNT_SHIFT) << 4;
    if (fc->battery_ticks == 0u) {
        fc->battery_q4 = mv16;
    } else {
        fc->battery_q4 = (uint32_t)((int32_t)fc->battery_q4 + QL_RSHIFT((int32_t)mv16 - (int32_t)fc->battery_q4,
                                                                         QL_BATTERY_SHIFT));
    }
    if (fc->battery_ticks < (1u << QL_BATTERY_SHIFT)) {
        fc->battery_ticks++;
        return; /* not settled: no verdict yet */
    }
    uint16_t mv = (uint16_t)(fc->battery_q4 >> 4);
    if (mv < fc->params.battery_low_mv) {
        fc->battery_low = 1;
    } else if (mv > fc->params.battery_low_mv + QL_BATTERY_HYST_MV) {
        fc->battery_low = 0;
    }
}

void ql_fc_tick(ql_fc_t *fc, const ql_adc_sweep_t *adc)
{
    /* 1. port 2: the raw sample k, nothing else ever goes there */
    ql_imu_msg_t imu;
    uint8_t buf[QL_IMU_LEN];
    for (uint8_t i = 0; i < 3u; i++) {
        imu.accel[i] = adc->accel[i];
        imu.gyro[i] = adc->gyro[i];
        fc->last_counts[i] = adc->accel[i];
        fc->last_counts[3 + i] = adc->gyro[i];
    }
    imu.counter = (uint16_t)(fc->tick & (QL_IMU_COUNTER_MODULO - 1u));
    send(fc, QL_PORT2, QL_CMD_IMU, buf, ql_pack_imu(buf, &imu));

    /* 2. estimates */
    uint8_t armed = fc->safety.armed;
    uint8_t flying = (uint8_t)(armed && fc->safety.flight_state != QL_STATE_LANDED); /* last tick's state */
    ql_attitude_update(&fc->att, adc->accel, adc->gyro, armed, flying);
    ql_baro_update(&fc->baro, adc->baro, armed);
    battery_update(fc, adc->battery);
    if (fc->att.saturated) {
        fc->sticky_errors |= QL_ERR_IMU_SATURATED;
    }
    uint32_t dropped = ql_mk_frames_dropped(&fc->dec.stats);
    if (dropped != fc->rx_dropped_seen) {
        fc->rx_dropped_seen = dropped;
        fc->sticky_errors |= QL_ERR_RX_FRAMES_DROPPED;
    }

    /* 3. safety and the attitude loop */
    int32_t f0 = (int32_t)adc->accel[0] - QL_IMU_ZERO_COUNT, f1 = (int32_t)adc->accel[1] - QL_IMU_ZERO_COUNT;
    int32_t f2 = (int32_t)adc->accel[2] - QL_IMU_ZERO_COUNT;
    int32_t norm2 = (int32_t)(int16_t)f0 * (int16_t)f0 + (int32_t)(int16_t)f1 * (int16_t)f1 +
                    (int32_t)(int16_t)f2 * (int16_t)f2; /* |f| <= 512: 16 x 16 -> 32 bit products */
    uint8_t accel_1g = (uint8_t)(norm2 >= QL_TOUCH_ACC_MIN2 && norm2 <= QL_TOUCH_ACC_MAX2);
    ql_att_cmd_t fly;
    uint8_t run = ql_safety_step(&fc->safety, &fc->params, fc->tick, fc->baro.v_t16,
                                 ql_baro_valid(&fc->baro), accel_1g, &fly);
    if (run) {
        ql_ctrl_step(&fc->ctrl, &fly, (uint8_t)(fc->safety.flight_state == QL_STATE_LANDED), fc->att.roll_q24,
                     fc->att.pitch_q24, fc->att.rate_q8, fc->motor_f);
        for (uint8_t i = 0; i < QL_MOTORS; i++) {
            fc->motor[i] = ql_motor_byte(&fc->ctrl, fc->motor_f[i]);
        }
        fc->thrust_flown_f = fly.thrust_f;
    } else {
        if (fc->running) {
            ql_ctrl_reset(&fc->ctrl);
        }
        uint8_t testing = (uint8_t)((int32_t)(fc->motor_test_until - fc->tick) > 0);
        for (uint8_t i = 0; i < QL_MOTORS; i++) {
            fc->motor[i] = testing ? fc->motor_test[i] : 0u;
            fc->motor_f[i] = (int32_t)(((int32_t)fc->motor[i] * fc->ctrl.max_f) / 255);
        }
        fc->thrust_flown_f = 0;
    }
    fc->running = run;

    /* 4. port 1 telemetry */
    if (++fc->second_countdown >= QL_LOOP_HZ) { /* countdowns: a 32-bit modulo costs ~600 cycles on the AVR */
        fc->second_countdown = 0;
        fc->setpoints_per_s = (uint16_t)(fc->safety.setpoints_received - fc->window_start_setpoints);
        fc->window_start_setpoints = fc->safety.setpoints_received;
    }
    /* at most one telemetry frame per tick (S, then Z, then C, then D): a frame that coincides with another
     * waits a tick, so the tick's worst case stays one frame's encoding */
    if (fc->baro_countdown < QL_BARO_PERIOD_TICKS) {
        fc->baro_countdown++;
    }
    if (fc->safety.armed != fc->reported_armed || (int32_t)(fc->tick - fc->next_status_tick) >= 0) {
        fc->next_status_tick = fc->tick + QL_STATUS_PERIOD_TICKS;
        send_status(fc);
    } else if (fc->baro_countdown >= QL_BARO_PERIOD_TICKS) {
        fc->baro_countdown = 0;
        send_baro(fc);
    } else if (stream_due(&fc->data3d, fc->tick)) {
        send_data3d(fc);
    } else if (stream_due(&fc->debug, fc->tick)) {
        send_debug(fc);
    }
    fc->tick++;
}
