/* Run quadlink-fc.elf in simavr (libsimavr) for a few simulated seconds with still sensors, arm it with 's'
 * frames at 100 Hz after 1 s, and report the 500 Hz tick's busy time from the PB0 edges (cycles), the frames
 * each port carried. STOP_S=t stops the setpoints at t s (failsafe). Writes the raw port bytes to <out>.port1 / .port2.
 *   build/host/simbench build/quadlink-fc.elf SECONDS OUTPREFIX */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <simavr/avr_adc.h>
#include <simavr/avr_eeprom.h>
#include <simavr/avr_ioport.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>

#include "../src/mk_codec.h"
#include "../src/mk_msgs.h"

static FILE *port_out[2];
static uint64_t rise_cycle, busy_sum, busy_n, busy_max, busy_min = ~0ull;
static uint64_t busy_armed_sum, busy_armed_n, busy_armed_max;
static int armed;
static avr_t *avr;
static int groups = 1;
static uint64_t first_rise, rise_lag_max;
static uint32_t armed_busy[200000];
static size_t armed_busy_n;
static uint64_t group_sum[16], group_n[16], group_max[16];

static void on_uart0(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    fputc((int)(value & 0xFF), port_out[0]);
}

static uint64_t last_u1_cycle, u1_gap_hist[4]; /* gaps between USART1 bytes: <1800, <1900, <2000, more */

static void on_uart1(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    uint64_t gap = avr->cycle - last_u1_cycle;
    last_u1_cycle = avr->cycle;
    u1_gap_hist[gap < 1800u ? 0 : (gap < 1900u ? 1 : (gap < 2000u ? 2 : 3))]++;
    fputc((int)(value & 0xFF), port_out[1]);
}

static void on_pb0(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value) {
        rise_cycle = avr->cycle;
        if (first_rise == 0) {
            first_rise = rise_cycle;
        }
        uint64_t lag = (rise_cycle - first_rise) % 40000u; /* from the tick's compare match (first rise ~ 0) */
        if (lag < 20000u && lag > rise_lag_max) {
            rise_lag_max = lag;
        }
        return;
    }
    if (rise_cycle == 0) {
        return;
    }
    uint64_t busy = avr->cycle - rise_cycle;
    int g = (int)(busy_n % (uint64_t)groups);
    group_sum[g] += busy;
    group_n[g]++;
    group_max[g] = busy > group_max[g] ? busy : group_max[g];
    busy_sum += busy;
    busy_n++;
    busy_max = busy > busy_max ? busy : busy_max;
    busy_min = busy < busy_min ? busy : busy_min;
    if (armed) {
        if (armed_busy_n < sizeof(armed_busy) / sizeof(armed_busy[0])) {
            armed_busy[armed_busy_n++] = (uint32_t)busy;
        }
        busy_armed_sum += busy;
        busy_armed_n++;
        busy_armed_max = busy > busy_armed_max ? busy : busy_armed_max;
    }
}

static int cmp_u32(const void *a, const void *b)
{
    uint32_t x = *(const uint32_t *)a, y = *(const uint32_t *)b;
    return x < y ? -1 : (x > y ? 1 : 0);
}

static void disable_stdio(char uart)
{
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS(uart), &flags);
    flags &= ~(uint32_t)AVR_UART_FLAG_STDIO;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS(uart), &flags);
}

/* EEP=path: preload the EEPROM from an Intel HEX file (the parameter image of tools/mkeep.c) */
static void load_eeprom(const char *path)
{
    FILE *f = fopen(path, "r");
    char line[128];
    static uint8_t mem[4096];
    unsigned top = 0;
    if (f == NULL) {
        fprintf(stderr, "cannot read %s\n", path);
        exit(1);
    }
    while (fgets(line, sizeof(line), f) != NULL) {
        unsigned len, addr, type, byte;
        if (sscanf(line, ":%2x%4x%2x", &len, &addr, &type) != 3 || type != 0) {
            continue;
        }
        for (unsigned i = 0; i < len && addr + i < sizeof(mem); i++) {
            sscanf(line + 9 + 2 * i, "%2x", &byte);
            mem[addr + i] = (uint8_t)byte;
        }
        top = addr + len > top ? addr + len : top;
    }
    fclose(f);
    avr_eeprom_desc_t d = {.ee = mem, .offset = 0, .size = top};
    avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &d);
}

static void set_mv(int channel, uint32_t mv) { avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, channel), mv); }

