#include "twi.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#define TWI_HZ 400000UL
#define TWBR_400K ((uint8_t)(((F_CPU / TWI_HZ) - 16u) / 2u)) /* prescaler 1: 17 */

/* TWSR status codes (master transmitter) */
#define TW_START_SENT 0x08u
#define TW_REP_START_SENT 0x10u
#define TW_SLA_ACK 0x18u
#define TW_DATA_ACK 0x28u

static volatile uint8_t motor_bytes[TWI_MOTORS];
static volatile uint8_t motor; /* TWI_MOTORS: bus idle */
static volatile uint16_t nacks, busy_skips;

#define TWCR_GO ((uint8_t)((1u << TWINT) | (1u << TWEN) | (1u << TWIE)))

void twi_init(void)
{
    TWSR = 0; /* prescaler 1 */
    TWBR = TWBR_400K;
    TWCR = (uint8_t)(1u << TWEN);
    motor = TWI_MOTORS;
}

uint8_t twi_write_motors(const uint8_t bytes[TWI_MOTORS])
{
    if (motor < TWI_MOTORS || (TWCR & (1u << TWSTO))) {
        busy_skips++;
        return 0;
    }
    for (uint8_t i = 0; i < TWI_MOTORS; i++) {
        motor_bytes[i] = bytes[i];
    }
    motor = 0;
    TWCR = (uint8_t)(TWCR_GO | (1u << TWSTA));
    return 1;
}

static void next_motor(void)
{
    motor++;
    if (motor < TWI_MOTORS) {
        TWCR = (uint8_t)(TWCR_GO | (1u << TWSTA)); /* repeated start to the next BL-Ctrl */
    } else {
        TWCR = (uint8_t)((1u << TWINT) | (1u << TWEN) | (1u << TWSTO)); /* stop; no more interrupts */
    }
}

ISR(TWI_vect)
{
    uint8_t status = (uint8_t)(TWSR & 0xF8u);
    if (motor >= TWI_MOTORS) {
        TWCR = (uint8_t)((1u << TWINT) | (1u << TWEN) | (1u << TWSTO));
        return;
    }
    switch (status) {
    case TW_START_SENT:
    case TW_REP_START_SENT:
        TWDR = (uint8_t)(TWI_BLCTRL_ADDR_W + 2u * motor);
        TWCR = TWCR_GO;
        break;
    case TW_SLA_ACK:
        TWDR = motor_bytes[motor];
        TWCR = TWCR_GO;
        break;
    case TW_DATA_ACK:
        next_motor();
        break;
    default: /* address or data not acknowledged, arbitration lost, bus error: skip this controller */
        nacks++;
        next_motor();
        break;
    }
}

uint16_t twi_nacks(void)
{
    uint8_t sreg = SREG;
    cli();
    uint16_t n = nacks;
    SREG = sreg;
    return n;
}

uint16_t twi_busy_skips(void)
{
    uint8_t sreg = SREG;
    cli();
    uint16_t n = busy_skips;
    SREG = sreg;
    return n;
}
