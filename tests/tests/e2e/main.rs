//! The end-to-end tests: one test binary (issue #34), one module per part of
//! the lab. One binary is linked once after a change in the core, and the
//! harness spreads every module's tests over the cores together instead of
//! running 21 binaries one after another.
//!
//! What needs a process of its own stays out: the allocation counter
//! (`rt-core/tests/control_step_no_alloc.rs`, a global allocator) and the
//! real-time priority checks (`rt-core/tests/rt_tuning.rs`); and the lab
//! against `isochron world` (`tests/tests/world`), which needs the machine's
//! two cores to itself. `make test` runs these one at a time
//! (`TEST_THREADS`): side by side they starved each other's simulated boards.

mod calibration_moves;
mod closed_loop_trials;
mod dead_man;
mod demo_mode;
mod eval_matches_trials;
mod foxglove;
mod fri_doctor;
mod fri_session;
mod fri_sim_cli;
mod fri_versions;
mod http_api;
mod http_basics;
mod http_calibration;
mod http_support;
mod http_trials_sim;
mod lifecycle_served;
mod magnet_firmware;
mod real_lab_wired;
mod serve_real_lab;
mod shard_merge;
mod tune_roundtrip;
mod vision_video;
mod ws_stream;
