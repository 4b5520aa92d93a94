#![doc = include_str!("README.md")]

pub mod fri_step;
pub mod loop_step;
pub mod runtime;
mod step;
pub mod trial;
pub mod vision;

pub use fri_step::FriLoopStep;
pub use loop_step::LoopStep;
pub use runtime::{
    CameraLink, FRI_PRIORITY, FriLink, IoStats, LabRuntime, LabSetup, LatencyUs, LoopReport,
    MagnetLink, RuntimeError, SourceFactory, raise_fri_priority, run_loop,
};
pub use step::LabStep;
pub use trial::{TrialDraw, draw_trial};
pub use vision::{TruthUpdate, TruthView, VideoParams, VideoStats, VisionLoop, VisionParts};
