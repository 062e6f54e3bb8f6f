#include "baro.h"

#include "fxmath.h"
#include "sensors.h"

void ql_baro_init(ql_baro_t *b)
{
    b->p16 = b->pf16 = b->pref_q12 = 0;
    b->h_q8 = b->v_t16 = 0;
    b->ref_ticks = 0;
    b->started = 0;
    b->was_armed = 0;
    b->saturated = 0;
}

void ql_baro_update(ql_baro_t *b, const uint16_t counts[QL_BARO_OVERSAMPLE], uint8_t armed)
{
    int32_t sum = 0;
    uint8_t sat = 0;
    for (uint8_t i = 0; i < QL_BARO_OVERSAMPLE; i++) {
        uint16_t c = counts[i] > QL_BARO_ADC_MAX ? QL_BARO_ADC_MAX : counts[i];
        sat |= (uint8_t)(c == 0u || c == QL_BARO_ADC_MAX);
        sum += (int32_t)c;
    }
    b->saturated = sat;
    b->p16 = QL_BARO_P0_PA * INT32_C(16) + ((sum * QL_BARO_P16_PER_SUM_K) >> QL_BARO_P16_PER_SUM_SHIFT);
    if (!b->started) {
        b->pf16 = b->p16;
        b->pref_q12 = b->p16 << 8;
        b->started = 1;
    }
    b->pf16 += QL_RSHIFT(b->p16 - b->pf16, QL_BARO_LP_SHIFT);
    if (!armed) {
        b->pref_q12 += QL_RSHIFT((b->p16 << 8) - b->pref_q12, QL_BARO_REF_SHIFT);
        if (b->ref_ticks < QL_BARO_REF_TICKS) {
            b->ref_ticks++;
        }
    } else if (!b->was_armed) {
        b->h_q8 = 0; /* arming: the disarmed average is the new zero */
        b->v_t16 = 0;
    }
    b->was_armed = armed;

    int32_t meas_mm = ((QL_RSHIFT(b->pref_q12, 8) - b->p16) * QL_BARO_MM_PER_P16_K) >> QL_BARO_MM_PER_P16_SHIFT;
    b->h_q8 += QL_RSHIFT(b->v_t16, 8);
    int32_t r = (meas_mm << 8) - b->h_q8;
    b->h_q8 += QL_RSHIFT(r, QL_BARO_ALPHA_SHIFT);
    b->v_t16 += QL_RSHIFT(r, QL_BARO_BETA_SHIFT);
    if (b->v_t16 > QL_BARO_V_LIMIT_T16) { /* a jump of the sensor must not overflow the climb scaling */
        b->v_t16 = QL_BARO_V_LIMIT_T16;
    } else if (b->v_t16 < -QL_BARO_V_LIMIT_T16) {
        b->v_t16 = -QL_BARO_V_LIMIT_T16;
    }
}

uint8_t ql_baro_valid(const ql_baro_t *b) { return (uint8_t)(b->ref_ticks >= QL_BARO_REF_TICKS && !b->saturated); }

/* mm * 256 -> cm without a division: (mm / 2) * 3277 / 2^14 = mm * 0.100006 (0.6 cm at the 925 m extreme) */
int32_t ql_baro_altitude_cm(const ql_baro_t *b) { return ((b->h_q8 >> 9) * INT32_C(3277)) >> 14; }

int16_t ql_baro_climb_cm_s(const ql_baro_t *b)
{
    /* mm/tick * 2^16 -> cm/s: * 500 / 10 / 65536 = * 25 / 2^15 */
    int32_t c = QL_RSHIFT(b->v_t16 * INT32_C(25), 15);
    return (int16_t)(c > INT32_C(32767) ? INT32_C(32767) : (c < -INT32_C(32768) ? -INT32_C(32768) : c));
}

uint32_t ql_baro_pressure_pa(const ql_baro_t *b) { return (uint32_t)QL_RSHIFT(b->pf16, 4); }

float ql_baro_climb_m_s(const ql_baro_t *b) { return (float)b->v_t16 * ((float)QL_LOOP_HZ / 65536.0f / 1000.0f); }
