/*
 * magnet-sim: runs the magnet firmware in simavr for isochron's tests (test-only).
 *
 *   magnet-sim FIRMWARE.elf LINK
 *
 * Loads the ELF into a simulated ATmega328P at 16 MHz, attaches UART0 to a
 * pseudo-terminal and makes LINK a symlink to it (the "serial port" the driver
 * opens), and reports on stdout, one line each:
 *
 *   READY <pty> t_us=<sim time>          once the port exists
 *   PIN D8|D12|D13 0|1 t_us=<sim time>   every change of the coil (PB0), calibration LED
 *                                        (PB4) or on-board LED (PB5) pin
 *   RESET t_us=<sim time>                after a RESET request
 *
 * Commands on stdin: RESET (an external reset of the board), QUIT. End of stdin
 * quits too, so a host never outlives the test that started it. Killing the
 * process looks like unplugging the board: the pty disappears and LINK dangles.
 */
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "uart_pty.h"

static avr_t *avr;
static uart_pty_t uart;
static volatile int want_reset, want_quit;
static int pin_level[8] = {-1, -1, -1, -1, -1, -1, -1, -1};

static unsigned long long sim_us(void)
{
    return (unsigned long long)(avr->cycle / (avr->frequency / 1000000));
}

static void report_pin(int bit, int level)
{
    if (pin_level[bit] == level) {
        return;
    }
    pin_level[bit] = level;
    printf("PIN %s %d t_us=%llu\n", bit == 0 ? "D8" : (bit == 4 ? "D12" : "D13"), level,
           sim_us());
}

static void pin_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    report_pin((int)(intptr_t)param, value ? 1 : 0);
}

/* After a reset the port registers are cleared without pin notifications. */
static void report_portb(void)
{
    uint8_t portb = avr->data[0x25];
    uint8_t ddrb = avr->data[0x24];
    report_pin(0, (ddrb & 1) && (portb & 1));
    report_pin(4, (ddrb & 0x10) && (portb & 0x10));
    report_pin(5, (ddrb & 0x20) && (portb & 0x20));
}

static void *stdin_thread(void *arg)
{
    (void)arg;
    char buf[64];
    while (fgets(buf, sizeof buf, stdin)) {
        if (strncmp(buf, "RESET", 5) == 0) {
            want_reset = 1;
        } else if (strncmp(buf, "QUIT", 4) == 0) {
            break;
        }
    }
    want_quit = 1;
    return NULL;
}

int main(int argc, char **argv)
{
    if (argc != 3) {
        fprintf(stderr, "usage: %s FIRMWARE.elf LINK\n", argv[0]);
        return 2;
    }
    setvbuf(stdout, NULL, _IOLBF, 0);

    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(argv[1], &fw) != 0) {
        fprintf(stderr, "magnet-sim: cannot read %s\n", argv[1]);
        return 1;
    }
    strcpy(fw.mmcu, "atmega328p");
    fw.frequency = 16000000;
    avr = avr_make_mcu_by_name(fw.mmcu);
    if (!avr) {
        fprintf(stderr, "magnet-sim: no atmega328p in this simavr\n");
        return 1;
    }
    avr_init(avr);
    avr->log = LOG_ERROR;
    avr_load_firmware(avr, &fw);

    uart_pty_init(avr, &uart);
    uart_pty_connect(&uart, '0');

    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 0), pin_hook,
                            (void *)(intptr_t)0);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 4), pin_hook,
                            (void *)(intptr_t)4);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 5), pin_hook,
                            (void *)(intptr_t)5);

    unlink(argv[2]);
    if (symlink(uart.port[0].slavename, argv[2]) != 0) {
        perror("magnet-sim: symlink");
        return 1;
    }
    report_portb();
    printf("READY %s t_us=%llu\n", uart.port[0].slavename, sim_us());

    pthread_t input;
    pthread_create(&input, NULL, stdin_thread, NULL);

    int state = cpu_Running;
    while (!want_quit && state != cpu_Done && state != cpu_Crashed) {
        state = avr_run(avr);
        if (want_reset) {
            want_reset = 0;
            avr_reset(avr);
            report_portb();
            printf("RESET t_us=%llu\n", sim_us());
        }
    }
    unlink(argv[2]);
    uart_pty_stop(&uart);
    if (state == cpu_Crashed) {
        fprintf(stderr, "magnet-sim: the firmware crashed\n");
        return 1;
    }
    return 0;
}
