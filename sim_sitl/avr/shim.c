/*
 * quadlink's board around simavr: the FlightCtrl's pins as firmware/HARDWARE.md defines them, driven in
 * whole chunks of cycles (Python calls this through ctypes once per 2 ms board tick, never per instruction).
 *
 *   ADC0..7        millivolts per channel (AVCC = AREF = 5000 mV)
 *   USART0/USART1  every transmitted byte with the cycle at which its stop bit left the pin; USART0 also
 *                  receives: queued bytes enter the receiver one byte time apart, only while simavr's
 *                  UART says XON (its input FIFO has room) and the receiver is enabled
 *   TWI            four BL-Ctrl slaves (8-bit write addresses 0x52, 0x54, 0x56, 0x58) that ACK their
 *                  address and keep the last byte written, how many bytes were written and when
 *   PB0, PB1       every edge with its cycle (PB0: the 500 Hz loop's busy pin; PB1: the LED, on while armed)
 *   EEPROM         read and written whole (parameters surviving a reset)
 *
 * Four corrections to simavr 1.6, so the pins behave as the datasheet's:
 *   - its UART counts a parity bit in every frame (1 + data + 1 + stop): an 8N1 byte takes 11 bit times
 *     instead of 10, so the 22-byte 'I' frame would take 105 % of the 2 ms tick. cycles_per_byte is
 *     recomputed here from the UART's registers after every write to them (start + data + parity if
 *     enabled + stop bits);
 *   - its default sleep callback usleeps to match the wall clock; the SITL owns time, so it is a no-op;
 *   - its TWI master keeps the TWDR-written latch while it sends SLA+W, so an acknowledged address reads as
 *     status 0x28 (data ACK) instead of 0x18 (TW_MT_SLA_ACK) and a firmware checking 0x18 never sends its
 *     byte: the latch is cleared when the address goes out, before simavr picks the status;
 *   - its TWINT flag is "sticky": writing TWCR with TWINT = 1 (the datasheet's way to clear it and start the
 *     next step) leaves it set, so a polling master never waits for its address or byte to go out. TWCR's
 *     write handler is wrapped to clear TWINT when it was written as 1; simavr sets it again when the step ends.
 * Not corrected: simavr 1.6 takes one TWI bit as 1 us whatever TWBR says (a byte in 9 us instead of 22.5 us
 * at 400 kHz), so a firmware waiting on TWI spends fewer cycles than on the board.
 *
 * Written for quadlink against simavr's public headers (GPL-3 library, linked dynamically).
 */
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_io.h>
#include <simavr/sim_irq.h>
#include <simavr/sim_cycle_timers.h>
#include <simavr/avr_adc.h>
#include <simavr/avr_uart.h>
#include <simavr/avr_twi.h>
#include <simavr/avr_ioport.h>
#include <simavr/avr_eeprom.h>

#define QS_UART_COUNT 2
#define QS_TX_CAP 16384        /* bytes kept per UART between two takes */
#define QS_RX_CAP 65536        /* bytes queued for USART0's receiver */
#define QS_EDGE_CAP 4096       /* PB edges kept between two takes */
#define QS_MOTORS 4
#define QS_ADC_CHANNELS 8
#define QS_AVCC_MV 5000
#define QS_MOTOR_BASE_ADDR 0x52 /* 8-bit write address of motor 1; motor k at 0x52 + 2k */

typedef struct {
	uint8_t byte[QS_TX_CAP];
	uint64_t cycle[QS_TX_CAP];
	int n;
	uint32_t overflow;          /* bytes lost because nobody took them */
	uint64_t wire_free;         /* cycle at which the last byte's stop bit leaves */
} qs_tx_t;

typedef struct {
	uint64_t cycle[QS_EDGE_CAP];
	uint8_t pin[QS_EDGE_CAP];
	uint8_t level[QS_EDGE_CAP];
	int n;
	uint32_t overflow;
} qs_edges_t;

