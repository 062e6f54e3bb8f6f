/* The board's 500 Hz core, free of AVR registers: the hardware layer (src/hw/) hands it one ADC sweep per
 * tick and the bytes port 1 received; it queues frames through the tx callbacks and leaves the motor
 * bytes in fc->motor. The host tests run exactly this code. */
#ifndef QL_FC_H
#define QL_FC_H

#include <stdint.h>

#include "attitude.h"
#include "baro.h"
#include "control.h"
#include "mk_codec.h"
#include "mk_msgs.h"
#include "params.h"
#include "safety.h"

#define QL_PORT1 0u
#define QL_PORT2 1u
#define QL_STATUS_PERIOD_TICKS 50u    /* 'S' at 10 Hz */
#define QL_BARO_PERIOD_TICKS 10u      /* 'Z' at 50 Hz */
#define QL_STREAM_TIMEOUT_TICKS 2000u /* 'D' / 'C' stop 4 s after the last request (as MK's FlightCtrl) */
#define QL_TICKS_PER_10MS 5u
#define QL_MOTOR_TEST_TICKS 250u      /* a 't' frame drives the motors for 0.5 s (disarmed only) */
#define QL_BATTERY_SHIFT 6            /* battery low-pass, tau 64 ticks */
#define QL_BATTERY_HYST_MV 200u
#define QL_TOUCH_ACC_MIN2 (INT32_C(230) * INT32_C(230)) /* |f| within 0.9 .. 1.1 g: not falling, not pushing off */
#define QL_TOUCH_ACC_MAX2 (INT32_C(282) * INT32_C(282))
#define QL_DEBUG_LABELS 21u
#define QL_HWERR_PARAMS_DEFAULTED 0x01u /* Version.hardware_error[0]: the EEPROM held no valid parameters */

typedef uint8_t (*ql_tx_fn)(void *ctx, uint8_t port, const uint8_t *frame, uint8_t len);

typedef struct {
    uint16_t accel[3];                  /* ADC3..5 */
    uint16_t gyro[3];                   /* ADC0..2 */
    uint16_t baro[QL_BARO_OVERSAMPLE];  /* ADC6 */
    uint16_t battery;                   /* ADC7 */
} ql_adc_sweep_t;

typedef struct {
    uint16_t interval_ticks; /* 0: stopped */
    uint32_t until_tick;
    uint32_t next_tick;
} ql_stream_t;

typedef struct {
    ql_params_t params;
    uint8_t params_ok;
    ql_attitude_t att;
    ql_baro_t baro;
    ql_ctrl_t ctrl;
    ql_safety_t safety;
    ql_mk_decoder_t dec;
    ql_mk_frame_t frame;
    ql_tx_fn tx;
    void *tx_ctx;
    uint32_t tick; /* IMU samples emitted = board time / 2 ms */
    uint32_t tx_dropped[2];
    uint8_t motor[QL_MOTORS];
    int32_t motor_f[QL_MOTORS]; /* per-motor thrust, N * 2^16 */
    int32_t thrust_flown_f;     /* collective flown, N * 2^16 */
    uint8_t running;
    uint8_t reported_armed; /* 0xFF before the first 'S' */
    uint32_t next_status_tick;
    uint8_t baro_seq;
    uint8_t baro_countdown;
    uint16_t second_countdown;
    ql_stream_t debug, data3d;
    uint8_t motor_test[QL_MOTORS];
    uint32_t motor_test_until;
    uint32_t battery_q4; /* mV * 16 */
    uint16_t battery_ticks;
    uint8_t battery_low;
    uint16_t sticky_errors;       /* IMU_SATURATED and RX_FRAMES_DROPPED since the last 'S' */
    uint32_t rx_dropped_seen;
    uint16_t setpoints_per_s;
    uint32_t window_start_setpoints;
    uint16_t busy_cycles, busy_max; /* set by the hardware layer after each tick */
    uint16_t late_ticks;            /* ticks whose work ran past the next compare match */
    uint16_t last_counts[6];      /* ax ay az gx gy gz of the last tick */
} ql_fc_t;

/* image: the EEPROM's parameter image (NULL or a bad CRC loads the defaults). */
void ql_fc_init(ql_fc_t *fc, const uint8_t *image, uint16_t image_len, ql_tx_fn tx, void *tx_ctx);
void ql_fc_rx_byte(ql_fc_t *fc, uint8_t byte);
/* The same for n bytes at once (the main loop's path: one call per batch, ql_mk_decoder_feed_buf). */
void ql_fc_rx_bytes(ql_fc_t *fc, const uint8_t *data, uint8_t n);
void ql_fc_tick(ql_fc_t *fc, const ql_adc_sweep_t *adc);
const char *ql_fc_label(uint8_t index); /* NULL beyond the board's labels */

#endif
