/* The FlightCtrl's main loop: Timer1 CTC at 500 Hz; each tick, with PB0 high: port-1 bytes into the decoder,
 * the last ADC sweep into the core (src/fc.c), the motors over TWI, the LED; then the busy time (Timer1
 * counts = CPU cycles) for 'D' analog[16..17]. Only this loop resets the 60 ms watchdog. */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>

#include "../fc.h"
#include "adc.h"
#include "twi.h"
#include "uart.h"

#define TICK_CYCLES 40000u /* 20 MHz / 500 Hz, Timer1 prescaler 1 */
#define PIN_BUSY PB0
#define PIN_LED PB1
#define EEPROM_PARAMS_ADDR 0u

static ql_fc_t fc;
static volatile uint8_t tick_pending;
static volatile uint16_t tick_overruns;

ISR(TIMER1_COMPA_vect)
{
    if (tick_pending) {
        tick_overruns++;
    }
    tick_pending = 1;
    adc_start_sweep();
}

static uint8_t tx(void *ctx, uint8_t port, const uint8_t *frame, uint8_t len)
{
    (void)ctx;
    return uart_send(port == QL_PORT1 ? 0u : 1u, frame, len);
}

static void timer1_init(void)
{
    TCCR1A = 0;
    TCCR1B = (uint8_t)((1u << WGM12) | (1u << CS10)); /* CTC on OCR1A, clk/1 */
    OCR1A = TICK_CYCLES - 1u;
    TIMSK1 = (uint8_t)(1u << OCIE1A);
}

int main(void)
{
    /* The watchdog stays on (at its shortest period) after a reset it caused: clear it first so start-up cannot
     * loop. Only .data/.bss initialisation (well under a millisecond) runs before this. */
    MCUSR = 0;
    wdt_disable();
    DDRB |= (uint8_t)((1u << PIN_BUSY) | (1u << PIN_LED));
    PORTB &= (uint8_t)~((1u << PIN_BUSY) | (1u << PIN_LED));

    uint8_t image[QL_PARAMS_IMAGE_LEN];
    eeprom_read_block(image, (const void *)EEPROM_PARAMS_ADDR, sizeof(image));
    ql_fc_init(&fc, image, sizeof(image), tx, 0);

    uart_init();
    adc_init();
    twi_init();
    sei();
    adc_start_sweep(); /* a complete sweep is ready for the first tick */
    timer1_init();
    wdt_enable(WDTO_60MS);
    set_sleep_mode(SLEEP_MODE_IDLE);

    for (;;) {
        wdt_reset();
        cli();
        if (!tick_pending) {
            sleep_enable();
            sei(); /* the instruction after sei runs before any interrupt: no wake-up is lost */
            sleep_cpu();
            sleep_disable();
            continue;
        }
        tick_pending = 0;
        sei();
        PORTB |= (uint8_t)(1u << PIN_BUSY);

        uint8_t rx[32]; /* port-1 bytes in batches: one call per batch, not three per byte */
        uint8_t n;
        while ((n = uart0_rx_take(rx, sizeof(rx))) != 0u) {
            ql_fc_rx_bytes(&fc, rx, n);
        }
        ql_adc_sweep_t sweep;
        adc_take_sweep(&sweep);
        ql_fc_tick(&fc, &sweep);
        twi_write_motors(fc.motor);
        if (fc.safety.armed) {
            PORTB |= (uint8_t)(1u << PIN_LED);
        } else {
            PORTB &= (uint8_t)~(1u << PIN_LED);
        }

        cli();
        uint16_t busy = TCNT1;
        uint8_t late = (uint8_t)((TIFR1 & (1u << OCF1A)) != 0u);
        sei();
        if (late || tick_pending) { /* the work ran past the next tick */
            fc.late_ticks++;
            busy = (uint16_t)(busy + TICK_CYCLES); /* TCNT1 restarted at the compare match */
        }
        fc.busy_cycles = busy;
        if (busy > fc.busy_max) {
            fc.busy_max = busy;
        }
        PORTB &= (uint8_t)~(1u << PIN_BUSY);
    }
}
