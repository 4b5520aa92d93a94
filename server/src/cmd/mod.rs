//! The `isochron` subcommands, one file each.

pub mod tune;
