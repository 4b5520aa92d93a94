//! The simulated KUKA controller: the robot side of FRI 1.11 to 2.7 (`fri_version`; [`SimController`],
//! stepped by its caller: virtual time) and its UDP server ([`SimServer`],
//! thread `isochron-fri-sim`, or `isochron fri-sim`). It speaks to the real
//! FRI client (`crate::fri`) through the real codec.

pub mod controller;
pub mod server;

pub use controller::{CommandingAbort, FriSimParams, SimController, SimReport, SimStats};
pub use server::{SimError, SimRunOptions, SimServer};
