/*
 * A test program for the simavr shim (tests/integration/test_avr_shim.py), not the flight firmware: it
 * exercises every pin of firmware/HARDWARE.md the way a firmware would, with known answers.
 *
 *   - boot: increments EEPROM byte 0 (a boot counter) and sends "B<counter>" on USART0;
 *   - USART0 (115200 8N1, U2X, UBRR 21): every received byte is echoed back + 1, through an RX ring read by
 *     the main loop;
 *   - Timer1 CTC at 500 Hz: PB0 high, converts ADC0..7, queues a 22-byte frame on USART1 (interrupt-driven
 *     ring: 'I', the tick's low byte, ADC0's count as two bytes, then '=' padding, '\r'), writes ADC1's
 *     count / 4 to each of the four BL-Ctrls (0x52..0x58) over TWI, PB0 low;
 *   - PB1 (the LED) mirrors bit 0 of the last byte received.
 */
#include <stdint.h>
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>

#define RING 64

static volatile uint8_t tx1[RING], tx1_head, tx1_tail;
static volatile uint8_t tx0[RING], tx0_head, tx0_tail;
static volatile uint8_t rx0[RING], rx0_head, rx0_tail;
static volatile uint8_t tick_due;
static uint8_t tick;

static void put1(uint8_t b)
{
	uint8_t next = (uint8_t)((tx1_head + 1) % RING);
	if (next == tx1_tail)
		return;
	tx1[tx1_head] = b;
	tx1_head = next;
	UCSR1B |= _BV(UDRIE1);
}

static void put0(uint8_t b)
{
	uint8_t next = (uint8_t)((tx0_head + 1) % RING);
	if (next == tx0_tail)
		return;
	tx0[tx0_head] = b;
	tx0_head = next;
	UCSR0B |= _BV(UDRIE0);
}

ISR(USART1_UDRE_vect)
{
	if (tx1_tail == tx1_head) {
		UCSR1B &= (uint8_t)~_BV(UDRIE1);
		return;
	}
	UDR1 = tx1[tx1_tail];
	tx1_tail = (uint8_t)((tx1_tail + 1) % RING);
}

ISR(USART0_UDRE_vect)
{
	if (tx0_tail == tx0_head) {
		UCSR0B &= (uint8_t)~_BV(UDRIE0);
		return;
	}
	UDR0 = tx0[tx0_tail];
	tx0_tail = (uint8_t)((tx0_tail + 1) % RING);
}

ISR(USART0_RX_vect)
{
	uint8_t b = UDR0;
	uint8_t next = (uint8_t)((rx0_head + 1) % RING);
	if (next != rx0_tail) {
		rx0[rx0_head] = b;
		rx0_head = next;
	}
}

ISR(TIMER1_COMPA_vect)
{
	tick_due = 1;
}

static uint16_t adc(uint8_t ch)
{
	ADMUX = _BV(REFS0) | ch;
	ADCSRA |= _BV(ADSC);
	while (ADCSRA & _BV(ADSC))
		;
	return ADC;
}

static void twi_write(uint8_t addr, uint8_t data)
{
	TWCR = _BV(TWINT) | _BV(TWSTA) | _BV(TWEN);
	while (!(TWCR & _BV(TWINT)))
		;
	TWDR = addr;
	TWCR = _BV(TWINT) | _BV(TWEN);
	while (!(TWCR & _BV(TWINT)))
		;
	if ((TWSR & 0xF8) == 0x18) { /* TW_MT_SLA_ACK */ /* SLA+W acknowledged */
		TWDR = data;
		TWCR = _BV(TWINT) | _BV(TWEN);
		while (!(TWCR & _BV(TWINT)))
			;
	}
	TWCR = _BV(TWINT) | _BV(TWSTO) | _BV(TWEN);
}

int main(void)
{
	DDRB = _BV(PB0) | _BV(PB1);
	UCSR0A = _BV(U2X0);
	UBRR0 = 21;
	UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
	UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
	UCSR1A = _BV(U2X1);
	UBRR1 = 21;
	UCSR1C = _BV(UCSZ11) | _BV(UCSZ10);
	UCSR1B = _BV(TXEN1);
	ADCSRA = _BV(ADEN) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0);
	TWBR = 17; /* 400 kHz at 20 MHz */
	OCR1A = 39999; /* 20 MHz / 40000 = 500 Hz */
	TCCR1B = _BV(WGM12) | _BV(CS10);
	TIMSK1 = _BV(OCIE1A);

	uint8_t boots = eeprom_read_byte((uint8_t *)0);
	boots = (uint8_t)(boots + 1);
	eeprom_write_byte((uint8_t *)0, boots);
	sei();
	put0('B');
	put0(boots);

	for (;;) {
		while (rx0_tail != rx0_head) {
			uint8_t b = rx0[rx0_tail];
			rx0_tail = (uint8_t)((rx0_tail + 1) % RING);
			put0((uint8_t)(b + 1));
			if (b & 1)
				PORTB |= _BV(PB1);
			else
				PORTB &= (uint8_t)~_BV(PB1);
		}
		if (tick_due) {
			tick_due = 0;
			PORTB |= _BV(PB0);
			uint16_t a0 = adc(0);
			uint16_t a1 = adc(1);
			put1('I');
			put1(tick++);
			put1((uint8_t)a0);
			put1((uint8_t)(a0 >> 8));
			for (uint8_t i = 0; i < 17; i++)
				put1('=');
			put1('\r');
			for (uint8_t m = 0; m < 4; m++)
				twi_write((uint8_t)(0x52 + 2 * m), (uint8_t)(a1 >> 2));
			PORTB &= (uint8_t)~_BV(PB0);
		}
		set_sleep_mode(SLEEP_MODE_IDLE);
		cli();
		if (!tick_due && rx0_tail == rx0_head) {
			sleep_enable();
			sei();
			sleep_cpu();
			sleep_disable();
		}
		sei();
	}
}
