/* USART0 (MK port 1: rx + tx) and USART1 (MK port 2: tx only), 115200 Bd 8N1 (U2X, UBRR 21), interrupt-driven
 * 256-byte rings. Enqueueing never waits: a frame that does not fit whole is refused (the caller counts it). */
#ifndef QL_HW_UART_H
#define QL_HW_UART_H

#include <stdint.h>

void uart_init(void);
/* port 0 = USART0, 1 = USART1. Returns 1 if the whole frame was queued. */
uint8_t uart_send(uint8_t port, const uint8_t *data, uint8_t len);
/* Moves up to max received port-1 bytes (oldest first) to out; returns how many (0: none is waiting). */
uint8_t uart0_rx_take(uint8_t *out, uint8_t max);
uint16_t uart0_rx_overflows(void);

#endif
