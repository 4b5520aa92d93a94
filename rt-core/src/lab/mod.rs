#![doc = include_str!("README.md")]

pub mod fri_step;
pub mod lifecycle;
pub mod loop_step;
mod measured;
mod replay;
#[cfg(all(feature = "opencv", feature = "serial"))]
pub mod runtime;
pub mod step;
pub mod trial;
pub mod truth;
pub mod virtual_time;
#[cfg(feature = "opencv")]
pub mod vision;

pub use fri_step::FriLoopStep;
pub use loop_step::LoopStep;
#[cfg(all(feature = "opencv", feature = "serial"))]
pub use runtime::{
    CameraLink, FriLink, IoStats, LabRuntime, LabSetup, LatencyUs, LoopReport, MagnetLink,
    RuntimeError, SourceFactory, run_loop,
};
pub use step::{AFTER_DONE_S, LabClock, LabStep, TRIAL_TIMEOUT_S, TrialOutcome};
pub use trial::{TrialDraw, draw_trial};
pub use truth::{PhysicalJudgeError, PhysicalVerdict, TrialStart, TruthObserver};
pub use virtual_time::{INITIAL_JOINTS_DEG, LOOPBACK_NS, LabError, VirtualLab, robot_params};
#[cfg(feature = "opencv")]
pub use vision::{VideoParams, VideoStats, VisionLoop, VisionParts};
