//! FRI versions and what differs between them on the wire (FRI.md; KUKA's
//! published client SDKs 1.11, 1.14, 1.15, 1.16, 2.5, 2.7).
//!
//! | Version | Framing | Monitoring message | Command message |
//! |---|---|---|---|
//! | 1.11 | bare protobuf | no IO values (monitorData 8) | no IO values (commandData 5) |
//! | 1.14, 1.15, 1.16 | bare protobuf | the FRI.md table | the FRI.md table |
//! | 2.5 | bare protobuf | no commandedJointPosition (monitorData 3); Cartesian pose and redundancy (monitorData 9, 10; ipoData 2, 3); transformations are 7-value quaternions | cartesianPose 6, redundancyInformation 7 |
//! | 2.7 | 4-byte LE length + protobuf + 4-byte LE CRC-32 (zlib) of the protobuf | as 2.5, plus externalForce (monitorData 6), no endOfMessageData (15) | as 2.5, no endOfMessageData (15) |
//!
//! Identifiers (`0x245142`, `0x34001`), 7 joints and the 1500-byte datagram
//! are the same in all. `ClientCommandMode` 1 is POSITION up to 1.16 and
//! JOINT_POSITION from 2.5 (same value); CARTESIAN_POSE (4) exists from 2.5.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// An FRI version whose wire format isochron reads and writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub enum FriVersion {
    /// FRI 1.11 (no IO values).
    V1_11,
    /// FRI 1.14.
    V1_14,
    /// FRI 1.15 (the default).
    #[default]
    V1_15,
    /// FRI 1.16.
    V1_16,
    /// FRI 2.5 (quaternion transformations, no commanded joint positions).
    V2_5,
    /// FRI 2.7 (2.5 plus length + CRC-32 framing and external force).
    V2_7,
}

impl FriVersion {
    /// Every version, oldest first.
    pub const ALL: [Self; 6] = [
        Self::V1_11,
        Self::V1_14,
        Self::V1_15,
        Self::V1_16,
        Self::V2_5,
        Self::V2_7,
    ];

    /// `"1.15"`.
    pub const fn name(self) -> &'static str {
        match self {
            Self::V1_11 => "1.11",
            Self::V1_14 => "1.14",
            Self::V1_15 => "1.15",
            Self::V1_16 => "1.16",
            Self::V2_5 => "2.5",
            Self::V2_7 => "2.7",
        }
    }

    /// True from 2.7: every datagram is `len (u32 LE) | protobuf | crc32 (u32 LE)`.
    pub const fn framed(self) -> bool {
        matches!(self, Self::V2_7)
    }

    /// True up to 1.16: the monitoring message carries `commandedJointPosition`
    /// (monitorData field 3).
    pub const fn has_commanded_joint_position(self) -> bool {
        !self.is_2x()
    }

    /// True from 1.14: IO values (monitorData 8, commandData 5).
    pub const fn has_io(self) -> bool {
        !matches!(self, Self::V1_11)
    }

    /// True from 2.7: `monitorData.externalForce` (field 6, 6 values).
    pub const fn has_external_force(self) -> bool {
        matches!(self, Self::V2_7)
    }

    /// True up to 2.5: `endOfMessageData` (field 15 of both messages).
    pub const fn has_end_of_message(self) -> bool {
        !matches!(self, Self::V2_7)
    }

    /// True from 2.5: 2.x schema (quaternion transformations, Cartesian pose,
    /// redundancy information, JOINT_POSITION).
    pub const fn is_2x(self) -> bool {
        matches!(self, Self::V2_5 | Self::V2_7)
    }

    /// Values of one transformation: 12 (3x4 matrix) in 1.x, 7 (position +
    /// quaternion) in 2.x.
    pub const fn transformation_values(self) -> usize {
        if self.is_2x() { 7 } else { 12 }
    }

    /// The name of `ClientCommandMode` 1 in this version.
    pub const fn joint_position_mode_name(self) -> &'static str {
        if self.is_2x() {
            "JOINT_POSITION"
        } else {
            "POSITION"
        }
    }

    /// Largest `ClientCommandMode` value this version defines.
    pub const fn max_client_command_mode(self) -> i32 {
        if self.is_2x() { 4 } else { 3 }
    }

    /// A short plain description of the wire format.
    pub const fn wire_summary(self) -> &'static str {
        match self {
            Self::V1_11 => "bare protobuf, FRI 1.x fields without IO values",
            Self::V1_14 | Self::V1_15 | Self::V1_16 => {
                "bare protobuf, FRI 1.x fields (commandedJointPosition, 3x4 transformations)"
            }
            Self::V2_5 => {
                "bare protobuf, FRI 2.x fields (no commandedJointPosition, quaternion transformations)"
            }
            Self::V2_7 => {
                "4-byte length + protobuf + CRC-32, FRI 2.x fields with externalForce, no endOfMessageData"
            }
        }
    }
}

impl fmt::Display for FriVersion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// An FRI version isochron does not know.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown FRI version {0:?}: expected one of 1.11, 1.14, 1.15, 1.16, 2.5, 2.7")]
pub struct UnknownVersion(pub String);

impl FromStr for FriVersion {
    type Err = UnknownVersion;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|v| v.name() == s.trim())
            .ok_or_else(|| UnknownVersion(s.to_owned()))
    }
}

impl Serialize for FriVersion {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for FriVersion {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_versions_are_refused() {
        for v in FriVersion::ALL {
            assert_eq!(v.name().parse::<FriVersion>(), Ok(v));
        }
        assert_eq!(FriVersion::default(), FriVersion::V1_15);
        for bad in ["1.12", "2.0", "3", "", "1.15.1"] {
            assert!(bad.parse::<FriVersion>().is_err(), "{bad}");
        }
    }
}
