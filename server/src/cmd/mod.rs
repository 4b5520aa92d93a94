//! The `isochron` subcommands, one file each.

pub mod bench;
pub mod bench_peers;
pub mod calibrate;
pub mod detect;
pub mod eval;
pub mod eval_envelope;
pub mod eval_reality;
pub mod fri_doctor;
pub mod fri_sim;
pub mod kin;
pub mod magnet;
pub mod merge;
pub mod trials;
pub mod tune;
pub mod world;
