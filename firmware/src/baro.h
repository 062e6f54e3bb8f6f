/* Barometric altitude from ADC6 (MPX4115A through the amplifier of firmware/HARDWARE.md).
 *
 * HARDWARE.md's law V_sensor = 5 (0.009 P_kPa - 0.095), V_adc = 2.5 + 10 (V_sensor - 4.05), count = V_adc / 5 V
 * * 1024 inverts to P = 95 000 Pa + count * 1000 / 92.16 Pa (10.85 Pa per count, 95.0 .. 106.1 kPa). The
 * board sums QL_BARO_OVERSAMPLE conversions per tick; the pressure is low-passed, the reference is its
 * average while disarmed (frozen at arming), and an alpha-beta filter (alpha = 2^-7, beta = 2^-15 ~ alpha^2 / 2)
 * on the altitude above the reference (ISA sea-level density) gives altitude and climb. Pure integer code,
 * mirrored by sim_sitl/board_estimators.py. */
#ifndef QL_BARO_H
#define QL_BARO_H

#include <stdint.h>

#define QL_BARO_OVERSAMPLE 8u
#define QL_BARO_P0_PA INT32_C(95000)             /* pressure at count 0 */
#define QL_BARO_P16_PER_SUM_K INT32_C(22222)     /* Pa*16 per count of the 8-sample sum: 21.7014 ~ 22222 / 1024 */
#define QL_BARO_P16_PER_SUM_SHIFT 10
#define QL_BARO_MM_PER_P16_K INT32_C(10655)      /* mm per (Pa * 16): 1000 / (1.225 * 9.80665 * 16) ~ 10655 / 2048 */
#define QL_BARO_MM_PER_P16_SHIFT 11
#define QL_BARO_LP_SHIFT 5               /* pressure low-pass, tau 32 ticks */
#define QL_BARO_REF_SHIFT 8              /* disarmed reference average, tau 256 ticks */
#define QL_BARO_REF_TICKS 256u           /* reference valid after this many ticks */
#define QL_BARO_ALPHA_SHIFT 7
#define QL_BARO_BETA_SHIFT 7             /* v (mm/tick * 2^16) += r (mm * 2^8) >> 7  <=> beta = 2^-15 */
#define QL_BARO_ADC_MAX 1023u
#define QL_BARO_V_LIMIT_T16 INT32_C(6553600)      /* 50 m/s = 100 mm per tick */

typedef struct {
    int32_t p16;        /* this tick's pressure, Pa * 16 */
    int32_t pf16;       /* low-passed pressure, Pa * 16 */
    int32_t pref_q12;   /* reference pressure, Pa * 4096 (8 bits below Pa * 16: no dead band in its average) */
    int32_t h_q8;       /* altitude above the reference, mm * 256, up positive */
    int32_t v_t16;      /* climb, mm per tick * 65536, up positive */
    uint16_t ref_ticks;
    uint8_t started;
    uint8_t was_armed;
    uint8_t saturated;
} ql_baro_t;

void ql_baro_init(ql_baro_t *b);
void ql_baro_update(ql_baro_t *b, const uint16_t counts[QL_BARO_OVERSAMPLE], uint8_t armed);
uint8_t ql_baro_valid(const ql_baro_t *b);
int32_t ql_baro_altitude_cm(const ql_baro_t *b);
int16_t ql_baro_climb_cm_s(const ql_baro_t *b);
uint32_t ql_baro_pressure_pa(const ql_baro_t *b);
float ql_baro_climb_m_s(const ql_baro_t *b);

#endif
