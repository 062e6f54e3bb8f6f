/* TWI master at 400 kHz, interrupt driven: each tick one byte to each of the four BL-Ctrl (8-bit write
 * addresses 0x52, 0x54, 0x56, 0x58), chained with repeated starts, then a stop. About 4 x 20 bit times = 0.2 ms
 * on the bus; the loop never waits for it. */
#ifndef QL_HW_TWI_H
#define QL_HW_TWI_H

#include <stdint.h>

#define TWI_MOTORS 4u
#define TWI_BLCTRL_ADDR_W 0x52u

void twi_init(void);
/* Start the writes; returns 0 (and counts it) if the previous tick's transfer is still on the bus. */
uint8_t twi_write_motors(const uint8_t bytes[TWI_MOTORS]);
uint16_t twi_nacks(void);
uint16_t twi_busy_skips(void);

#endif
