#include "adc.h"

#include <avr/interrupt.h>
#include <avr/io.h>

/* channel order of a sweep: the six IMU channels first (sampled closest to the tick), the slow ones after; as
 * ADMUX values (AVCC reference, right adjusted) so the interrupt only copies a byte */
#define MUX(ch) ((uint8_t)((1u << REFS0) | (ch)))
static const uint8_t k_admux[] = {MUX(0), MUX(1), MUX(2), MUX(3), MUX(4), MUX(5), MUX(6), MUX(6),
                                  MUX(6), MUX(6), MUX(6), MUX(6), MUX(6), MUX(6), MUX(7)};
#define SEQ_LEN ((uint8_t)sizeof(k_admux))

/* two sweep buffers: the interrupt fills one while the tick reads the other (no copy in the interrupt) */
static uint16_t sweeps[2][SEQ_LEN];
static uint16_t *wptr;           /* next sample of the sweep being written (interrupt-owned) */
static uint8_t index_;           /* conversions done in this sweep; SEQ_LEN: idle */
static uint8_t writing;          /* buffer being written */
static volatile uint8_t ready;   /* last complete buffer */
static volatile uint8_t fresh;
static volatile uint16_t overruns;

void adc_init(void)
{
    DIDR0 = 0xFFu; /* all eight pins analog: no digital input buffers */
    ADCSRA = (uint8_t)((1u << ADEN) | (1u << ADIE) | (1u << ADPS2) | (1u << ADPS1) | (1u << ADPS0));
    for (uint8_t i = 0; i < SEQ_LEN; i++) {
        sweeps[0][i] = sweeps[1][i] = 512u;
    }
    writing = 0;
    ready = 1;
    index_ = SEQ_LEN;
}

void adc_start_sweep(void)
{
    if (index_ < SEQ_LEN) {
        overruns++;
        return;
    }
    index_ = 0;
    wptr = sweeps[writing];
    ADMUX = k_admux[0];
    ADCSRA |= (uint8_t)(1u << ADSC);
}

ISR(ADC_vect)
{
    uint8_t i = index_;
    if (i >= SEQ_LEN) {
        return;
    }
    *wptr++ = ADC;
    i++;
    if (i < SEQ_LEN) {
        ADMUX = k_admux[i];
        ADCSRA |= (uint8_t)(1u << ADSC);
    } else {
        ready = writing;
        writing ^= 1u;
        fresh = 1;
    }
    index_ = i;
}

uint8_t adc_take_sweep(ql_adc_sweep_t *out)
{
    uint8_t sreg = SREG;
    cli();
    const uint16_t *src = sweeps[ready]; /* the interrupt writes the other buffer for the next 1.25 ms */
    uint8_t was_fresh = fresh;
    fresh = 0;
    SREG = sreg;
    for (uint8_t k = 0; k < 3u; k++) {
        out->gyro[k] = src[k];
        out->accel[k] = src[3u + k];
    }
    for (uint8_t k = 0; k < QL_BARO_OVERSAMPLE; k++) {
        out->baro[k] = src[6u + k];
    }
    out->battery = src[SEQ_LEN - 1u];
    return was_fresh;
}

uint16_t adc_sweep_overruns(void)
{
    uint8_t sreg = SREG;
    cli();
    uint16_t n = overruns;
    SREG = sreg;
    return n;
}
