/*
 * isochron magnet firmware: Arduino Uno R3 (ATmega328P, 16 MHz), plain avr-libc C.
 *
 * Holds the pendulum's ball with an electromagnet switched by a logic-level
 * MOSFET on D8 (PB0); the on-board LED on D13 (PB5) mirrors the coil. A
 * calibration LED on D12 (PB4), in the camera's view, is switched on command
 * (camera latency calibration, `isochron calibrate latency`).
 * Line protocol on UART0 at 115200 8N1 (README.md has the full table):
 *
 *   PING <token>   -> OK PONG <token>
 *   MAGNET ON|OFF  -> OK MAGNET magnet=on|off held_ms=.. hold_max_ms=.. uptime_ms=..
 *   STATUS         -> OK STATUS magnet=.. held_ms=.. hold_max_ms=.. uptime_ms=.. reset=.. fw=..
 *   HOLD <s>       -> OK HOLD hold_max_ms=..      (1..3600 s; coil protection)
 *   LED ON|OFF     -> OK LED led=on|off uptime_ms=..  (D12; switched before the answer)
 *   TEST HANG      -> OK HANG, then the main loop hangs until the watchdog resets the board
 *   anything else  -> ERR <code>   (unknown-command, bad-argument, line-too-long, bad-byte, overrun)
 *   unsolicited    -> EVT BOOT fw=.. reset=power|external|brownout|watchdog|unknown hold_max_ms=..
 *                     EVT HOLD_LIMIT magnet=off held_ms=..
 *
 * The magnet is never switched off because the host went quiet (that would drop
 * the ball); only an explicit MAGNET OFF, the hold limit or a reset switch it off.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <util/atomic.h>

#define FW_VERSION "1"

#define MAGNET_BIT PB0 /* D8: MOSFET gate (10k pull-down on the board) */
#define LED_BIT PB5    /* D13: on-board LED, mirrors the coil */
#define CAL_LED_BIT PB4 /* D12: calibration LED in the camera's view (330 R to GND) */

#define BAUD_UBRR 16 /* 115200 baud with U2X at 16 MHz (as the Arduino core does) */

#define LINE_MAX 32 /* longest accepted command line, without the newline */
#define RX_SIZE 64  /* receive ring, a power of two */
#define TOKEN_MAX 16

#define HOLD_DEFAULT_S 120UL
#define HOLD_MIN_S 1UL
#define HOLD_MAX_S 3600UL

/* Written by the watchdog interrupt just before the reset it precedes; survives
 * the reset (.noinit), so a watchdog reset is recognised even when a bootloader
 * (the Uno's stock optiboot) has already cleared MCUSR. */
#define WDT_MAGIC 0x57D0C0DEUL
static volatile uint32_t wdt_marker __attribute__((section(".noinit")));
static uint8_t mcusr_mirror __attribute__((section(".noinit")));

/* Runs before main (and before .data/.bss are set up): save and clear the reset
 * cause, and stop a watchdog that survived the reset at its shortest timeout. */
void early_init(void) __attribute__((naked, used, section(".init3")));
void early_init(void)
{
    mcusr_mirror = MCUSR;
    MCUSR = 0;
    wdt_disable();
}

static volatile uint32_t ms_now;
static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail, rx_overrun;

static uint8_t magnet_on;
static uint32_t on_since_ms;
static uint32_t hold_max_ms = HOLD_DEFAULT_S * 1000UL;
static const char *reset_cause = "unknown";

ISR(TIMER0_COMPA_vect) { ms_now++; }

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A;
    uint8_t c = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1) & (RX_SIZE - 1));
    if ((status & (_BV(DOR0) | _BV(FE0))) || next == rx_tail) {
        rx_overrun = 1;
        return;
    }
    rx_buf[rx_head] = c;
    rx_head = next;
}

/* First watchdog timeout of a hung main loop: remember why, make the coil safe,
 * and let the watchdog reset the board 15 ms later. */
ISR(WDT_vect)
{
    wdt_marker = WDT_MAGIC;
    PORTB &= (uint8_t)~(_BV(MAGNET_BIT) | _BV(LED_BIT));
    wdt_enable(WDTO_15MS);
    for (;;) {
    }
}

static uint32_t millis(void)
{
    uint32_t t;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { t = ms_now; }
    return t;
}

