//! A clock-agnostic model of the firmware (`firmware/magnet/magnet.c`): the same
//! line protocol, the same hold limit, byte for byte the same answers.
//!
//! It runs behind the in-process [`FakeDevice`](super::FakeDevice) in real time,
//! and can be stepped directly in virtual time (the simulated lab): feed it bytes
//! and the time, read the bytes it answers and whether the coil is on.

use crate::magnet::protocol::{
    FW_VERSION, HOLD_DEFAULT_S, HOLD_RANGE_S, LINE_MAX, ResetCause, TOKEN_MAX,
};

/// The firmware's state machine. Times are milliseconds on the caller's clock.
#[derive(Debug, Clone)]
pub struct FirmwareModel {
    magnet_on: bool,
    led_on: bool,
    on_since_ms: u64,
    hold_max_ms: u32,
    boot_ms: u64,
    reset: ResetCause,
    line: [u8; LINE_MAX],
    len: usize,
    too_long: bool,
    bad_byte: bool,
    commands: u64,
    errors: u64,
}

impl FirmwareModel {
    /// A board that has just reset at `now_ms`; its boot banner goes to `out`.
    pub fn boot(now_ms: u64, reset: ResetCause, out: &mut Vec<u8>) -> Self {
        let m = Self {
            magnet_on: false,
            led_on: false,
            on_since_ms: 0,
            hold_max_ms: u32::from(HOLD_DEFAULT_S) * 1000,
            boot_ms: now_ms,
            reset,
            line: [0; LINE_MAX],
            len: 0,
            too_long: false,
            bad_byte: false,
            commands: 0,
            errors: 0,
        };
        m.banner(out);
        m
    }

    /// Resets the board at `now_ms` (coil off, defaults back, a new banner).
    pub fn reset(&mut self, now_ms: u64, reset: ResetCause, out: &mut Vec<u8>) {
        *self = Self::boot(now_ms, reset, out);
    }

    /// Whether the coil is energised (the D8 pin).
    pub fn magnet_on(&self) -> bool {
        self.magnet_on
    }

    /// Whether the calibration LED is lit (the D12 pin).
    pub fn led_on(&self) -> bool {
        self.led_on
    }

    /// Complete command lines received (answered with `OK` or `ERR`).
    pub fn commands(&self) -> u64 {
        self.commands
    }

    /// Command lines answered with `ERR`.
    pub fn errors(&self) -> u64 {
        self.errors
    }

    /// The hold limit in force, ms.
    pub fn hold_max_ms(&self) -> u32 {
        self.hold_max_ms
    }

    fn banner(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(
            format!(
                "EVT BOOT fw={FW_VERSION} reset={} hold_max_ms={}\r\n",
                self.reset.as_str(),
                self.hold_max_ms
            )
            .as_bytes(),
        );
    }

    fn held_ms(&self, now_ms: u64) -> u64 {
        if self.magnet_on {
            now_ms.saturating_sub(self.on_since_ms)
        } else {
            0
        }
    }

    fn state(&self, now_ms: u64) -> String {
        format!(
            " magnet={} held_ms={} hold_max_ms={} uptime_ms={}",
            if self.magnet_on { "on" } else { "off" },
            self.held_ms(now_ms),
            self.hold_max_ms,
            now_ms.saturating_sub(self.boot_ms)
        )
    }

    /// Advances time: the hold limit switches the coil off and reports it.
    pub fn tick(&mut self, now_ms: u64, out: &mut Vec<u8>) {
        let held = self.held_ms(now_ms);
        if self.magnet_on && held >= u64::from(self.hold_max_ms) {
            self.magnet_on = false;
            out.extend_from_slice(
                format!("EVT HOLD_LIMIT magnet=off held_ms={held}\r\n").as_bytes(),
            );
        }
    }

    /// One received byte at `now_ms`; answers go to `out`.
    pub fn feed(&mut self, byte: u8, now_ms: u64, out: &mut Vec<u8>) {
        match byte {
            b'\r' => {}
            b'\n' => {
                let (too_long, bad_byte, len) = (self.too_long, self.bad_byte, self.len);
                self.len = 0;
                self.too_long = false;
                self.bad_byte = false;
                if too_long {
                    self.answer_err("line-too-long", out);
                } else if bad_byte {
                    self.answer_err("bad-byte", out);
                } else if len > 0 {
                    let line = String::from_utf8_lossy(&self.line[..len]).into_owned();
                    self.commands += 1;
                    self.handle(&line, now_ms, out);
                }
            }
            0x20..=0x7e => {
                if self.len < LINE_MAX {
                    self.line[self.len] = byte;
                    self.len += 1;
                } else {
                    self.too_long = true;
                }
            }
            _ => self.bad_byte = true,
        }
    }

    fn answer_err(&mut self, code: &str, out: &mut Vec<u8>) {
        self.commands += 1;
        self.errors += 1;
        out.extend_from_slice(format!("ERR {code}\r\n").as_bytes());
    }

    fn handle(&mut self, line: &str, now_ms: u64, out: &mut Vec<u8>) {
        let answer = self.answer(line, now_ms);
        if answer.starts_with("ERR") {
            self.errors += 1;
        }
        out.extend_from_slice(answer.as_bytes());
        out.extend_from_slice(b"\r\n");
    }

    fn answer(&mut self, line: &str, now_ms: u64) -> String {
        let first = line.split(' ').next().unwrap_or("");
        match line {
            "STATUS" => format!(
                "OK STATUS{} reset={} fw={FW_VERSION}",
                self.state(now_ms),
                self.reset.as_str()
            ),
            "MAGNET ON" | "MAGNET OFF" => {
                let on = line == "MAGNET ON";
                if on && !self.magnet_on {
                    self.on_since_ms = now_ms;
                }
                self.magnet_on = on;
                format!("OK MAGNET{}", self.state(now_ms))
            }
            _ if first == "PING" => match line.strip_prefix("PING ") {
                Some(t) if valid_token(t) => format!("OK PONG {t}"),
                _ => "ERR bad-argument".to_owned(),
            },
            _ if first == "HOLD" => {
                let s = line.strip_prefix("HOLD ").and_then(parse_seconds);
                match s {
                    Some(s) if (HOLD_RANGE_S.0..=HOLD_RANGE_S.1).contains(&s) => {
                        self.hold_max_ms = u32::from(s) * 1000;
                        format!("OK HOLD hold_max_ms={}", self.hold_max_ms)
                    }
                    _ => "ERR bad-argument".to_owned(),
                }
            }
            "LED ON" | "LED OFF" => {
                self.led_on = line == "LED ON";
                format!(
                    "OK LED led={} uptime_ms={}",
                    if self.led_on { "on" } else { "off" },
                    now_ms.saturating_sub(self.boot_ms)
                )
            }
            _ if first == "MAGNET" || first == "LED" => "ERR bad-argument".to_owned(),
            _ => "ERR unknown-command".to_owned(),
        }
    }
}

fn valid_token(t: &str) -> bool {
    !t.is_empty()
        && t.len() <= TOKEN_MAX
        && t.bytes()
            .all(|c| c.is_ascii_alphanumeric() || c == b'-' || c == b'_')
}

/// 1..4 decimal digits, as the firmware parses them.
fn parse_seconds(s: &str) -> Option<u16> {
    if s.is_empty() || s.len() > 4 || !s.bytes().all(|c| c.is_ascii_digit()) {
        return None;
    }
    s.parse().ok()
}