#define QS_HOOKS 16
struct qs_sim;
typedef void (*qs_post_write_t)(struct qs_sim *s, avr_io_addr_t addr, uint8_t v);
typedef struct {
	struct qs_sim *sim;
	avr_io_write_t orig;
	void *orig_param;
	qs_post_write_t post;
} qs_hook_t;

typedef struct qs_sim {
	avr_t *avr;
	avr_uart_t *uart[QS_UART_COUNT];
	avr_eeprom_t *eeprom;
	avr_twi_t *twi;
	qs_tx_t tx[QS_UART_COUNT];
	/* USART0 receive side */
	uint8_t *rx;
	int rx_head, rx_len;
	int rx_xon;                 /* simavr's UART said there is room */
	uint64_t rx_next;           /* earliest cycle for the next byte to start */
	uint32_t rx_fed;
	uint64_t rx_last_start;     /* cycle the last fed byte started on the wire */
	/* BL-Ctrl slaves */
	int twi_selected;           /* motor index addressed for writing, or -1 */
	uint8_t motor[QS_MOTORS];
	uint32_t motor_writes[QS_MOTORS];
	uint64_t motor_cycle[QS_MOTORS];
	uint32_t twi_nacked;        /* addresses nobody answered */
	avr_irq_t *twi_in;
	avr_irq_t *adc_in[QS_ADC_CHANNELS]; /* ADC0..7 inputs, looked up once */
	/* pins */
	qs_edges_t edges;
	uint64_t target;            /* end of the chunk being run */
	qs_hook_t hooks[QS_HOOKS];
	int hook_count;
	uint32_t *profile;          /* cycles spent at each flash word address (NULL: not profiling) */
	uint32_t profile_words;
	uint32_t resets;
} qs_sim_t;

/* ------------------------------------------------------------------ register write hooks */


static void qs_hooked_write(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
	qs_hook_t *h = (qs_hook_t *)param;
	if (h->orig)
		h->orig(avr, addr, v, h->orig_param);
	else
		avr->data[addr] = v;
	h->post(h->sim, addr, v);
}

/* run `post` after whatever simavr does when the firmware writes `addr` (writes only, never reads) */
static void qs_hook_write(qs_sim_t *s, avr_io_addr_t addr, qs_post_write_t post)
{
	if (s->hook_count >= QS_HOOKS)
		return;
	avr_t *avr = s->avr;
	int io = AVR_DATA_TO_IO(addr);
	qs_hook_t *h = &s->hooks[s->hook_count++];
	h->sim = s;
	h->orig = avr->io[io].w.c;
	h->orig_param = avr->io[io].w.param;
	h->post = post;
	avr->io[io].w.c = qs_hooked_write;
	avr->io[io].w.param = h;
}

/* ------------------------------------------------------------------ time */

static void qs_no_sleep(avr_t *avr, avr_cycle_count_t how_long)
{
	(void)avr;
	(void)how_long; /* simulated time is the SITL's: never wait on the wall clock */
}

static avr_cycle_count_t qs_wake(avr_t *avr, avr_cycle_count_t when, void *param)
{
	(void)avr;
	(void)when;
	(void)param; /* only there so a sleeping core stops at the chunk's end or the next RX byte */
	return 0;
}

/* ------------------------------------------------------------------ UART */

static void qs_uart_fix_timing(qs_sim_t *s, avr_uart_t *u)
{
	avr_t *avr = s->avr;
	uint32_t ubrr = avr_regbit_get(avr, u->ubrrl) | (avr_regbit_get(avr, u->ubrrh) << 8);
	static const int databits[8] = {5, 6, 7, 8, 8, 8, 8, 9};
	int db = databits[avr_regbit_get(avr, u->ucsz) | (avr_regbit_get(avr, u->ucsz2) << 2)];
	int parity = (avr->data[u->r_ucsrc] >> 4) & 3 ? 1 : 0; /* UPMn1:0 */
	int stop = 1 + avr_regbit_get(avr, u->usbs);
	uint32_t cycles_per_bit = (ubrr + 1) * (avr_regbit_get(avr, u->u2x) ? 8 : 16);
	u->cycles_per_byte = cycles_per_bit * (1 + db + parity + stop);
}