static void putc_uart(char c)
{
    while (!(UCSR0A & _BV(UDRE0))) {
    }
    UDR0 = (uint8_t)c;
}

static void puts_uart(const char *s)
{
    while (*s) {
        putc_uart(*s++);
    }
}

static void put_u32(uint32_t v)
{
    char buf[11];
    ultoa(v, buf, 10);
    puts_uart(buf);
}

static void end_line(void) { puts_uart("\r\n"); }

static void set_magnet(uint8_t on)
{
    if (on && !magnet_on) {
        on_since_ms = millis();
    }
    magnet_on = on ? 1 : 0;
    if (magnet_on) {
        PORTB |= _BV(MAGNET_BIT) | _BV(LED_BIT);
    } else {
        PORTB &= (uint8_t)~(_BV(MAGNET_BIT) | _BV(LED_BIT));
    }
}

static uint8_t cal_led_on;

/* The calibration LED: switched before the answer is written, so half the
 * command's round trip bounds when it lit. */
static void set_cal_led(uint8_t on)
{
    cal_led_on = on ? 1 : 0;
    if (cal_led_on) {
        PORTB |= _BV(CAL_LED_BIT);
    } else {
        PORTB &= (uint8_t)~_BV(CAL_LED_BIT);
    }
}

static uint32_t held_ms(void) { return magnet_on ? millis() - on_since_ms : 0; }

static void put_state(void)
{
    puts_uart(" magnet=");
    puts_uart(magnet_on ? "on" : "off");
    puts_uart(" held_ms=");
    put_u32(held_ms());
    puts_uart(" hold_max_ms=");
    put_u32(hold_max_ms);
    puts_uart(" uptime_ms=");
    put_u32(millis());
}

static void err(const char *code)
{
    puts_uart("ERR ");
    puts_uart(code);
    end_line();
}

/* Parses 1..4 decimal digits; returns 0 on anything else. */
static uint16_t parse_seconds(const char *s)
{
    uint16_t v = 0;
    uint8_t n = 0;
    for (; *s; s++, n++) {
        if (*s < '0' || *s > '9' || n >= 4) {
            return 0;
        }
        v = (uint16_t)(v * 10 + (uint16_t)(*s - '0'));
    }
    return v;
}

static uint8_t valid_token(const char *s)
{
    uint8_t n = 0;
    for (; *s; s++, n++) {
        char c = *s;
        uint8_t ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') ||
                     (c >= '0' && c <= '9') || c == '-' || c == '_';
        if (!ok || n >= TOKEN_MAX) {
            return 0;
        }
    }
    return n > 0;
}

static void handle(char *line)
{
    if (strcmp(line, "STATUS") == 0) {
        puts_uart("OK STATUS");
        put_state();
        puts_uart(" reset=");
        puts_uart(reset_cause);
        puts_uart(" fw=" FW_VERSION);
        end_line();
    } else if (strcmp(line, "MAGNET ON") == 0 || strcmp(line, "MAGNET OFF") == 0) {
        set_magnet(line[8] == 'N');
        puts_uart("OK MAGNET");
        put_state();
        end_line();
    } else if (strncmp(line, "MAGNET", 6) == 0 && (line[6] == ' ' || line[6] == 0)) {
        err("bad-argument");
    } else if (strcmp(line, "LED ON") == 0 || strcmp(line, "LED OFF") == 0) {
        set_cal_led(line[5] == 'N');
        puts_uart("OK LED led=");
        puts_uart(cal_led_on ? "on" : "off");
        puts_uart(" uptime_ms=");
        put_u32(millis());
        end_line();
    } else if (strncmp(line, "LED", 3) == 0 && (line[3] == ' ' || line[3] == 0)) {
        err("bad-argument");
    } else if (strncmp(line, "PING ", 5) == 0 && valid_token(line + 5)) {
        puts_uart("OK PONG ");
        puts_uart(line + 5);
        end_line();
    } else if (strncmp(line, "PING", 4) == 0 && (line[4] == ' ' || line[4] == 0)) {
        err("bad-argument");
    } else if (strncmp(line, "HOLD ", 5) == 0) {
        uint16_t s = parse_seconds(line + 5);
        if (s < HOLD_MIN_S || s > HOLD_MAX_S) {
            err("bad-argument");
            return;
        }
        hold_max_ms = (uint32_t)s * 1000UL;
        puts_uart("OK HOLD hold_max_ms=");
        put_u32(hold_max_ms);
        end_line();
    } else if (strcmp(line, "HOLD") == 0) {
        err("bad-argument");
    } else if (strcmp(line, "TEST HANG") == 0) {
        puts_uart("OK HANG");
        end_line();
        for (;;) {
            /* A hung main loop: interrupts still run, nobody resets the watchdog. */
        }
    } else {
        err("unknown-command");
    }
}

