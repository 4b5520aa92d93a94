//! The `isochron` subcommands, one file each.

pub mod bench;
pub mod trials;
pub mod kin;
pub mod tune;
