#include "adc.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <string.h>

/* channel order of a sweep: the six IMU channels first (sampled closest to the tick), the slow ones after */
static const uint8_t k_sequence[] = {0, 1, 2, 3, 4, 5, 6, 6, 6, 6, 6, 6, 6, 6, 7};
#define SEQ_LEN ((uint8_t)sizeof(k_sequence))

static volatile uint16_t work[SEQ_LEN];
static volatile uint16_t done[SEQ_LEN];
static volatile uint8_t index_; /* SEQ_LEN: idle */
static volatile uint8_t fresh;
static volatile uint16_t overruns;

static void select_and_start(uint8_t ch)
{
    ADMUX = (uint8_t)((1u << REFS0) | ch); /* AVCC reference, right adjusted */
    ADCSRA |= (uint8_t)(1u << ADSC);
}

void adc_init(void)
{
    DIDR0 = 0xFFu; /* all eight pins analog: no digital input buffers */
    ADCSRA = (uint8_t)((1u << ADEN) | (1u << ADIE) | (1u << ADPS2) | (1u << ADPS1) | (1u << ADPS0));
    for (uint8_t i = 0; i < SEQ_LEN; i++) {
        work[i] = done[i] = 512u;
    }
    index_ = SEQ_LEN;
}

void adc_start_sweep(void)
{
    if (index_ < SEQ_LEN) {
        overruns++;
        return;
    }
    index_ = 0;
    select_and_start(k_sequence[0]);
}

ISR(ADC_vect)
{
    uint8_t i = index_;
    if (i >= SEQ_LEN) {
        return;
    }
    work[i] = ADC;
    i++;
    if (i < SEQ_LEN) {
        select_and_start(k_sequence[i]);
    } else {
        for (uint8_t k = 0; k < SEQ_LEN; k++) {
            done[k] = work[k];
        }
        fresh = 1;
    }
    index_ = i;
}

uint8_t adc_take_sweep(ql_adc_sweep_t *out)
{
    uint16_t copy[SEQ_LEN];
    uint8_t sreg = SREG;
    cli();
    for (uint8_t k = 0; k < SEQ_LEN; k++) {
        copy[k] = done[k];
    }
    uint8_t was_fresh = fresh;
    fresh = 0;
    SREG = sreg;
    for (uint8_t k = 0; k < 3u; k++) {
        out->gyro[k] = copy[k];
        out->accel[k] = copy[3u + k];
    }
    for (uint8_t k = 0; k < QL_BARO_OVERSAMPLE; k++) {
        out->baro[k] = copy[6u + k];
    }
    out->battery = copy[SEQ_LEN - 1u];
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