static void check_hold_limit(void)
{
    if (magnet_on && held_ms() >= hold_max_ms) {
        uint32_t held = held_ms();
        set_magnet(0);
        puts_uart("EVT HOLD_LIMIT magnet=off held_ms=");
        put_u32(held);
        end_line();
    }
}

static char line[LINE_MAX + 1];
static uint8_t line_len, line_too_long, line_bad_byte, line_overrun;

static void feed(uint8_t c)
{
    if (c == '\r') {
        return;
    }
    if (c == '\n') {
        line[line_len] = 0;
        if (line_overrun) {
            err("overrun");
        } else if (line_too_long) {
            err("line-too-long");
        } else if (line_bad_byte) {
            err("bad-byte");
        } else if (line_len > 0) {
            handle(line);
        }
        line_len = line_too_long = line_bad_byte = line_overrun = 0;
        return;
    }
    if (c < 0x20 || c > 0x7e) {
        line_bad_byte = 1;
    } else if (line_len < LINE_MAX) {
        line[line_len++] = (char)c;
    } else {
        line_too_long = 1;
    }
}

static void boot_banner(void)
{
    puts_uart("EVT BOOT fw=" FW_VERSION " reset=");
    puts_uart(reset_cause);
    puts_uart(" hold_max_ms=");
    put_u32(hold_max_ms);
    end_line();
}

static const char *classify_reset(uint8_t mcusr)
{
    if (wdt_marker == WDT_MAGIC || (mcusr & _BV(WDRF))) {
        return "watchdog";
    }
    if (mcusr & _BV(BORF)) {
        return "brownout";
    }
    if (mcusr & _BV(EXTRF)) {
        return "external";
    }
    if (mcusr & _BV(PORF)) {
        return "power";
    }
    return "unknown"; /* e.g. the stock bootloader cleared MCUSR */
}

int main(void)
{
    reset_cause = classify_reset(mcusr_mirror);
    wdt_marker = 0;

    /* Coil off first, then outputs. */
    PORTB &= (uint8_t)~(_BV(MAGNET_BIT) | _BV(LED_BIT) | _BV(CAL_LED_BIT));
    DDRB |= _BV(MAGNET_BIT) | _BV(LED_BIT) | _BV(CAL_LED_BIT);

    /* UART0: 115200 8N1, receive interrupt. */
    UCSR0A = _BV(U2X0);
    UBRR0H = 0;
    UBRR0L = BAUD_UBRR;
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);

    /* Timer0: CTC at 1 kHz (16 MHz / 64 / 250): the millisecond clock. */
    TCCR0A = _BV(WGM01);
    TCCR0B = _BV(CS01) | _BV(CS00);
    OCR0A = 249;
    TIMSK0 = _BV(OCIE0A);

    /* Watchdog: interrupt, then reset, after 0.5 s without wdt_reset(). */
    cli();
    wdt_reset();
    WDTCSR = _BV(WDCE) | _BV(WDE);
    WDTCSR = _BV(WDIE) | _BV(WDE) | _BV(WDP2) | _BV(WDP0);
    sei();

    boot_banner();

    set_sleep_mode(SLEEP_MODE_IDLE);
    for (;;) {
        wdt_reset();
        uint8_t have = 0, c = 0, overrun = 0;
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
        {
            if (rx_tail != rx_head) {
                c = rx_buf[rx_tail];
                rx_tail = (uint8_t)((rx_tail + 1) & (RX_SIZE - 1));
                have = 1;
            }
            overrun = rx_overrun;
            rx_overrun = 0;
        }
        if (overrun) {
            line_overrun = 1;
        }
        if (have) {
            feed(c);
            continue;
        }
        check_hold_limit();
        /* Sleep until the next interrupt (a byte or the 1 ms tick), so that
         * simulated time tracks wall time and the board idles cool. */
        cli();
        if (rx_tail == rx_head) {
            sleep_enable();
            sei();
            sleep_cpu();
            sleep_disable();
        }
        sei();
    }
}
