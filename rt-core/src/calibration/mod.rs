#![doc = include_str!("README.md")]

pub mod contact;
pub mod extrinsics;
pub mod file;
pub mod intrinsics;
pub mod latency;
pub mod lsq;
#[cfg(feature = "opencv")]
pub mod marker;
#[cfg(feature = "opencv")]
pub mod procedure;
pub mod robot;
// The fits' synthetic data for their unit tests: a hidden draw around the
// beliefs, simple simulators. No step of a lab runs on it: `isochron
// calibrate` and the service run every step on `sim::world` behind a real
// lab's interfaces.
#[cfg(all(test, feature = "opencv"))]
mod sim_extrinsics;
#[cfg(all(test, feature = "opencv"))]
mod sim_intrinsics;
#[cfg(all(test, feature = "opencv"))]
mod simworld;
pub mod swing;
pub mod view;

#[cfg(test)]
mod tests;

pub use contact::{ContactCalibration, KnockRecording, fit_knock};
pub use extrinsics::CameraRobotCalibration;
pub use file::{CalibrationFile, StepRecord};
pub use intrinsics::{BoardView, CameraCalibration, Chessboard};
#[cfg(feature = "opencv")]
pub use intrinsics::{detect_corners, fit_intrinsics};
pub use latency::{LedEdge, LedLatency, estimate_led_latency};
pub use robot::{RobotLatency, fit_robot_latency};
pub use swing::{SwingFit, SwingSample, fit_swing};
pub use view::{StepView, Unwatched, ViewKind, Watch};

/// Why a calibration step could not give a result (nothing is written then).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum CalibrationError {
    /// Too few usable samples.
    #[error("{what}: {got} usable samples, at least {need} needed")]
    TooFewSamples {
        /// What was being measured.
        what: &'static str,
        /// Samples there were.
        got: usize,
        /// Samples needed.
        need: usize,
    },
    /// The swing is too small to fit its period and decay.
    #[error(
        "swing too small: amplitude {amplitude_m:.4} m, at least {min_m:.3} m needed (release the ball from a larger angle)"
    )]
    SwingTooSmall {
        /// Measured half peak-to-peak amplitude, metres.
        amplitude_m: f64,
        /// Smallest accepted amplitude, metres.
        min_m: f64,
    },
    /// The recording is too short.
    #[error("{what}: {got_s:.2} s recorded, at least {need_s:.2} s needed")]
    TooShort {
        /// What was being measured.
        what: &'static str,
        /// Duration recorded, seconds.
        got_s: f64,
        /// Duration needed, seconds.
        need_s: f64,
    },
    /// A sample is NaN or infinite.
    #[error("{what}: sample {index} is not finite")]
    NotFinite {
        /// What was being measured.
        what: &'static str,
        /// Index of the bad sample.
        index: usize,
    },
    /// The LED was never seen switching.
    #[error(
        "LED never seen: {edges} switchings commanded, {seen} seen by the camera (is the LED in view and the magnet board connected?)"
    )]
    LedNotSeen {
        /// Switchings commanded.
        edges: usize,
        /// Switchings seen.
        seen: usize,
    },
    /// The fitted free swing leaves residuals no free pendulum seen by a
    /// camera has: the ball was touched, hidden, or mistaken.
    #[error(
        "{what}: the samples do not follow a free swing: residual {residual_m:.4} m RMS over an amplitude of \
         {amplitude_m:.3} m, at most {limit_share:.0}% of it accepted (was the ball touched, held or hidden?)",
        limit_share = 100.0 * .limit_share
    )]
    PoorFit {
        /// What was being fitted.
        what: &'static str,
        /// Root mean square of the residuals, metres.
        residual_m: f64,
        /// The swing's half peak-to-peak amplitude, metres.
        amplitude_m: f64,
        /// The largest residual accepted, as a share of the amplitude.
        limit_share: f64,
    },
    /// The camera's frames arrive too irregularly to give them their capture
    /// slots by their delivery times.
    #[error(
        "the camera's frames arrive too irregularly to time {what}: they come {spread_ms:.1} ms \
         apart from their grid (standard deviation) against a frame period of {period_ms:.1} ms, \
         at most {limit_ms:.1} ms usable (a busy host or network: calibrate when it is quieter)"
    )]
    IrregularFrames {
        /// What was being timed.
        what: &'static str,
        /// Standard deviation of the frames' lateness, ms.
        spread_ms: f64,
        /// The measured frame period, ms.
        period_ms: f64,
        /// The largest spread accepted, ms.
        limit_ms: f64,
    },
    /// Too few of the camera's frames came on time to stamp them.
    #[error(
        "the camera's frames arrive too irregularly to time {what}: {late} of {frames} came over \
         half a frame period ({period_ms:.1} ms) after their slot (a busy host or network: \
         calibrate when it is quieter)"
    )]
    LateFrames {
        /// What was being timed.
        what: &'static str,
        /// Frames late.
        late: usize,
        /// Frames in all.
        frames: usize,
        /// The measured frame period, ms.
        period_ms: f64,
    },
    /// The least-squares fit did not converge or gave a non-physical result.
    #[error("{what}: fit failed: {reason}")]
    FitFailed {
        /// What was being fitted.
        what: &'static str,
        /// Why.
        reason: String,
    },
    /// The chessboard was found in no frame.
    #[error(
        "no board visible: the {inner_cols}x{inner_rows} chessboard (inner corners) was found in none of {shown} frames \
         (is it in view, whole, lit, and is its pattern size right?)"
    )]
    BoardNotSeen {
        /// Frames the board was looked for in.
        shown: usize,
        /// The board's inner corners along a row.
        inner_cols: u32,
        /// The board's inner corners along a column.
        inner_rows: u32,
    },
    /// The knock's two contacts (the tool meeting the hanging ball, the
    /// ball swinging back to the stopped tool) were not both seen.
    #[error(
        "contact (knock): {seen} of the 2 contacts seen in the external joint torques (did the tool \
         meet the hanging ball, and did the ball swing back to it?)"
    )]
    ContactNotSeen {
        /// Contacts seen.
        seen: usize,
    },
    /// The excitation did not move the joint enough to fit.
    #[error(
        "robot excitation not seen: the measured joint moved {moved_rad:.5} rad, at least {min_rad:.5} rad needed"
    )]
    NoResponse {
        /// Peak-to-peak measured motion, radians.
        moved_rad: f64,
        /// Needed, radians.
        min_rad: f64,
    },
}