int main(int argc, char **argv)
{
    if (argc < 4) {
        fprintf(stderr, "usage: %s ELF SECONDS OUTPREFIX\n", argv[0]);
        return 2;
    }
    elf_firmware_t fw;
    memset(&fw, 0, sizeof(fw));
    if (elf_read_firmware(argv[1], &fw) != 0) {
        fprintf(stderr, "cannot read %s\n", argv[1]);
        return 1;
    }
    avr = avr_make_mcu_by_name("atmega1284p");
    avr_init(avr);
    avr->frequency = 20000000;
    avr->avcc = avr->aref = 5000;
    avr_load_firmware(avr, &fw);
    avr->log = LOG_ERROR;

    char path[512];
    for (int p = 0; p < 2; p++) {
        snprintf(path, sizeof(path), "%s.port%d", argv[3], p + 1);
        port_out[p] = fopen(path, "wb");
    }
    if (getenv("EEP") != NULL) {
        load_eeprom(getenv("EEP"));
    }
    disable_stdio('0');
    disable_stdio('1');
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), on_uart0, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('1'), UART_IRQ_OUTPUT), on_uart1, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 0), on_pb0, NULL);

    /* still and level: gyros at zero rate, accel z at -1 g (count 256), 101.3 kPa, 12.6 V */
    for (int ch = 0; ch < 5; ch++) {
        set_mv(ADC_IRQ_ADC0 + ch, 2500);
    }
    set_mv(ADC_IRQ_ADC5, 1250);
    set_mv(ADC_IRQ_ADC6, 2900);
    set_mv(ADC_IRQ_ADC7, 3150);

    if (getenv("GROUPS") != NULL) {
        groups = atoi(getenv("GROUPS"));
        groups = groups < 1 ? 1 : (groups > 16 ? 16 : groups);
    }
    const double seconds = atof(argv[2]);
    const uint64_t end = (uint64_t)(seconds * 20e6);
    uint64_t next_sp = 20000000; /* 1 s: start arming */
    /* STOP_S: the companion goes silent at this time (the board's failsafe takes over) */
    const uint64_t stop = getenv("STOP_S") != NULL ? (uint64_t)(atof(getenv("STOP_S")) * 20e6) : UINT64_MAX;
    uint8_t seq = 0;
    avr_irq_t *rx = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    int state = cpu_Running;
    while (avr->cycle < end && state != cpu_Done && state != cpu_Crashed) {
        state = avr_run(avr);
        if (avr->cycle >= next_sp && avr->cycle < stop) {
            next_sp += 200000; /* 100 Hz */
            ql_setpoint_msg_t m = {0, 0, 0, 32768u, QL_SETPOINT_FLAG_ARMED, seq++};
            uint8_t payload[QL_SETPOINT_LEN], frame[QL_MK_MAX_FRAME_LEN];
            uint8_t n = ql_mk_encode(frame, QL_MK_ADDR_FC, QL_CMD_SETPOINT, payload, ql_pack_setpoint(payload, &m));
            for (uint8_t i = 0; i < n; i++) {
                avr_raise_irq(rx, frame[i]);
            }
            if (seq == 50u) { /* ask for the version once: hardware_error[0] says whether the EEPROM was valid */
                n = ql_mk_encode(frame, QL_MK_ADDR_FC, QL_CMD_VERSION_REQ, payload, 0);
                for (uint8_t i = 0; i < n; i++) {
                    avr_raise_irq(rx, frame[i]);
                }
            }
            if (getenv("NO_D") == NULL && seq % 200u == 1u) { /* every 2 s: 'd' with a 10 ms interval (the heaviest telemetry) */
                uint8_t interval = 1;
                n = ql_mk_encode(frame, QL_MK_ADDR_FC, QL_CMD_DEBUG_REQ, &interval, 1);
                for (uint8_t i = 0; i < n; i++) {
                    avr_raise_irq(rx, frame[i]);
                }
            }
            armed = 1;
        }
    }
    fclose(port_out[0]);
    fclose(port_out[1]);
    printf("simulated %.3f s, cpu state %d\n", (double)avr->cycle / 20e6, state);
    printf("tick busy (PB0 high, cycles of 40000): min %llu mean %.0f max %llu over %llu ticks\n",
           (unsigned long long)busy_min, busy_n ? (double)busy_sum / (double)busy_n : 0.0,
           (unsigned long long)busy_max, (unsigned long long)busy_n);
    printf("USART1 byte gaps (cycles): <1800 %llu, 1800-1899 %llu, 1900-1999 %llu, >=2000 %llu\n",
           (unsigned long long)u1_gap_hist[0], (unsigned long long)u1_gap_hist[1],
           (unsigned long long)u1_gap_hist[2], (unsigned long long)u1_gap_hist[3]);
    printf("tick start lag (PB0 rise after the first tick's phase): max %llu cycles\n",
           (unsigned long long)rise_lag_max);
    printf("armed ticks: mean %.0f max %llu over %llu ticks\n",
           busy_armed_n ? (double)busy_armed_sum / (double)busy_armed_n : 0.0, (unsigned long long)busy_armed_max,
           (unsigned long long)busy_armed_n);
    if (armed_busy_n > 0) {
        qsort(armed_busy, armed_busy_n, sizeof(armed_busy[0]), cmp_u32);
        printf("armed ticks percentiles: 50 %% %u, 90 %% %u, 99 %% %u, 99.9 %% %u, max %u cycles\n",
               armed_busy[armed_busy_n / 2], armed_busy[armed_busy_n * 9 / 10], armed_busy[armed_busy_n * 99 / 100],
               armed_busy[armed_busy_n * 999 / 1000], armed_busy[armed_busy_n - 1]);
    }
    for (int g = 0; groups > 1 && g < groups; g++) {
        printf("pulse %d: mean %.0f max %llu cycles\n", g, group_n[g] ? (double)group_sum[g] / (double)group_n[g] : 0.0,
               (unsigned long long)group_max[g]);
    }
    return state == cpu_Crashed ? 1 : 0;
}
