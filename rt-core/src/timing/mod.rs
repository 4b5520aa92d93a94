#![doc = include_str!("README.md")]

mod dynamics;
pub mod fit;
mod motion;
mod neurons;
mod params;

pub use dynamics::{HopfDrive, SpeedDynamics, SpeedState};
pub use fit::{ArrivalFit, fit_arrival};
pub use motion::{
    MAX_DURATION_S, MAX_STEP_S, MIN_DISTANCE_M, MIN_DURATION_S, MotionPhase, MotionSample,
    REST_SPEED_MPS, TimedMotion,
};
pub use neurons::{Neurons, Regime};
pub use params::TimingParams;

/// A refused call: the motion is unchanged. Carries no heap data, so the
/// real-time step can return it without allocating.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum TimingError {
    /// NaN or an infinity.
    #[error("{what} is not finite")]
    NotFinite {
        /// The argument.
        what: &'static str,
    },
    /// A value outside its allowed range.
    #[error("{what} = {value} is out of range: {bound}")]
    OutOfRange {
        /// The argument.
        what: &'static str,
        /// The refused value.
        value: f64,
        /// The bound it broke.
        bound: &'static str,
    },
    /// The call needs a motion that has begun.
    #[error("no motion is running: call begin() first")]
    NotStarted,
    /// `begin` while a motion runs.
    #[error("a motion is running: retarget or reset it instead of beginning another")]
    Busy,
}

#[cfg(test)]
mod tests;