static void qs_uart_reg_written(qs_sim_t *s, avr_io_addr_t addr, uint8_t v)
{
	(void)addr;
	(void)v;
	for (int i = 0; i < QS_UART_COUNT; i++)
		if (s->uart[i])
			qs_uart_fix_timing(s, s->uart[i]);
}

static void qs_tx_byte(qs_sim_t *s, int port, uint32_t value)
{
	qs_tx_t *t = &s->tx[port];
	uint64_t start = s->avr->cycle > t->wire_free ? s->avr->cycle : t->wire_free;
	t->wire_free = start + s->uart[port]->cycles_per_byte;
	if (t->n >= QS_TX_CAP) {
		t->overflow++;
		return;
	}
	t->byte[t->n] = (uint8_t)value;
	t->cycle[t->n] = t->wire_free;
	t->n++;
}

static void qs_tx0(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	qs_tx_byte((qs_sim_t *)param, 0, value);
}

static void qs_tx1(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	qs_tx_byte((qs_sim_t *)param, 1, value);
}

static void qs_rx_xon(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	((qs_sim_t *)param)->rx_xon = 1;
}

static void qs_rx_xoff(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	if (value)
		((qs_sim_t *)param)->rx_xon = 0;
}

/* the next queued byte starts on the wire now if the line and the receiver allow it */
static void qs_rx_feed(qs_sim_t *s)
{
	avr_uart_t *u = s->uart[0];
	if (!s->rx_len || !s->rx_xon || s->avr->cycle < s->rx_next || !avr_regbit_get(s->avr, u->rxen))
		return;
	uint8_t b = s->rx[s->rx_head];
	s->rx_head = (s->rx_head + 1) % QS_RX_CAP;
	s->rx_len--;
	s->rx_fed++;
	s->rx_last_start = s->avr->cycle;
	s->rx_next = s->avr->cycle + u->cycles_per_byte;
	avr_raise_irq(u->io.irq + UART_IRQ_INPUT, b);
}

/* ------------------------------------------------------------------ TWI: the BL-Ctrls */

static void qs_twi_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	qs_sim_t *s = (qs_sim_t *)param;
	avr_twi_msg_irq_t m;
	m.u.v = value;
	uint8_t msg = m.u.twi.msg;
	if (msg & TWI_COND_STOP) {
		s->twi_selected = -1;
	}
	if (msg & TWI_COND_START) {
		uint8_t a = m.u.twi.addr;
		int k = (a - QS_MOTOR_BASE_ADDR) / 2;
		s->twi_selected = -1;
		s->twi->state &= ~TWI_COND_WRITE; /* SLA+W is an address, not a data byte (see the top) */
		if (!(a & 1) && a >= QS_MOTOR_BASE_ADDR && (a - QS_MOTOR_BASE_ADDR) % 2 == 0 && k < QS_MOTORS) {
			s->twi_selected = k;
			avr_raise_irq(s->twi_in, avr_twi_irq_msg(TWI_COND_ACK, a, 1));
		} else {
			s->twi_nacked++;
		}
	}
	if ((msg & TWI_COND_WRITE) && s->twi_selected >= 0) {
		int k = s->twi_selected;
		s->motor[k] = m.u.twi.data;
		s->motor_writes[k]++;
		s->motor_cycle[k] = s->avr->cycle;
		avr_raise_irq(s->twi_in, avr_twi_irq_msg(TWI_COND_ACK, m.u.twi.addr, 1));
	}
}

static void qs_twcr_written(qs_sim_t *s, avr_io_addr_t addr, uint8_t v)
{
	(void)addr;
	avr_regbit_t twint = s->twi->twi.raised;
	if (v & (twint.mask << twint.bit))
		avr_regbit_clear(s->avr, twint);
}

/* ------------------------------------------------------------------ pins */

