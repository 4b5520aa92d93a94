#![doc = include_str!("README.md")]

pub mod control_side;
pub mod fri_step;
pub mod loop_step;
mod measured;
pub(crate) mod replay;
#[cfg(all(feature = "opencv", feature = "serial"))]
pub mod runtime;
pub mod stand;
pub mod step;
pub mod trial;
pub mod truth;
#[cfg(feature = "opencv")]
pub mod vision;

pub use control_side::LabError;
pub use fri_step::FriLoopStep;
pub use loop_step::LoopStep;
#[cfg(all(feature = "opencv", feature = "serial"))]
pub use runtime::{
    CameraFactory, CameraLink, CameraSetup, FriLink, IoStats, LabRuntime, LabSetup, LatencyUs,
    LoopReport, MagnetFactory, MagnetLink, RobotFactory, RobotLoopCounts, RuntimeError,
    SimulatedCamera, SimulatedRobot, SourceFactory,
};
pub use stand::Stand;
pub use step::{
    AFTER_DONE_S, CameraBasis, CameraModel, LabClock, LabStep, TRIAL_TIMEOUT_S, TrialOutcome, Truth,
};
pub use trial::{TrialDraw, draw_trial};
pub use truth::{PhysicalJudgeError, PhysicalVerdict, TrialStart, TruthObserver};
#[cfg(feature = "opencv")]
pub use vision::{
    LedFeed, LedReading, LedTap, Still, StillSlot, VideoParams, VideoStats, VisionLoop, VisionParts,
};
