/* The ADC walks one sweep per 500 Hz tick, interrupt driven (AVCC reference, prescaler 128: 13 ADC clocks =
 * 83.2 us per conversion): gyro x, y, z (ADC0..2), accel x, y, z (ADC3..5), pressure (ADC6) x 8, battery (ADC7);
 * 15 conversions = 1.25 ms. The Timer1 tick starts a sweep; the tick's work reads the last complete one. */
#ifndef QL_HW_ADC_H
#define QL_HW_ADC_H

#include <stdint.h>

#include "../fc.h"

void adc_init(void);
void adc_start_sweep(void); /* from the Timer1 ISR; a sweep still running is counted and left to finish */
/* Copy the last complete sweep; returns 0 if none completed since the previous call (the copy is the old one). */
uint8_t adc_take_sweep(ql_adc_sweep_t *out);
uint16_t adc_sweep_overruns(void);

#endif