static void qs_pin_edge(qs_sim_t *s, uint8_t pin, uint32_t level)
{
	qs_edges_t *e = &s->edges;
	if (e->n >= QS_EDGE_CAP) {
		e->overflow++;
		return;
	}
	e->cycle[e->n] = s->avr->cycle;
	e->pin[e->n] = pin;
	e->level[e->n] = (uint8_t)(level & 1);
	e->n++;
}

static void qs_pb0(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	qs_pin_edge((qs_sim_t *)param, 0, value);
}

static void qs_pb1(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	qs_pin_edge((qs_sim_t *)param, 1, value);
}

/* ------------------------------------------------------------------ lifecycle */

static void qs_find_ios(qs_sim_t *s)
{
	for (avr_io_t *io = s->avr->io_port; io; io = io->next) {
		if (!strcmp(io->kind, "uart")) {
			avr_uart_t *u = (avr_uart_t *)io;
			int k = u->name - '0';
			if (k >= 0 && k < QS_UART_COUNT)
				s->uart[k] = u;
		} else if (!strcmp(io->kind, "twi")) {
			s->twi = (avr_twi_t *)io;
		} else if (!strcmp(io->kind, "eeprom")) {
			s->eeprom = (avr_eeprom_t *)io;
		}
	}
}

/* simavr's messages: errors to stderr; warnings ("avr_timer_write_ocr mode 0 UNSUPPORTED" when a firmware
 * writes OCR1A before the timer mode) and chatter ("Loaded 1112 .text") dropped */
static void qs_logger(avr_t *avr, const int level, const char *format, va_list ap)
{
	if (level > LOG_ERROR || (avr && level > avr->log))
		return;
	vfprintf(stderr, format, ap);
}

qs_sim_t *qs_new(const char *elf_path, const char *mmcu, uint32_t frequency_hz, char *err, int err_len)
{
	elf_firmware_t fw;
	memset(&fw, 0, sizeof(fw));
	avr_global_logger_set(qs_logger);
	if (elf_read_firmware(elf_path, &fw) != 0) {
		snprintf(err, err_len, "cannot read the ELF %s", elf_path);
		return NULL;
	}
	avr_t *avr = avr_make_mcu_by_name(mmcu);
	if (!avr) {
		snprintf(err, err_len, "simavr does not know the MCU %s", mmcu);
		return NULL;
	}
	avr_init(avr);
	avr->log = LOG_WARNING;
	avr->sleep = qs_no_sleep;
	strncpy(fw.mmcu, mmcu, sizeof(fw.mmcu) - 1);
	fw.frequency = frequency_hz;
	fw.vcc = fw.avcc = fw.aref = 5000;
	avr_load_firmware(avr, &fw);
	avr->frequency = frequency_hz;
	avr->vcc = avr->avcc = avr->aref = 5000;

	qs_sim_t *s = calloc(1, sizeof(*s));
	s->avr = avr;
	s->rx = malloc(QS_RX_CAP);
	s->twi_selected = -1;
	qs_find_ios(s);
	if (!s->uart[0] || !s->uart[1] || !s->eeprom || !s->twi) {
		snprintf(err, err_len, "%s has no USART0/USART1/TWI/EEPROM in simavr", mmcu);
		avr_terminate(avr);
		free(s->rx);
		free(s);
		return NULL;
	}
	for (int i = 0; i < QS_UART_COUNT; i++) {
		avr_uart_t *u = s->uart[i];
		uint32_t flags = 0; /* no stdio echo, no poll-sleep (it would usleep) */
		avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0' + i), &flags);
		avr_irq_register_notify(u->io.irq + UART_IRQ_OUTPUT, i ? qs_tx1 : qs_tx0, s);
		avr_io_addr_t regs[5] = {u->r_ucsra, u->r_ucsrb, u->r_ucsrc, u->ubrrl.reg, u->ubrrh.reg};
		for (int r = 0; r < 5; r++)
			qs_hook_write(s, regs[r], qs_uart_reg_written);
	}
	qs_hook_write(s, s->twi->r_twcr, qs_twcr_written);
	avr_irq_register_notify(s->uart[0]->io.irq + UART_IRQ_OUT_XON, qs_rx_xon, s);
	avr_irq_register_notify(s->uart[0]->io.irq + UART_IRQ_OUT_XOFF, qs_rx_xoff, s);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_OUTPUT), qs_twi_out, s);
	s->twi_in = avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_INPUT);
	for (int c = 0; c < QS_ADC_CHANNELS; c++)
		s->adc_in[c] = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + c);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), IOPORT_IRQ_PIN0), qs_pb0, s);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), IOPORT_IRQ_PIN1), qs_pb1, s);
	return s;
}

