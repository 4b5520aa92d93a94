//! The simulated magnet: the firmware's model ([`FirmwareModel`]), the fake
//! board behind a pseudo-terminal ([`FakeDevice`], real time: the real driver
//! talks to it) and the virtual-time serial line ([`VirtualMagnet`]).

#[cfg(feature = "serial")]
pub mod fake;
pub mod firmware;
pub mod line;

#[cfg(feature = "serial")]
pub use fake::FakeDevice;
pub use firmware::FirmwareModel;
pub use line::{BAUD, BITS_PER_BYTE, HOST_WRITE_DELAY_MAX_S, Switch, VirtualMagnet};
