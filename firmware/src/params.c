#include "params.h"

#include <string.h>

void ql_params_defaults(ql_params_t *p)
{
    memset(p, 0, sizeof(*p)); /* padding bytes too: the CRC covers the whole struct */
    p->version = QL_PARAMS_VERSION;
    p->angle_kp_1_s = 7.0f;
    p->rate_kp_1_s = 16.0f;
    p->rate_ki_1_s2 = 20.0f;
    p->rate_kd = 0.15f;
    p->yaw_rate_kp_1_s = 8.0f;
    p->yaw_rate_ki_1_s2 = 4.0f;
    p->max_tilt_rad = 0.6f;
    p->max_rate_rad_s = 3.5f;
    p->max_yaw_rate_rad_s = 2.5f;
    p->integrator_limit_rad_s2 = 20.0f;
    p->setpoint_timeout_s = 0.5f;
    p->landed_thrust_fraction = 0.15f;
    p->failsafe_descent_m_s = 0.5f;
    p->failsafe_climb_gain_1_m_s = 0.3f;
    p->failsafe_thrust_min = 0.7f;
    p->failsafe_thrust_max = 1.1f;
    p->failsafe_ground_speed_m_s = 0.15f;
    p->battery_low_mv = 10500u; /* 3.5 V per cell, 3S */
    p->mass_kg = 1.0f;
    p->inertia_kg_m2[0] = 0.0075f;
    p->inertia_kg_m2[1] = 0.0075f;
    p->inertia_kg_m2[2] = 0.013f;
    p->arm_length_m = 0.25f;
    p->frame_x = 1u;
    p->max_thrust_n = 5.0f;
    p->idle_fraction = 0.08f;
    p->drag_torque_per_thrust_m = 0.016f;
}

uint16_t ql_crc16(const uint8_t *data, uint16_t len)
{
    uint16_t crc = 0xFFFFu;
    for (uint16_t i = 0; i < len; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (uint8_t b = 0; b < 8u; b++) {
            crc = (uint16_t)((crc & 0x8000u) ? ((uint16_t)(crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1));
        }
    }
    return crc;
}

uint8_t ql_params_load(ql_params_t *p, const uint8_t *image, uint16_t image_len)
{
    const uint16_t n = (uint16_t)sizeof(ql_params_t);
    if (image_len >= QL_PARAMS_IMAGE_LEN) {
        uint16_t crc = (uint16_t)(image[n] | ((uint16_t)image[n + 1u] << 8));
        if (crc == ql_crc16(image, n)) {
            memcpy(p, image, n);
            if (p->version == QL_PARAMS_VERSION) {
                return 1;
            }
        }
    }
    ql_params_defaults(p);
    return 0;
}

uint16_t ql_params_store(const ql_params_t *p, uint8_t *image)
{
    const uint16_t n = (uint16_t)sizeof(ql_params_t);
    memcpy(image, p, n);
    uint16_t crc = ql_crc16(image, n);
    image[n] = (uint8_t)crc;
    image[n + 1u] = (uint8_t)(crc >> 8);
    return QL_PARAMS_IMAGE_LEN;
}