void qs_free(qs_sim_t *s)
{
	if (!s)
		return;
	avr_terminate(s->avr);
	free(s->avr);
	free(s->rx);
	free(s->profile);
	free(s);
}

/* a reset of the MCU (the reset pin): RAM, registers and peripherals, not the EEPROM nor the cycle count */
void qs_reset(qs_sim_t *s)
{
	avr_reset(s->avr);
	s->rx_xon = 0;
	s->twi_selected = -1;
	s->resets++;
}

/* ------------------------------------------------------------------ running */

uint64_t qs_cycle(qs_sim_t *s) { return s->avr->cycle; }

int qs_state(qs_sim_t *s) { return s->avr->state; }

/* run until the cycle counter reaches `target` (a sleeping core may pass it by at most one cycle);
 * returns simavr's state (cpu_Crashed / cpu_Done end the run early) */
int qs_run_until(qs_sim_t *s, uint64_t target)
{
	avr_t *avr = s->avr;
	s->target = target;
	while (avr->cycle < target) {
		uint64_t before = avr->cycle;
		avr_flashaddr_t pc = avr->pc;
		qs_rx_feed(s);
		if (avr->state == cpu_Sleeping) {
			uint64_t wake = target;
			if (s->rx_len && s->rx_xon && s->rx_next > avr->cycle && s->rx_next < wake)
				wake = s->rx_next;
			avr_cycle_timer_register(avr, wake > avr->cycle ? wake - avr->cycle : 1, qs_wake, s);
		}
		int sleeping = avr->state == cpu_Sleeping;
		int st = avr_run(avr);
		if (s->profile && !sleeping && (pc >> 1) < s->profile_words)
			s->profile[pc >> 1] += (uint32_t)(avr->cycle - before);
		if (st == cpu_Crashed || st == cpu_Done)
			return st;
	}
	avr_cycle_timer_cancel(avr, qs_wake, s);
	return avr->state;
}

/* cycle profile: the cycles each instruction (by flash word address) took, sleep excluded; interrupt entry is
 * counted at the instruction it interrupted. on = 0 stops and frees it. */
void qs_profile(qs_sim_t *s, int on)
{
	free(s->profile);
	s->profile = NULL;
	if (on) {
		s->profile_words = (s->avr->flashend + 1) / 2;
		s->profile = calloc(s->profile_words, sizeof(uint32_t));
	}
}

int qs_profile_take(qs_sim_t *s, uint32_t *out, int max)
{
	if (!s->profile)
		return 0;
	int n = (int)s->profile_words < max ? (int)s->profile_words : max;
	memcpy(out, s->profile, n * sizeof(uint32_t));
	memset(s->profile, 0, s->profile_words * sizeof(uint32_t));
	return n;
}

/* ------------------------------------------------------------------ ADC */

void qs_set_adc_mv(qs_sim_t *s, int channel, uint32_t millivolts)
{
	avr_raise_irq(s->adc_in[channel], millivolts);
}

/* ADC0..n-1 at once (one call per tick): each channel driven with the smallest input simavr's converter
 * (count = mV * 1023 / AVCC) reads as counts[c], counts clamped to 0..1023 (sim.py's mv_for_count) */
void qs_set_adc_counts(qs_sim_t *s, const uint16_t *counts, int n)
{
	for (int c = 0; c < n && c < QS_ADC_CHANNELS; c++) {
		uint32_t count = counts[c] > 1023 ? 1023 : counts[c];
		avr_raise_irq(s->adc_in[c], (count * QS_AVCC_MV + 1022) / 1023);
	}
}

