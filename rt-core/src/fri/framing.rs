//! FRI 2.7 framing: `length (u32 LE) | protobuf message | CRC-32 (u32 LE)`.
//!
//! The CRC is the zlib/IEEE CRC-32 (reflected polynomial `0xEDB88320`, initial
//! value and final XOR `0xFFFFFFFF`) of the protobuf bytes only. A datagram
//! whose length field does not match its size, or whose CRC does not match its
//! message, is refused before any protobuf decoding. No allocation.

/// Bytes the framing adds: 4 of length, 4 of CRC.
pub const FRAME_OVERHEAD: usize = 8;

/// The zlib CRC-32 of `bytes` (`crc32(b"123456789") == 0xCBF43926`), by
/// `crc32fast` (no allocation).
///
/// ```
/// assert_eq!(rt_core::fri::framing::crc32(b"123456789"), 0xCBF4_3926);
/// ```
pub fn crc32(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

/// Why a framed datagram was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// The length field does not match the datagram's size.
    #[error("frame length field says {declared} bytes, the datagram carries {available}")]
    Length {
        /// The length field.
        declared: u64,
        /// Bytes between the length field and the CRC.
        available: usize,
    },
    /// The CRC-32 does not match the message bytes.
    #[error("CRC-32 mismatch: frame says {got:#010x}, message has {computed:#010x}")]
    Crc {
        /// The CRC in the frame.
        got: u32,
        /// The CRC of the message bytes.
        computed: u32,
    },
}

/// The protobuf message inside a framed datagram, after checking its length and CRC.
///
/// # Errors
///
/// [`FrameError::Length`] when the datagram is shorter than a frame or its length
/// field does not match; [`FrameError::Crc`] when the CRC-32 does not match.
pub fn unframe(datagram: &[u8]) -> Result<&[u8], FrameError> {
    if datagram.len() < FRAME_OVERHEAD {
        return Err(FrameError::Length {
            declared: 0,
            available: datagram.len().saturating_sub(FRAME_OVERHEAD),
        });
    }
    let (len_bytes, rest) = datagram.split_at(4);
    let declared = u32::from_le_bytes([len_bytes[0], len_bytes[1], len_bytes[2], len_bytes[3]]);
    let available = rest.len() - 4;
    if declared as usize != available {
        return Err(FrameError::Length {
            declared: u64::from(declared),
            available,
        });
    }
    let (msg, crc_bytes) = rest.split_at(available);
    let got = u32::from_le_bytes([crc_bytes[0], crc_bytes[1], crc_bytes[2], crc_bytes[3]]);
    let computed = crc32(msg);
    if got != computed {
        return Err(FrameError::Crc { got, computed });
    }
    Ok(msg)
}

/// Frames the `msg_len` message bytes that start at `buf[4]`: writes the length
/// into `buf[..4]` and the CRC after the message; returns the datagram's size,
/// or `None` when `buf` is too small.
pub fn frame_in_place(buf: &mut [u8], msg_len: usize) -> Option<usize> {
    let total = msg_len.checked_add(FRAME_OVERHEAD)?;
    if total > buf.len() {
        return None;
    }
    let len = u32::try_from(msg_len).ok()?;
    buf[..4].copy_from_slice(&len.to_le_bytes());
    let crc = crc32(&buf[4..4 + msg_len]);
    buf[4 + msg_len..total].copy_from_slice(&crc.to_le_bytes());
    Some(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_is_zlibs() {
        // The standard check value of CRC-32/ISO-HDLC (zlib, PNG, Ethernet).
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
        assert_eq!(crc32(b"a"), 0xE8B7_BE43);
    }

    #[test]
    fn frames_round_trip_and_any_single_bit_flip_is_refused() {
        let msg = [0x0a, 0x08, 0x08, 0x81, 0x80, 0x0d, 0x10, 0x01, 0x18, 0x02];
        let mut buf = [0u8; 64];
        buf[4..4 + msg.len()].copy_from_slice(&msg);
        let n = frame_in_place(&mut buf, msg.len()).unwrap();
        assert_eq!(n, msg.len() + 8);
        assert_eq!(&buf[..4], &[10, 0, 0, 0]);
        assert_eq!(unframe(&buf[..n]), Ok(&msg[..]));
        for bit in 0..n * 8 {
            let mut d = buf;
            d[bit / 8] ^= 1 << (bit % 8);
            assert!(unframe(&d[..n]).is_err(), "bit {bit} flipped was accepted");
        }
        assert!(matches!(
            unframe(&buf[..n - 1]),
            Err(FrameError::Length { .. })
        ));
        assert!(matches!(unframe(&buf[..3]), Err(FrameError::Length { .. })));
    }
}
