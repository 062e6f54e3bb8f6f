#include "fxmath.h"

int32_t ql_wrap_pi_q24(int32_t a)
{
    while (a >= QL_PI_Q24) {
        a -= QL_TWO_PI_Q24;
    }
    while (a < -QL_PI_Q24) {
        a += QL_TWO_PI_Q24;
    }
    return a;
}

/* Taylor series to x^7 in Horner form on [-pi/2, pi/2]: x (1 - x^2/6 (1 - x^2/20 (1 - x^2/42))), with 16-bit
 * operands, 32-bit products and shifts by 16 (the AVR takes the high word for free): x in Q14, x^2 in Q12, the
 * Horner terms in unsigned Q15 (all positive on this interval), 1/42, 0.8 and 2/3 as Q16 multipliers. Max error
 * about 5e-4 (tests/unit/test_firmware_estimators.py); ~4 x cheaper on the AVR than 32 x 32 products. */
#define SIN_8_OVER_42_Q16 UINT32_C(12483)  /* x2 (Q12) / 42 -> Q15: x 8 / 42 */
#define SIN_16_OVER_20_Q16 UINT32_C(52429) /* Q11 / 20 -> Q15: x 16 / 20 */
#define SIN_2_OVER_3_Q16 UINT32_C(43691)   /* Q11 / 6 -> Q15 = x 8 / 3 = x 2 + x 2/3 */
#define Q15_ONE_U UINT32_C(32768)

int16_t ql_sin_q12(int32_t a_q24)
{
    int32_t a = ql_wrap_pi_q24(a_q24);
    if (a > QL_HALF_PI_Q24) {
        a = QL_PI_Q24 - a; /* sin(pi - a) = sin(a) */
    } else if (a < -QL_HALF_PI_Q24) {
        a = -QL_PI_Q24 - a;
    }
    int16_t x = (int16_t)QL_RSHIFT(a, 10);                                /* Q14, |x| <= 25736 */
    uint16_t x2 = (uint16_t)(((int32_t)x * x) >> 16);                     /* Q12, <= 10106 */
    uint16_t t = (uint16_t)(Q15_ONE_U - (((uint32_t)x2 * SIN_8_OVER_42_Q16) >> 16));
    uint16_t u = (uint16_t)(((uint32_t)x2 * t) >> 16);                    /* Q11 */
    t = (uint16_t)(Q15_ONE_U - (((uint32_t)u * SIN_16_OVER_20_Q16) >> 16));
    u = (uint16_t)(((uint32_t)x2 * t) >> 16);
    t = (uint16_t)(Q15_ONE_U - (2u * (uint32_t)u + (((uint32_t)u * SIN_2_OVER_3_Q16) >> 16)));
    int32_t s = ((int32_t)x * (int32_t)t + (INT32_C(1) << 16)) >> 17;  /* Q14 * Q15 -> Q12, rounded */
    if (s > QL_Q12_ONE) {
        s = QL_Q12_ONE;
    } else if (s < -QL_Q12_ONE) {
        s = -QL_Q12_ONE;
    }
    return (int16_t)s;
}

int16_t ql_cos_q12(int32_t a_q24) { return ql_sin_q12(ql_wrap_pi_q24(a_q24) + QL_HALF_PI_Q24); }

/* atan(z) on [0, 1] ~ pi/4 z + z (1 - z)(0.2447 + 0.0663 z) (max error 1.5e-3 rad), z in Q15. */
#define ATAN_PI4_Q15 INT32_C(25736)
#define ATAN_C0_Q15 INT32_C(8018)
#define ATAN_C1_Q15 INT32_C(2173)
#define Q15_ONE INT32_C(32768)

static int32_t atan_unit_q24(int32_t z)
{
    int32_t t = (z * (Q15_ONE - z)) >> 15;
    int32_t poly = ATAN_C0_Q15 + ((ATAN_C1_Q15 * z) >> 15);
    int32_t a15 = ((ATAN_PI4_Q15 * z) >> 15) + ((t * poly) >> 15);
    return a15 << 9; /* Q15 -> Q24 */
}

int32_t ql_atan2_q24(int32_t y, int32_t x)
{
    int32_t ax = x < 0 ? -x : x;
    int32_t ay = y < 0 ? -y : y;
    int32_t a;
    if (ax == 0 && ay == 0) {
        return 0;
    }
    if (ay <= ax) {
        a = atan_unit_q24((ay << 15) / ax);
    } else {
        a = QL_HALF_PI_Q24 - atan_unit_q24((ax << 15) / ay);
    }
    if (x < 0) {
        a = QL_PI_Q24 - a;
    }
    return y < 0 ? -a : a;
}

uint32_t ql_isqrt32(uint32_t n)
{
    uint32_t root = 0;
    uint32_t bit = 1UL << 30;
    while (bit > n) {
        bit >>= 2;
    }
    while (bit != 0u) {
        if (n >= root + bit) {
            n -= root + bit;
            root = (root >> 1) + bit;
        } else {
            root >>= 1;
        }
        bit >>= 2;
    }
    return root;
}
