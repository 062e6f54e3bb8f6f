#include "mk_msgs.h"

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    put_u16(p, (uint16_t)v);
    put_u16(p + 2, (uint16_t)(v >> 16));
}

static uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | ((uint16_t)p[1] << 8)); }

uint8_t ql_pack_imu(uint8_t *out, const ql_imu_msg_t *m)
{
    /* the 12-bit counter rides in the spare high bits of the first two accel words */
    uint16_t counter = (uint16_t)(m->counter % QL_IMU_COUNTER_MODULO);
    put_u16(out + 0, (uint16_t)((m->accel[0] & QL_IMU_COUNT_MASK) | ((counter & 0x3Fu) << 10)));
    put_u16(out + 2, (uint16_t)((m->accel[1] & QL_IMU_COUNT_MASK) | ((counter >> 6) << 10)));
    put_u16(out + 4, (uint16_t)(m->accel[2] & QL_IMU_COUNT_MASK));
    for (uint8_t i = 0; i < 3u; i++) {
        put_u16(out + 6 + 2 * i, (uint16_t)(m->gyro[i] & QL_IMU_COUNT_MASK));
    }
    return QL_IMU_LEN;
}

uint8_t ql_unpack_imu(const uint8_t *in, uint8_t len, ql_imu_msg_t *m)
{
    if (len < QL_IMU_LEN) {
        return 0;
    }
    uint16_t w0 = get_u16(in), w1 = get_u16(in + 2);
    m->accel[0] = (uint16_t)(w0 & QL_IMU_COUNT_MASK);
    m->accel[1] = (uint16_t)(w1 & QL_IMU_COUNT_MASK);
    m->accel[2] = (uint16_t)(get_u16(in + 4) & QL_IMU_COUNT_MASK);
    for (uint8_t i = 0; i < 3u; i++) {
        m->gyro[i] = (uint16_t)(get_u16(in + 6 + 2 * i) & QL_IMU_COUNT_MASK);
    }
    m->counter = (uint16_t)((w0 >> 10) | ((w1 >> 10) << 6));
    return 1;
}

uint8_t ql_pack_setpoint(uint8_t *out, const ql_setpoint_msg_t *m)
{
    put_u16(out + 0, (uint16_t)m->roll_cdeg);
    put_u16(out + 2, (uint16_t)m->pitch_cdeg);
    put_u16(out + 4, (uint16_t)m->yaw_rate_ddeg_s);
    put_u16(out + 6, m->thrust);
    out[8] = m->flags;
    out[9] = m->seq;
    return QL_SETPOINT_LEN;
}

uint8_t ql_unpack_setpoint(const uint8_t *in, uint8_t len, ql_setpoint_msg_t *m)
{
    if (len < QL_SETPOINT_LEN) {
        return 0;
    }
    m->roll_cdeg = (int16_t)get_u16(in + 0);
    m->pitch_cdeg = (int16_t)get_u16(in + 2);
    m->yaw_rate_ddeg_s = (int16_t)get_u16(in + 4);
    m->thrust = get_u16(in + 6);
    m->flags = in[8];
    m->seq = in[9];
    return 1;
}

uint8_t ql_pack_status(uint8_t *out, const ql_status_msg_t *m)
{
    out[0] = m->flags;
    out[1] = m->flight_state;
    put_u16(out + 2, m->battery_mv);
    put_u16(out + 4, m->error_flags);
    put_u32(out + 6, m->board_time_ms);
    put_u32(out + 10, m->imu_sample_count);
    out[14] = m->last_setpoint_seq;
    return QL_STATUS_LEN;
}

uint8_t ql_pack_baro(uint8_t *out, const ql_baro_msg_t *m)
{
    put_u32(out + 0, (uint32_t)m->altitude_cm);
    put_u16(out + 4, (uint16_t)m->climb_cm_s);
    put_u32(out + 6, m->pressure_pa);
    out[10] = m->flags;
    out[11] = m->seq;
    return QL_BARO_LEN;
}

uint8_t ql_pack_version(uint8_t *out, const uint8_t version[QL_VERSION_LEN])
{
    for (uint8_t i = 0; i < QL_VERSION_LEN; i++) {
        out[i] = version[i];
    }
    return QL_VERSION_LEN;
}

uint8_t ql_pack_debug(uint8_t *out, const uint8_t status[2], const int16_t analog[QL_DEBUG_ANALOGS])
{
    out[0] = status[0];
    out[1] = status[1];
    for (uint8_t i = 0; i < QL_DEBUG_ANALOGS; i++) {
        put_u16(out + 2 + 2 * i, (uint16_t)analog[i]);
    }
    return QL_DEBUG_LEN;
}

uint8_t ql_pack_label(uint8_t *out, uint8_t index, const char *label)
{
    out[0] = index;
    uint8_t i = 0;
    for (; i < QL_LABEL_TEXT && label[i] != '\0'; i++) {
        uint8_t c = (uint8_t)label[i];
        out[1 + i] = (uint8_t)(c < 0x80u ? c : '?');
    }
    for (; i < QL_LABEL_TEXT; i++) {
        out[1 + i] = ' ';
    }
    return QL_LABEL_LEN;
}

uint8_t ql_pack_data3d(uint8_t *out, const ql_data3d_msg_t *m)
{
    for (uint8_t i = 0; i < 3u; i++) {
        put_u16(out + 2 * i, (uint16_t)m->angle_ddeg[i]);
        out[6 + i] = m->centroid[i];
    }
    for (uint8_t i = 0; i < 5u; i++) {
        out[9 + i] = m->reserve[i];
    }
    return QL_DATA3D_LEN;
}

uint8_t ql_pack_u8(uint8_t *out, uint8_t value)
{
    out[0] = value;
    return 1;
}
