//! The end-to-end tests: one test binary (issue #34), one module per part of
//! the lab. One binary is linked once after a change in the core, and the
//! harness spreads every module's tests over the cores together instead of
//! running 22 binaries one after another.
//!
//! What needs a process of its own stays out: the allocation counter
//! (`rt-core/tests/control_step_no_alloc.rs`, a global allocator) and the
//! real-time priority checks (`rt-core/tests/rt_tuning.rs`). The lab
//! processes started here (`isochron serve`, `isochron world`, simavr) are
//! their own processes anyway; tests that need the machine's cores to
//! themselves take [`ONE_LAB`].

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
mod world_lab;
mod ws_stream;

/// One world and its lab at a time: a world renders its camera, runs the
/// cabinet and a simavr board, and two worlds with their labs side by side
/// on a 2-core machine starve each other's camera. (Labs started here run
/// with [`isochron_tests::SHARED_RT`], not spinning on a CPU of their own.)
pub static ONE_LAB: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());
