//! The control side of a lab: the FRI client session and the trial driver
//! around the controller, with the other ends of its rings, built from the
//! scenario's beliefs alone. The virtual-clock lab (`sim/virtual_lab.rs`)
//! steps it between its simulators; the replay (`replay.rs`) feeds it a
//! recorded run's inputs with no world behind it.

use crate::fri::proto::SessionState;
use rtrb::{Consumer, Producer};

use super::step::{IoReply, IoRequest, LabClock, LabParts, LabStep, MagnetNote, Truth};
use crate::bridge::{self, ServerEnd};
use crate::control::{ControlError, Controller};
use crate::fri::client::{FriClient, FriClientParams};
use crate::params::Scenario;
use crate::vision::{Measurement, SwingPlaneCalibration};

/// Errors setting up the lab.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LabError {
    /// The controller refused its parameters.
    #[error(transparent)]
    Control(#[from] ControlError),
    /// The simulated robot refused its parameters.
    #[error("simulated robot: {0}")]
    Robot(#[source] crate::check::ParamError),
    /// The simulated robot's FRI session did not reach COMMANDING_ACTIVE in time.
    #[error(
        "simulated robot: the FRI session did not reach COMMANDING_ACTIVE within {timeout_s} s \
         (controller {}, quality {})",
        controller.name(),
        quality.name()
    )]
    NotCommanding {
        /// How long it was given, seconds (virtual time).
        timeout_s: f64,
        /// The simulated controller's session state then.
        controller: SessionState,
        /// Its connection quality then.
        quality: crate::fri::proto::ConnectionQuality,
    },
    /// The simulated camera could not start.
    #[error("simulated camera: {0}")]
    Camera(#[source] crate::vision::VisionError),
    /// The detector of the rendered frames could not start.
    #[error("simulated camera: vision: {0}")]
    Vision(#[source] crate::vision::VisionError),
    /// `camera.vision = "full"` in a build without OpenCV.
    #[error(
        "simulated camera: camera.vision = \"full\" renders frames through the OpenCV detector: \
         this build has no `opencv` feature (use vision = \"model\")"
    )]
    NoOpenCv,
}

/// The control side of a lab: what the real lab runs on its FRI thread (the
/// FRI client session and the trial driver around the controller), with the
/// other ends of its rings (the operator's bridge, the camera's
/// measurements, the magnet's notes, `isochron-lab-io`'s requests and
/// replies). Built from the scenario's beliefs; `truth`: the simulated world
/// the driver follows and judges on (`None`: none, as in the real lab).
pub(crate) struct ControlSide {
    pub client: FriClient,
    pub step: LabStep,
    pub server: ServerEnd,
    pub measurements: Producer<Measurement>,
    pub notes: Producer<MagnetNote>,
    pub io_requests: Consumer<IoRequest>,
    pub io_replies: Producer<IoReply>,
}

impl ControlSide {
    pub(crate) fn new(
        scenario: &Scenario,
        seed: u64,
        period_s: f64,
        calibration: SwingPlaneCalibration,
        truth: Option<Truth>,
    ) -> Result<Self, LabError> {
        // The controller is built from the beliefs only: it never holds
        // `[world]`. Every believed section is checked, `[camera]` and
        // `[success]` too (the controller checks only those it reads).
        scenario.validate_but_world().map_err(ControlError::from)?;
        let controller = Controller::new(&scenario.beliefs(), period_s)?;
        let client = FriClient::new(FriClientParams::default()).map_err(LabError::Robot)?;
        let (control, server) = bridge::bridge(bridge::BridgeCapacity::default());
        let (meas_tx, meas_rx) = crate::vision::measurement_ring(64);
        let (note_tx, note_rx) = rtrb::RingBuffer::<MagnetNote>::new(64);
        let (req_tx, req_rx) = rtrb::RingBuffer::<IoRequest>::new(16);
        let (reply_tx, reply_rx) = rtrb::RingBuffer::<IoReply>::new(16);
        let cell = std::sync::Arc::new(std::sync::OnceLock::new());
        let _ = cell.set(client.stats().clone());
        let step = LabStep::new(
            controller,
            LabParts {
                scenario: Box::new(scenario.clone()),
                seed,
                fixed_distance_m: None,
                bridge: control,
                clock: LabClock::Virtual,
                measurements: meas_rx,
                magnet_notes: note_rx,
                io_requests: req_tx,
                io_replies: reply_rx,
                #[cfg(feature = "serial")]
                magnet: None,
                session: cell,
                truth,
                calibration,
                // No operator in virtual time: no dead-man.
                operator_timeout_s: None,
                stamp_latency: None,
                real_plane: None,
                // Virtual time: a camera is never lost.
                camera_lost_after_s: super::step::CAMERA_LOST_AFTER_S,
                stand: None,
            },
        );
        Ok(Self {
            client,
            step,
            server,
            measurements: meas_tx,
            notes: note_tx,
            io_requests: req_rx,
            io_replies: reply_tx,
        })
    }
}
