/* Payloads of the MK frames the board speaks (quadlink/mk/messages.py and standard.py are the reference;
 * little-endian, the AVR's order). Pure C. pack_* return the payload length; unpack_* return 1 if the
 * payload is long enough (trailing bytes, e.g. base64 zero padding, are ignored). */
#ifndef QL_MK_MSGS_H
#define QL_MK_MSGS_H

#include <stdint.h>

#define QL_CMD_IMU 'I'
#define QL_CMD_SETPOINT 's'
#define QL_CMD_STATUS 'S'
#define QL_CMD_BARO 'Z'
#define QL_CMD_VERSION_REQ 'v'
#define QL_CMD_VERSION 'V'
#define QL_CMD_DEBUG_REQ 'd'
#define QL_CMD_DEBUG 'D'
#define QL_CMD_LABEL_REQ 'a'
#define QL_CMD_LABEL 'A'
#define QL_CMD_DATA3D_REQ 'c'
#define QL_CMD_DATA3D 'C'
#define QL_CMD_EXTERN 'b'
#define QL_CMD_EXTERN_ACK 'B'
#define QL_CMD_MOTOR_TEST 't'

#define QL_IMU_LEN 12u
#define QL_SETPOINT_LEN 10u
#define QL_STATUS_LEN 15u
#define QL_BARO_LEN 12u
#define QL_VERSION_LEN 10u
#define QL_DEBUG_ANALOGS 32u
#define QL_DEBUG_LEN (2u + 2u * QL_DEBUG_ANALOGS)
#define QL_LABEL_TEXT 16u
#define QL_LABEL_LEN (1u + QL_LABEL_TEXT)
#define QL_DATA3D_LEN 14u
#define QL_EXTERN_LEN 11u
#define QL_EXTERN_FRAME_INDEX 9u /* <2BBbbbBbBBB>: digital[2] buttons nick roll yaw gas height free FRAME config */
#define QL_MOTOR_TEST_LEN 16u

#define QL_IMU_COUNT_MASK 0x3FFu
#define QL_IMU_COUNTER_MODULO 4096u
#define QL_SETPOINT_FLAG_ARMED 0x01u
#define QL_STATUS_FLAG_ARMED 0x01u
#define QL_STATUS_FLAG_FAILSAFE 0x02u
#define QL_BARO_FLAG_VALID 0x01u
#define QL_BARO_FLAG_SATURATED 0x02u

/* BoardError bits (quadlink/mk/flags.py) */
#define QL_ERR_SETPOINT_TIMEOUT 0x0001u
#define QL_ERR_BATTERY_LOW 0x0002u
#define QL_ERR_IMU_SATURATED 0x0004u
#define QL_ERR_RX_FRAMES_DROPPED 0x0008u

/* BoardFlightState */
#define QL_STATE_LANDED 0u
#define QL_STATE_FLYING 1u
#define QL_STATE_FAILSAFE_DESCEND 2u

typedef struct {
    uint16_t accel[3]; /* raw 10-bit counts, body FRD */
    uint16_t gyro[3];
    uint16_t counter; /* sample k carries k mod 4096 */
} ql_imu_msg_t;

typedef struct {
    int16_t roll_cdeg;
    int16_t pitch_cdeg;
    int16_t yaw_rate_ddeg_s;
    uint16_t thrust; /* fraction x 65535 */
    uint8_t flags;
    uint8_t seq;
} ql_setpoint_msg_t;

typedef struct {
    uint8_t flags;
    uint8_t flight_state;
    uint16_t battery_mv;
    uint16_t error_flags;
    uint32_t board_time_ms;
    uint32_t imu_sample_count;
    uint8_t last_setpoint_seq;
} ql_status_msg_t;

typedef struct {
    int32_t altitude_cm;
    int16_t climb_cm_s;
    uint32_t pressure_pa;
    uint8_t flags;
    uint8_t seq;
} ql_baro_msg_t;

typedef struct {
    int16_t angle_ddeg[3]; /* nick (pitch), roll, yaw [-1800, 1799] */
    uint8_t centroid[3];
    uint8_t reserve[5];
} ql_data3d_msg_t;

uint8_t ql_pack_imu(uint8_t *out, const ql_imu_msg_t *m);
uint8_t ql_unpack_imu(const uint8_t *in, uint8_t len, ql_imu_msg_t *m);
uint8_t ql_pack_setpoint(uint8_t *out, const ql_setpoint_msg_t *m);
uint8_t ql_unpack_setpoint(const uint8_t *in, uint8_t len, ql_setpoint_msg_t *m);
uint8_t ql_pack_status(uint8_t *out, const ql_status_msg_t *m);
uint8_t ql_pack_baro(uint8_t *out, const ql_baro_msg_t *m);
uint8_t ql_pack_version(uint8_t *out, const uint8_t version[QL_VERSION_LEN]);
uint8_t ql_pack_debug(uint8_t *out, const uint8_t status[2], const int16_t analog[QL_DEBUG_ANALOGS]);
/* label: NUL-terminated ASCII, truncated to 16 and space padded as DebugLabel.pack */
uint8_t ql_pack_label(uint8_t *out, uint8_t index, const char *label);
uint8_t ql_pack_data3d(uint8_t *out, const ql_data3d_msg_t *m);
uint8_t ql_pack_u8(uint8_t *out, uint8_t value); /* 'B' ack and the one-byte requests */

#endif
