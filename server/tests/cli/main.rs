//! The `isochron` binary as a user runs it, one test binary (issue #34): a
//! module per command (`basics`: version, scenario check, serve's refusals
//! and SIGTERM; `calibrate`, `envelope`, `kin`, `tune`).

use std::process::Command;

mod basics;
mod calibrate;
mod envelope;
mod kin;
mod tune;

/// The `isochron` binary this package builds.
fn isochron() -> Command {
    Command::new(env!("CARGO_BIN_EXE_isochron"))
}
