//! The magnet in the virtual-time lab: the firmware model
//! ([`crate::sim::magnet::firmware::FirmwareModel`]) stepped in virtual time behind a
//! simulated serial line.
//!
//! A command is written by the host (the `isochron-magnet` thread) after a
//! wake-up delay drawn uniformly from `0..HOST_WRITE_DELAY_MAX_S`; its bytes
//! reach the board at 115200 baud, 10 bits per byte (8N1); the firmware
//! switches the coil when the line's `\n` arrives, before it answers. So
//! `MAGNET OFF\n` (11 bytes) drops the ball 0.95 ms plus the wake-up delay after
//! the lab decided to release, and the driver's release hook reports exactly
//! that pin time (write time plus the bytes' transmission time), which is what
//! the controller is told. The decay of the coil's field is not modelled.

use rand::{Rng, RngExt};

use super::firmware::FirmwareModel;
use crate::magnet::protocol::{Line, OkReply, ResetCause, parse_line};

/// Serial speed of the board, baud.
pub const BAUD: f64 = 115_200.0;
/// Bits on the wire per byte (8N1).
pub const BITS_PER_BYTE: f64 = 10.0;
/// Largest host-side delay before a command's first byte is written, seconds.
pub const HOST_WRITE_DELAY_MAX_S: f64 = 0.001;

/// One switch of the coil.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Switch {
    /// When the host decided (called [`VirtualMagnet::switch`]), seconds.
    pub t_decided_s: f64,
    /// When the command's first byte was written, seconds.
    pub t_written_s: f64,
    /// When the coil's pin switched (the line's last byte arrived), seconds.
    pub t_pin_s: f64,
}

impl Switch {
    /// Decided -> pin switched, seconds.
    pub fn latency_s(&self) -> f64 {
        self.t_pin_s - self.t_decided_s
    }
}

/// The magnet's board behind a simulated serial line, in virtual time.
#[derive(Debug, Clone)]
pub struct VirtualMagnet {
    fw: FirmwareModel,
    out: Vec<u8>,
    /// Switches made.
    pub switches: u64,
}

fn ms(t_s: f64) -> u64 {
    (t_s.max(0.0) * 1e3) as u64
}

impl VirtualMagnet {
    /// A board powered on at `t_s` (coil off).
    pub fn new(t_s: f64) -> Self {
        let mut out = Vec::with_capacity(256);
        let fw = FirmwareModel::boot(ms(t_s), ResetCause::Power, &mut out);
        out.clear();
        Self {
            fw,
            out,
            switches: 0,
        }
    }

    /// Whether the coil is on.
    pub fn is_on(&self) -> bool {
        self.fw.magnet_on()
    }

    /// The host decides at `t_s` to switch the coil `on` or off: the command
    /// goes over the line (delays drawn from `rng`), the firmware switches and
    /// answers. Errors carry the device's answer when it is not the expected
    /// `OK MAGNET` with the asked state.
    ///
    /// # Errors
    ///
    /// A message with the board's answer when it does not confirm the asked state
    /// with `OK MAGNET` (or the coil is not in it).
    pub fn switch<R: Rng>(&mut self, t_s: f64, on: bool, rng: &mut R) -> Result<Switch, String> {
        let t_written_s = t_s + rng.random_range(0.0..HOST_WRITE_DELAY_MAX_S);
        let line: &[u8] = if on { b"MAGNET ON\n" } else { b"MAGNET OFF\n" };
        self.out.clear();
        self.fw.tick(ms(t_written_s), &mut self.out);
        self.out.clear();
        let byte_s = BITS_PER_BYTE / BAUD;
        let mut t_pin_s = t_written_s;
        for (i, b) in line.iter().enumerate() {
            t_pin_s = t_written_s + (i + 1) as f64 * byte_s;
            self.fw.feed(*b, ms(t_pin_s), &mut self.out);
        }
        let answer = String::from_utf8_lossy(&self.out).trim_end().to_owned();
        let confirmed = answer
            .lines()
            .any(|l| matches!(parse_line(l), Line::Ok(OkReply::Magnet(s)) if s.magnet_on == on));
        if !confirmed || self.fw.magnet_on() != on {
            return Err(format!(
                "magnet: asked {}, the board answered {answer:?}",
                if on { "on" } else { "off" }
            ));
        }
        self.switches += 1;
        Ok(Switch {
            t_decided_s: t_s,
            t_written_s,
            t_pin_s,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn a_release_takes_the_line_time_after_the_host_wakes_up() {
        let mut m = VirtualMagnet::new(0.0);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        assert!(!m.is_on());
        let on = m.switch(1.0, true, &mut rng).unwrap();
        assert!(m.is_on());
        // 10 bytes at 115200 baud after the write.
        assert!((on.t_pin_s - on.t_written_s - 10.0 * 10.0 / 115_200.0).abs() < 1e-12);
        let off = m.switch(5.0, false, &mut rng).unwrap();
        assert!(!m.is_on());
        let line_s = 11.0 * 10.0 / 115_200.0;
        assert!((off.t_pin_s - off.t_written_s - line_s).abs() < 1e-12);
        assert!(off.latency_s() >= line_s && off.latency_s() < line_s + HOST_WRITE_DELAY_MAX_S);
        assert_eq!(m.switches, 2);
        // The same seed gives the same delays.
        let mut again = VirtualMagnet::new(0.0);
        let mut rng2 = ChaCha8Rng::seed_from_u64(1);
        again.switch(1.0, true, &mut rng2).unwrap();
        assert_eq!(again.switch(5.0, false, &mut rng2).unwrap(), off);
    }
}
