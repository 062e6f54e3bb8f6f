/* AVR program that times the pure modules one by one: PB0 high around each call, in a fixed order
 * (attitude, baro, safety, control, I-frame encode, whole tick), repeated; tools/simbench.c with GROUPS=6
 * reports the cycles of each. Sensor inputs vary a little so no branch is always skipped. */
#include <avr/io.h>

#include "../src/fc.h"

static ql_fc_t fc;
static uint8_t sink(void *ctx, uint8_t port, const uint8_t *frame, uint8_t len)
{
    (void)ctx;
    (void)port;
    (void)frame;
    (void)len;
    return 1;
}

#define PULSE(stmt)                                                                                              \
    do {                                                                                                         \
        PORTB |= 1u;                                                                                             \
        stmt;                                                                                                    \
        PORTB &= (uint8_t)~1u;                                                                                   \
        __asm__ volatile("nop\n nop\n nop\n nop");                                                              \
    } while (0)

int main(void)
{
    DDRB |= 1u;
    ql_fc_init(&fc, 0, 0, sink, 0);
    ql_adc_sweep_t s = {{510, 515, 258}, {511, 514, 509}, {600, 601, 600, 602, 600, 601, 600, 600}, 645};
    for (uint16_t i = 0; i < 300u; i++) {
        ql_fc_tick(&fc, &s); /* past the gyro calibration */
    }
    ql_setpoint_msg_t m = {500, -300, 100, 40000u, QL_SETPOINT_FLAG_ARMED, 1};
    ql_safety_on_setpoint(&fc.safety, &fc.params, &m, fc.tick);
    ql_att_cmd_t fly;
    int32_t rates[3] = {2500, -5000, 1250}, motor[4];
    uint8_t frame[QL_MK_MAX_FRAME_LEN], payload[QL_IMU_LEN];
    ql_imu_msg_t imu = {{510, 515, 258}, {511, 514, 509}, 77};
    for (uint16_t k = 0;; k++) {
        s.gyro[0] = (uint16_t)(505u + (k & 15u));
        s.accel[1] = (uint16_t)(500u + (k & 31u));
        PULSE(ql_attitude_update(&fc.att, s.accel, s.gyro, 1, 1));
        PULSE(ql_baro_update(&fc.baro, s.baro, 1));
        PULSE(ql_safety_step(&fc.safety, &fc.params, fc.tick, 0.1f, 1, 1, &fly));
        rates[0] = (int32_t)(2500 + (k & 63));
        PULSE(ql_ctrl_step(&fc.ctrl, &fly, 0, 170000L, -340000L, rates, motor));
        PULSE(ql_mk_encode(frame, 1, 'I', payload, ql_pack_imu(payload, &imu)));
        PULSE(ql_fc_tick(&fc, &s));
        fc.safety.last_setpoint_tick = fc.tick; /* stay armed, no failsafe */
    }
}