/* ------------------------------------------------------------------ UARTs */

/* moves the bytes transmitted since the last call (and the cycle each one completed) out; returns the count */
int qs_uart_take(qs_sim_t *s, int port, uint8_t *bytes, uint64_t *cycles, int max)
{
	qs_tx_t *t = &s->tx[port];
	int n = t->n < max ? t->n : max;
	memcpy(bytes, t->byte, n);
	memcpy(cycles, t->cycle, n * sizeof(uint64_t));
	memmove(t->byte, t->byte + n, t->n - n);
	memmove(t->cycle, t->cycle + n, (t->n - n) * sizeof(uint64_t));
	t->n -= n;
	return n;
}

uint32_t qs_uart_tx_overflow(qs_sim_t *s, int port) { return s->tx[port].overflow; }

uint32_t qs_uart_cycles_per_byte(qs_sim_t *s, int port) { return (uint32_t)s->uart[port]->cycles_per_byte; }

/* queue bytes for USART0's receiver; returns how many fit */
int qs_uart0_send(qs_sim_t *s, const uint8_t *data, int n)
{
	int k = 0;
	while (k < n && s->rx_len < QS_RX_CAP) {
		s->rx[(s->rx_head + s->rx_len) % QS_RX_CAP] = data[k++];
		s->rx_len++;
	}
	return k;
}

int qs_uart0_pending(qs_sim_t *s) { return s->rx_len; }

uint32_t qs_uart0_fed(qs_sim_t *s) { return s->rx_fed; }

/* the cycle at which the last byte fed to USART0 was completely received (its stop bit) */
uint64_t qs_uart0_last_received(qs_sim_t *s) { return s->rx_last_start + s->uart[0]->cycles_per_byte; }

/* ------------------------------------------------------------------ TWI motors */

void qs_motors(qs_sim_t *s, uint8_t *bytes, uint32_t *writes, uint64_t *cycles)
{
	memcpy(bytes, s->motor, QS_MOTORS);
	memcpy(writes, s->motor_writes, sizeof(s->motor_writes));
	memcpy(cycles, s->motor_cycle, sizeof(s->motor_cycle));
}

uint32_t qs_twi_nacked(qs_sim_t *s) { return s->twi_nacked; }

/* ------------------------------------------------------------------ pins */

int qs_edges_take(qs_sim_t *s, uint64_t *cycles, uint8_t *pins, uint8_t *levels, int max)
{
	qs_edges_t *e = &s->edges;
	int n = e->n < max ? e->n : max;
	memcpy(cycles, e->cycle, n * sizeof(uint64_t));
	memcpy(pins, e->pin, n);
	memcpy(levels, e->level, n);
	memmove(e->cycle, e->cycle + n, (e->n - n) * sizeof(uint64_t));
	memmove(e->pin, e->pin + n, e->n - n);
	memmove(e->level, e->level + n, e->n - n);
	e->n -= n;
	return n;
}

uint32_t qs_edges_overflow(qs_sim_t *s) { return s->edges.overflow; }

/* the level PORTB drives on `pin` now (the LED) */
int qs_portb(qs_sim_t *s, int pin)
{
	avr_ioport_state_t st;
	if (avr_ioctl(s->avr, AVR_IOCTL_IOPORT_GETSTATE('B'), &st) != 0)
		return -1;
	return (st.port >> pin) & 1;
}

/* ------------------------------------------------------------------ EEPROM */

int qs_eeprom_size(qs_sim_t *s) { return s->eeprom->size; }

int qs_eeprom_read(qs_sim_t *s, uint8_t *buf, int n)
{
	if (n > s->eeprom->size)
		n = s->eeprom->size;
	memcpy(buf, s->eeprom->eeprom, n);
	return n;
}

int qs_eeprom_write(qs_sim_t *s, const uint8_t *buf, int n)
{
	if (n > s->eeprom->size)
		n = s->eeprom->size;
	memcpy(s->eeprom->eeprom, buf, n);
	return n;
}
