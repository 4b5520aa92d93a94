//! The `isochron` subcommands, one file each.

pub mod trials;
pub mod tune;
