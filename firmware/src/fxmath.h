/* Fixed-point helpers of the attitude filter. Every operation is an integer multiply, a shift that rounds
 * half up ((x + 2^(s-1)) >> s, arithmetic), or a division of non-negative values, so that
 * sim_sitl/board_estimators.py reproduces them bit for bit. Angles are rad in Q24 (2^-24 rad),
 * trigonometric values are Q12 (4096 = 1.0). */
#ifndef QL_FXMATH_H
#define QL_FXMATH_H

#include <stdint.h>

#define QL_Q24_ONE INT32_C(16777216)
#define QL_PI_Q24 INT32_C(52707179)       /* round(pi * 2^24) */
#define QL_HALF_PI_Q24 INT32_C(26353589)  /* round(pi / 2 * 2^24) */
#define QL_TWO_PI_Q24 INT32_C(105414357)  /* round(2 pi * 2^24) */
#define QL_Q12_ONE INT32_C(4096)

/* (x + 2^(s-1)) >> s: a rounding right shift (gcc shifts signed values arithmetically). */
#define QL_RSHIFT(x, s) ((int32_t)(((int32_t)(x) + (INT32_C(1) << ((s) - 1))) >> (s)))

int32_t ql_wrap_pi_q24(int32_t a);
int16_t ql_sin_q12(int32_t a_q24);
int16_t ql_cos_q12(int32_t a_q24);
int32_t ql_atan2_q24(int32_t y, int32_t x); /* |y|, |x| < 2^16 */
uint32_t ql_isqrt32(uint32_t n);             /* floor(sqrt(n)) */

#endif
