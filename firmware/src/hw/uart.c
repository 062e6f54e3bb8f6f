#include "uart.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#define UBRR_115200_U2X 21u /* 20 MHz / (8 x 22) = 113 636 Bd, -1.4 % */

/* 256-byte rings with uint8_t indices: one producer, one consumer, and the index each side writes is a single
 * byte, so no critical section is needed. */
typedef struct {
    uint8_t buf[256];
    volatile uint8_t head; /* written by the producer */
    volatile uint8_t tail; /* written by the consumer */
} ring_t;

static ring_t tx_ring[2];
static ring_t rx0_ring;
static volatile uint16_t rx0_overflows;

void uart_init(void)
{
    /* U2X before UBRR: the baud generator (and simavr's model of it) takes the divisor with the mode set */
    UCSR0A = (uint8_t)(1u << U2X0);
    UBRR0 = UBRR_115200_U2X;
    UCSR0C = (uint8_t)((1u << UCSZ01) | (1u << UCSZ00));
    UCSR0B = (uint8_t)((1u << RXEN0) | (1u << TXEN0) | (1u << RXCIE0));
    UCSR1A = (uint8_t)(1u << U2X1);
    UBRR1 = UBRR_115200_U2X;
    UCSR1C = (uint8_t)((1u << UCSZ11) | (1u << UCSZ10));
    UCSR1B = (uint8_t)(1u << TXEN1);
}

uint8_t uart_send(uint8_t port, const uint8_t *data, uint8_t len)
{
    ring_t *r = &tx_ring[port & 1u];
    uint8_t head = r->head;
    uint8_t used = (uint8_t)(head - r->tail);
    if ((uint16_t)used + len > 255u) {
        return 0;
    }
    for (uint8_t i = 0; i < len; i++) {
        r->buf[head++] = data[i];
    }
    r->head = head;
    if (port == 0u) { /* the data-register-empty interrupt drains the ring */
        UCSR0B |= (uint8_t)(1u << UDRIE0);
    } else {
        UCSR1B |= (uint8_t)(1u << UDRIE1);
    }
    return 1;
}

ISR(USART0_UDRE_vect)
{
    ring_t *r = &tx_ring[0];
    if (r->tail != r->head) {
        UDR0 = r->buf[r->tail];
        r->tail = (uint8_t)(r->tail + 1u);
    } else {
        UCSR0B &= (uint8_t)~(1u << UDRIE0);
    }
}

ISR(USART1_UDRE_vect)
{
    ring_t *r = &tx_ring[1];
    if (r->tail != r->head) {
        UDR1 = r->buf[r->tail];
        r->tail = (uint8_t)(r->tail + 1u);
    } else {
        UCSR1B &= (uint8_t)~(1u << UDRIE1);
    }
}

ISR(USART0_RX_vect)
{
    uint8_t b = UDR0;
    uint8_t next = (uint8_t)(rx0_ring.head + 1u);
    if (next == rx0_ring.tail) {
        rx0_overflows++;
        return;
    }
    rx0_ring.buf[rx0_ring.head] = b;
    rx0_ring.head = next;
}

uint8_t uart0_rx_take(uint8_t *out, uint8_t max)
{
    uint8_t tail = rx0_ring.tail;
    uint8_t head = rx0_ring.head; /* bytes the interrupt adds meanwhile wait for the next call */
    uint8_t n = 0;
    while (tail != head && n < max) {
        out[n++] = rx0_ring.buf[tail];
        tail = (uint8_t)(tail + 1u);
    }
    rx0_ring.tail = tail;
    return n;
}

uint16_t uart0_rx_overflows(void)
{
    uint8_t sreg = SREG;
    cli();
    uint16_t n = rx0_overflows;
    SREG = sreg;
    return n;
}
