//! Why a calibration procedure could not run or give a result (the fits'
//! refusals, the camera's and the robot's failures).

use super::CalibrationError;
use crate::params::ParamError;
use crate::vision::VisionError;

/// Why a procedure could not run or give a result.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ProcedureError {
    /// The fit refused the data.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// The scenario is not valid.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The camera or detector failed.
    #[error("camera: {0}")]
    Vision(#[from] VisionError),
    /// The simulated pendulum refused a time or a state.
    #[error(transparent)]
    Pendulum(#[from] crate::pendulum::SimError),
    /// More board views asked for than the step takes.
    #[error("{views} board views asked for: must be 1..=200")]
    Views {
        /// The number asked for.
        views: usize,
    },
    /// The hanging ball was found in too few frames.
    #[error("the hanging ball was found in {found} of {frames} frames (is it in view?)")]
    BallNotFound {
        /// Frames it was found in.
        found: usize,
        /// Frames looked at.
        frames: usize,
    },
    /// The hanging ball projects outside the image.
    #[error("the hanging ball is not in the camera's view")]
    BallOutOfView,
    /// The camera ray through the rest pixel does not meet the swing plane.
    #[error("the rest point's ray misses the swing plane")]
    RayMissesSwingPlane,
    /// The camera ray through the rest pixel does not reach the plane of the
    /// ball's surface (too grazing).
    #[error("the rest point's ray does not reach the ball's plane")]
    RayMissesBallPlane,
    /// The marker on the tool was seen at too few poses.
    #[error("{}", marker_sentence(*seen, *commanded, *needed))]
    MarkerNotSeen {
        /// Poses it was seen at.
        seen: usize,
        /// Poses commanded.
        commanded: usize,
        /// Poses the fit needs.
        needed: usize,
    },
    /// The simulated robot or FRI client refused its parameters.
    #[error("robot: {0}")]
    RobotParams(#[source] ParamError),
    /// Too few of the marker tour's poses are within the joint limits.
    #[error(
        "robot: only {reachable} marker poses reachable inside the joint limits, at least {needed} needed"
    )]
    TooFewPoses {
        /// Reachable poses.
        reachable: usize,
        /// Poses the fit needs.
        needed: usize,
    },
    /// The tool cannot touch the hanging ball within the joint limits.
    #[error("robot: the hanging ball is out of the tool's reach")]
    BallOutOfReach,
    /// The tour's commands would have left the joint limits.
    #[error("robot: a command would have left the joint limits; the tour stopped")]
    TourLeftLimits,
    /// The FRI session left commanding during the step.
    #[error(
        "robot: the FRI session did not stay in COMMANDING_ACTIVE (client {client:?}, controller {})",
        controller.name()
    )]
    LeftCommanding {
        /// The client's link state at the end.
        client: crate::fri::client::LinkState,
        /// The simulated controller's session state at the end.
        controller: crate::fri::proto::SessionState,
    },
    /// The simulated controller aborted commanding.
    #[error("robot: the controller aborted: {0:?}")]
    ControllerAborted(crate::sim::kuka::CommandingAbort),
    /// No joint measurement while the tool touched the ball.
    #[error("robot: no measurement at the touch")]
    NoTouchMeasurement,
    /// An excitation amplitude outside `(0, 0.05]` rad.
    #[error("robot: excitation amplitude {amplitude_rad} rad out of range: must be in (0, 0.05]")]
    Amplitude {
        /// The refused amplitude, radians.
        amplitude_rad: f64,
    },
}

/// [`ProcedureError::MarkerNotSeen`]'s sentence.
fn marker_sentence(seen: usize, commanded: usize, needed: usize) -> String {
    if seen == 0 {
        format!(
            "marker never seen: 0 of {commanded} poses (is the disc on the tool and in the camera's view?)"
        )
    } else {
        format!("marker seen at {seen} of {commanded} poses, at least {needed} needed")
    }
}

impl From<opencv::Error> for ProcedureError {
    fn from(e: opencv::Error) -> Self {
        Self::Vision(VisionError::OpenCv(e))
    }
}
