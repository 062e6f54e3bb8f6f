/* The board's parameters (defaults = sim_sitl/config.py FirmwareConfig and configs/vehicle.yaml) and
 * their EEPROM image: the struct followed by a CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over its
 * bytes. A bad CRC (blank or corrupted EEPROM) loads the defaults and the caller flags it. Pure C. */
#ifndef QL_PARAMS_H
#define QL_PARAMS_H

#include <stdint.h>

#define QL_PARAMS_VERSION 1u

/* packed: the same byte layout on the AVR and on the host (IEEE-754 little-endian floats on both), so the host
 * tool tools/mkeep.c writes the EEPROM image the board reads */
typedef struct __attribute__((packed)) {
    uint16_t version;
    /* FirmwareConfig */
    float angle_kp_1_s;
    float rate_kp_1_s;
    float rate_ki_1_s2;
    float rate_kd;
    float yaw_rate_kp_1_s;
    float yaw_rate_ki_1_s2;
    float max_tilt_rad;
    float max_rate_rad_s;
    float max_yaw_rate_rad_s;
    float integrator_limit_rad_s2;
    float setpoint_timeout_s;
    float landed_thrust_fraction;
    float failsafe_descent_m_s;       /* target sink rate of the failsafe descent */
    float failsafe_climb_gain_1_m_s;  /* thrust change (fraction of hover) per m/s of climb error */
    float failsafe_thrust_min;        /* failsafe thrust bounds, fractions of hover thrust */
    float failsafe_thrust_max;
    float failsafe_ground_speed_m_s;  /* |climb| below this (and |f| ~ 1 g) = on the ground */
    uint16_t battery_low_mv;
    /* vehicle */
    float mass_kg;
    float inertia_kg_m2[3];
    float arm_length_m;
    uint8_t frame_x; /* 1: x frame, 0: + frame */
    float max_thrust_n;      /* per motor */
    float idle_fraction;
    float drag_torque_per_thrust_m;
} ql_params_t;

void ql_params_defaults(ql_params_t *p);
uint16_t ql_crc16(const uint8_t *data, uint16_t len);
/* Load from an EEPROM image (sizeof(ql_params_t) + 2 CRC bytes, little-endian). Returns 1 if the CRC and the
 * version matched; else loads the defaults and returns 0. */
uint8_t ql_params_load(ql_params_t *p, const uint8_t *image, uint16_t image_len);
/* Write the image of p (returns its length, sizeof(ql_params_t) + 2). */
uint16_t ql_params_store(const ql_params_t *p, uint8_t *image);

#define QL_PARAMS_IMAGE_LEN ((uint16_t)(sizeof(ql_params_t) + 2u))

#endif
