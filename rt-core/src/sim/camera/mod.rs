//! The simulated camera: the measurement model ([`ModelCamera`]) and the
//! rendered camera (`SimCamera`: frames drawn from the true ball and run
//! through the real OpenCV detector by `SimVision`; `SimCameraSource` is
//! the same camera as a real-time frame source; feature `opencv`).

pub mod geometry;
pub mod model;
#[cfg(feature = "opencv")]
pub mod render;

pub use geometry::{BallState, SimCameraParams};
pub use model::{ModelCamera, gaussian};
#[cfg(feature = "opencv")]
pub use render::{
    EdgeScene, ImageBall, Lookalike, SimCamera, SimCameraSource, SimVision, tool_occluder,
};
