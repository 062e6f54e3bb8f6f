/* Write the EEPROM image of the default parameters (ql_params_t + CRC-16, src/params.c) as Intel HEX for
 * avrdude (-U eeprom:w:quadlink-fc.eep:i) and the simavr SITL. ql_params_t is packed, so the host's layout is
 * the AVR's.   build/host/mkeep > build/quadlink-fc.eep */
#include <stdio.h>

#include "../src/params.h"

int main(void)
{
    ql_params_t p;
    uint8_t image[QL_PARAMS_IMAGE_LEN];
    ql_params_defaults(&p);
    uint16_t n = ql_params_store(&p, image);
    for (uint16_t addr = 0; addr < n; addr = (uint16_t)(addr + 16u)) {
        uint16_t left = (uint16_t)(n - addr);
        uint8_t len = (uint8_t)(left < 16u ? left : 16u);
        uint8_t sum = (uint8_t)(len + (addr >> 8) + (addr & 0xFFu));
        printf(":%02X%04X00", len, addr);
        for (uint8_t i = 0; i < len; i++) {
            printf("%02X", image[addr + i]);
            sum = (uint8_t)(sum + image[addr + i]);
        }
        printf("%02X\n", (uint8_t)(0x100u - sum));
    }
    printf(":00000001FF\n");
    return 0;
}
