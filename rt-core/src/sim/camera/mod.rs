//! The simulated camera: the measurement model ([`ModelCamera`]) and the
//! rendered camera ([`SimCamera`]: frames drawn from the true ball and run
//! through the real OpenCV detector by [`SimVision`]; [`SimCameraSource`] is
//! the same camera as a real-time frame source).

pub mod model;
pub mod render;

pub use model::{ModelCamera, gaussian};
pub use render::{BallState, SimCamera, SimCameraParams, SimCameraSource, SimVision};
