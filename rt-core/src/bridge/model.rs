//! The shared data model: what the control thread tells the server
//! ([`Snapshot`], [`EventRecord`]) and what the server asks of it ([`Command`],
//! answered by an [`Ack`]).
//!
//! Everything the control thread writes is `Copy` and fixed-size (no heap), so
//! publishing it never allocates.

use serde::{Serialize, Serializer, ser::SerializeSeq};
use ts_rs::TS;
use utoipa::ToSchema;

use crate::kinematics::iiwa7::JOINTS;
use crate::params::Scenario;

/// Points in the predicted horizon of the pendulum ([`PendulumView::horizon`]).
pub const HORIZON_POINTS: usize = 25;

/// Where a trial is: the controller's state machine's state, one type for
/// the controller and the API.
pub use crate::control::{Excitation, TrialState};

/// The last sighting the filter was given ([`crate::control::Sighting`]), as
/// the dashboard shows it.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, TS, ToSchema)]
pub struct MeasurementView {
    /// False until a measurement arrived (then the other fields are meaningless).
    pub valid: bool,
    /// Capture time, control clock, seconds.
    pub t_s: f64,
    /// Lateral ball position x = l sin(phi), metres (+y of the robot base).
    pub x_m: f64,
}

/// One point of the predicted ball trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, TS, ToSchema)]
pub struct HorizonPoint {
    /// Time, control clock, seconds.
    pub t_s: f64,
    /// Predicted lateral position, metres.
    pub x_m: f64,
    /// One standard deviation of `x_m`, metres.
    pub sigma_m: f64,
}

/// The pendulum as measured, estimated and predicted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
pub struct PendulumView {
    /// Last measurement.
    pub measured: MeasurementView,
    /// Where the pendulum hangs now: the robot base axis to the ball at
    /// rest, horizontal, metres (the simulated lab's stand, or a real lab's
    /// fixed distance; null: each trial's own, not known between trials).
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub rest_distance_m: f64,
    /// Estimated angle from the vertical, radians (positive towards +y).
    pub phi_rad: f64,
    /// Estimated angular velocity, rad/s.
    pub dphi_radps: f64,
    /// One standard deviation of `phi_rad`.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub sigma_phi_rad: f64,
    /// One standard deviation of `dphi_radps`.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub sigma_dphi_radps: f64,
    /// Estimated lateral position l sin(phi), metres.
    pub x_m: f64,
    /// One standard deviation of `x_m`, metres.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub sigma_x_m: f64,
    /// Estimated ball centre in the robot base frame, metres.
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub ball_m: [f64; 3],
    /// True ball centre (simulated lab only; NaN, shown as null, otherwise).
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub truth_ball_m: [f64; 3],
    /// Predicted time the ball next crosses the intercept point, seconds (NaN if none).
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub crossing_t_s: f64,
    /// One standard deviation of `crossing_t_s`, seconds.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub crossing_sigma_s: f64,
    /// The predicted horizon; only the first `horizon_len` points are meaningful.
    #[serde(serialize_with = "serialize_horizon", rename = "horizon")]
    #[ts(as = "Vec<HorizonPoint>")]
    #[schema(value_type = Vec<HorizonPoint>)]
    pub horizon: Horizon,
}

/// A fixed-capacity predicted horizon.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Horizon {
    /// Storage; points past `len` are ignored.
    pub points: [HorizonPoint; HORIZON_POINTS],
    /// Number of meaningful points (at most [`HORIZON_POINTS`]).
    pub len: usize,
}

impl Default for Horizon {
    fn default() -> Self {
        Self {
            points: [HorizonPoint::default(); HORIZON_POINTS],
            len: 0,
        }
    }
}

impl Horizon {
    /// The meaningful points.
    pub fn as_slice(&self) -> &[HorizonPoint] {
        &self.points[..self.len.min(HORIZON_POINTS)]
    }

    /// Appends a point; returns false (and changes nothing) when full.
    pub fn push(&mut self, p: HorizonPoint) -> bool {
        match self.points.get_mut(self.len) {
            Some(slot) => {
                *slot = p;
                self.len += 1;
                true
            }
            None => false,
        }
    }
}

fn serialize_horizon<S: Serializer>(h: &Horizon, s: S) -> Result<S::Ok, S::Error> {
    let pts = h.as_slice();
    let mut seq = s.serialize_seq(Some(pts.len()))?;
    for p in pts {
        seq.serialize_element(p)?;
    }
    seq.end()
}

impl Default for PendulumView {
    fn default() -> Self {
        Self {
            measured: MeasurementView::default(),
            rest_distance_m: f64::NAN,
            phi_rad: 0.0,
            dphi_radps: 0.0,
            sigma_phi_rad: f64::NAN,
            sigma_dphi_radps: f64::NAN,
            x_m: 0.0,
            sigma_x_m: f64::NAN,
            ball_m: [f64::NAN; 3],
            truth_ball_m: [f64::NAN; 3],
            crossing_t_s: f64::NAN,
            crossing_sigma_s: f64::NAN,
            horizon: Horizon::default(),
        }
    }
}

/// The Hopf oscillator and the three competing neurons (paper eqs. 20-21).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, TS, ToSchema)]
pub struct HopfView {
    /// True while the timing system drives a motion.
    pub active: bool,
    /// Oscillator state a.
    pub a: f64,
    /// Oscillator state b.
    pub b: f64,
    /// Activation of the initial-posture neuron.
    pub u_init: f64,
    /// Activation of the Hopf (moving) neuron.
    pub u_hopf: f64,
    /// Activation of the final-posture neuron.
    pub u_final: f64,
}

/// The straight-line interception path and its speed profile.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
pub struct PathView {
    /// Planned tool speed along the path now, m/s.
    pub speed_planned_mps: f64,
    /// Executed (measured) tool speed along the path now, m/s.
    pub speed_executed_mps: f64,
    /// Planned progress along the path, 0..1.
    pub progress_planned: f64,
    /// Executed progress along the path, 0..1.
    pub progress_executed: f64,
    /// Path length, metres.
    pub length_m: f64,
    /// Motion start, control clock, seconds (NaN before a motion).
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub start_t_s: f64,
    /// Planned arrival at the intercept point, control clock, seconds (NaN before a motion).
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub arrival_t_s: f64,
    /// Planned movement time, seconds.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub movement_time_s: f64,
    /// Intercept point, robot base frame, metres.
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub intercept_m: [f64; 3],
}

impl Default for PathView {
    fn default() -> Self {
        Self {
            speed_planned_mps: 0.0,
            speed_executed_mps: 0.0,
            progress_planned: 0.0,
            progress_executed: 0.0,
            length_m: 0.0,
            start_t_s: f64::NAN,
            arrival_t_s: f64::NAN,
            movement_time_s: f64::NAN,
            intercept_m: [f64::NAN; 3],
        }
    }
}

/// The arm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
pub struct RobotView {
    /// Measured joint angles, radians.
    pub q_rad: [f64; JOINTS],
    /// Commanded joint angles, radians.
    pub q_cmd_rad: [f64; JOINTS],
    /// Symmetric position limits |q| <= limit, radians.
    pub q_limit_rad: [f64; JOINTS],
    /// Tool point, robot base frame, metres.
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub tool_m: [f64; 3],
    /// Estimated command-to-motion latency of the robot, milliseconds.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub actuation_latency_ms: f64,
    /// FRI's external joint torques of the latest message, N m (null: the
    /// robot sends none).
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub tau_ext_nm: [f64; JOINTS],
}

impl Default for RobotView {
    fn default() -> Self {
        Self {
            q_rad: [0.0; JOINTS],
            q_cmd_rad: [0.0; JOINTS],
            q_limit_rad: crate::kinematics::iiwa7::POSITION_LIMIT_RAD,
            tool_m: [f64::NAN; 3],
            actuation_latency_ms: f64::NAN,
            tau_ext_nm: [f64::NAN; JOINTS],
        }
    }
}

/// The FRI session state (KUKA FRI 1.15 `ESessionState`, plus "no link").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FriSessionState {
    /// No controller messages (yet, or any more).
    #[default]
    Disconnected,
    /// Monitoring, the controller is not ready.
    MonitoringWait,
    /// Monitoring, ready to command.
    MonitoringReady,
    /// Commanding requested, waiting.
    CommandingWait,
    /// Commands are executed.
    CommandingActive,
    /// The session ended.
    Idle,
}

/// The FRI connection quality (KUKA FRI `EConnectionQuality`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FriQuality {
    /// Not known (no link).
    #[default]
    Unknown,
    /// Poor.
    Poor,
    /// Fair.
    Fair,
    /// Good.
    Good,
    /// Excellent.
    Excellent,
}

/// The FRI link.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
pub struct FriView {
    /// Session state.
    pub session: FriSessionState,
    /// Connection quality.
    pub quality: FriQuality,
    /// Controller send period, milliseconds.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub period_ms: f64,
    /// Message receive -> reply sent of the last cycle, microseconds.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub reply_latency_us: f64,
    /// Replies sent after their deadline, since start.
    #[ts(type = "number")]
    pub late_replies: u64,
    /// Controller messages not answered, since start.
    #[ts(type = "number")]
    pub missed_cycles: u64,
    /// Times the controller went silent (the client's safe reaction ran), since start.
    #[ts(type = "number")]
    pub silences: u64,
    /// Times the controller left commanding (abort, quality drop), since start.
    #[ts(type = "number")]
    pub commanding_lost: u64,
}

impl Default for FriView {
    fn default() -> Self {
        Self {
            session: FriSessionState::Disconnected,
            quality: FriQuality::Unknown,
            period_ms: f64::NAN,
            reply_latency_us: f64::NAN,
            late_replies: 0,
            missed_cycles: 0,
            silences: 0,
            commanding_lost: 0,
        }
    }
}

/// The electromagnet holding the ball.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum MagnetState {
    /// Not known (device silent or not connected).
    #[default]
    Unknown,
    /// Holding.
    On,
    /// Released.
    Off,
    /// The device reported a fault.
    Fault,
}

/// Timing of the control loop.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, TS, ToSchema)]
pub struct LoopTiming {
    /// Duration of the last control step, microseconds.
    pub step_us: f64,
    /// Longest control step since start, microseconds.
    pub step_max_us: f64,
    /// Mean period between steps over the last window, microseconds.
    pub period_mean_us: f64,
    /// Longest period between steps over the last window, microseconds.
    pub period_max_us: f64,
    /// Steps that missed their deadline, since start.
    #[ts(type = "number")]
    pub deadline_misses: u64,
}

/// Counters of the control side, since start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, TS, ToSchema)]
pub struct Counters {
    /// Control steps run.
    #[ts(type = "number")]
    pub steps: u64,
    /// Camera measurements folded into the filter.
    #[ts(type = "number")]
    pub measurements: u64,
    /// Camera measurements lost because their ring was full.
    #[ts(type = "number")]
    pub measurement_overflows: u64,
    /// Commands the guard limited or refused.
    #[ts(type = "number")]
    pub guard_interventions: u64,
    /// Joint limit violations detected.
    #[ts(type = "number")]
    pub limit_violations: u64,
    /// Trials finished (with a result or aborted).
    #[ts(type = "number")]
    pub trials: u64,
    /// Trials stopped because no operator heartbeat came within the dead-man time.
    #[ts(type = "number")]
    pub operator_timeouts: u64,
}

/// The camera as the dashboard overlays it on `/ws/camera`'s frames: the latest
/// processed frame's detection in the pixels of the full camera image, and the
/// swing plane's calibration, with which predicted positions and the intercept
/// point are projected into the same image ([`CameraView::project_lateral`]).
/// The streamed frames may be downscaled: scale by their width / `width_px`.
/// `width_px == 0`: no camera (nothing to overlay).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, TS, ToSchema)]
pub struct CameraView {
    /// Width of the camera image the pixel coordinates refer to.
    pub width_px: u32,
    /// Height of the camera image the pixel coordinates refer to.
    pub height_px: u32,
    /// Number of the latest processed frame.
    #[ts(type = "number")]
    pub frame: u64,
    /// Its capture time, control clock, seconds.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub t_s: f64,
    /// Whether the detector found the ball in it.
    pub found: bool,
    /// The camera stopped delivering frames (none for over a second; a real
    /// camera unplugged or its stream broken): trials are refused until it
    /// delivers again.
    pub lost: bool,
    /// Detections dropped so far as inconsistent with the track and shape
    /// (a ball-like blob where the tracked ball cannot be).
    #[ts(type = "number")]
    pub rejected: u64,
    /// Ball centre, image column, pixels (pixel centres at integers).
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub x_px: f64,
    /// Ball centre, image row, pixels.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub y_px: f64,
    /// Apparent ball radius, pixels.
    #[ts(type = "number | null")]
    #[schema(nullable)]
    pub r_px: f64,
    /// Focal length along columns, pixels.
    pub fx_px: f64,
    /// Focal length along rows, pixels.
    pub fy_px: f64,
    /// Principal point, column, pixels.
    pub cx_px: f64,
    /// Principal point, row, pixels.
    pub cy_px: f64,
    /// Radial distortion, r^2 term.
    pub k1: f64,
    /// Radial distortion, r^4 term.
    pub k2: f64,
    /// The ball's rest position (the intercept point), camera frame, metres.
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub rest_c_m: [f64; 3],
    /// The lateral axis (robot base +y), camera frame, unit.
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub lateral_c: [f64; 3],
    /// Up (robot base +z), camera frame, unit.
    #[ts(type = "(number | null)[]")]
    #[schema(value_type = Vec<Option<f64>>)]
    pub up_c: [f64; 3],
}

impl CameraView {
    /// Takes the calibration in use and the size of the image it describes.
    pub fn set_calibration(
        &mut self,
        cal: &crate::vision::SwingPlaneCalibration,
        width_px: u32,
        height_px: u32,
    ) {
        let k = &cal.intrinsics;
        let up = cal.normal_c.cross(&cal.lateral_c);
        self.width_px = width_px;
        self.height_px = height_px;
        (self.fx_px, self.fy_px, self.cx_px, self.cy_px) = (k.fx_px, k.fy_px, k.cx_px, k.cy_px);
        (self.k1, self.k2) = (k.k1, k.k2);
        self.rest_c_m = [cal.rest_c.x, cal.rest_c.y, cal.rest_c.z];
        self.lateral_c = [cal.lateral_c.x, cal.lateral_c.y, cal.lateral_c.z];
        self.up_c = [up.x, up.y, up.z];
    }

    /// Takes the latest processed frame (found or not).
    pub fn set_frame(&mut self, m: &crate::vision::Measurement) {
        self.frame = m.frame;
        self.t_s = m.t_capture_s;
        self.found = m.found;
        self.rejected = m.rejected;
        (self.x_px, self.y_px, self.r_px) = (m.x_px, m.y_px, m.r_px);
    }

    /// Pixel of the ball centre at lateral position `x_m` (= l sin phi) of a
    /// pendulum of length `length_m`: the point `rest + x lateral + l (1 - cos phi) up`
    /// through the pinhole with radial distortion. `None` without a calibration,
    /// for |x| > l, or behind the camera. (The dashboard does the same in TypeScript.)
    pub fn project_lateral(&self, x_m: f64, length_m: f64) -> Option<[f64; 2]> {
        let usable = length_m > 0.0 && x_m.abs() <= length_m; // false for NaN too
        if self.width_px == 0 || !usable {
            return None;
        }
        let lift = length_m - (length_m * length_m - x_m * x_m).sqrt();
        let p: [f64; 3] = std::array::from_fn(|i| {
            self.rest_c_m[i] + x_m * self.lateral_c[i] + lift * self.up_c[i]
        });
        if p[2] <= 1e-6 {
            return None;
        }
        let (x, y) = (p[0] / p[2], p[1] / p[2]);
        let r2 = x * x + y * y;
        let d = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        Some([
            self.fx_px * x * d + self.cx_px,
            self.fy_px * y * d + self.cy_px,
        ])
    }
}

/// Everything the dashboard shows, as of one control step. `Copy`, no heap.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, TS, ToSchema)]
pub struct Snapshot {
    /// Control clock, seconds since the lab started.
    pub t_s: f64,
    /// Control step number (increases by one per step).
    #[ts(type = "number")]
    pub seq: u64,
    /// The trial this step belongs to (0: none).
    #[ts(type = "number")]
    pub trial_id: u64,
    /// Trial state.
    pub trial_state: TrialState,
    /// Pendulum: measured, estimated, predicted.
    pub pendulum: PendulumView,
    /// Hopf oscillator and neurons.
    pub hopf: HopfView,
    /// Path and speed profile.
    pub path: PathView,
    /// Joints and tool.
    pub robot: RobotView,
    /// FRI link.
    pub fri: FriView,
    /// Electromagnet.
    pub magnet: MagnetState,
    /// Loop timing.
    pub timing: LoopTiming,
    /// Counters.
    pub counters: Counters,
    /// The camera's latest detection and calibration, for the overlays.
    pub camera: CameraView,
    /// Why the last trial was aborted (kept until the next trial starts).
    pub abort: AbortView,
    /// Whether the control loop would take a trial now, and if not, why.
    pub ready: Readiness,
}

/// Whether the control loop would start a trial posted now (`POST
/// /api/trials`), and if not, why: what a script waits on instead of
/// retrying refusals. The service adds its own reasons (a calibration step
/// running, a real lab not calibrated) in `GET /api/health`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, TS, ToSchema)]
pub struct Readiness {
    /// A trial posted now would start.
    pub trial: bool,
    /// Why not (`null` when it would): `busy` (a trial runs, is being planned
    /// or is finishing its record), `robot_not_commanding`, `device_unavailable`.
    pub reason: Option<Refusal>,
    /// The reason as a sentence (empty when ready).
    pub message: &'static str,
}

impl Readiness {
    /// Ready when `refusal` is `None`.
    pub const fn from_refusal(refusal: Option<Refusal>) -> Self {
        match refusal {
            None => Self {
                trial: true,
                reason: None,
                message: "",
            },
            Some(r) => Self {
                trial: false,
                reason: Some(r),
                message: r.message(),
            },
        }
    }
}

/// Why the last trial was aborted, as `/api/state` and the dashboard show it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, TS, ToSchema)]
pub struct AbortView {
    /// The trial aborted (0: none since the lab started, or a new trial runs).
    #[ts(type = "number")]
    pub trial_id: u64,
    /// Why (`null` while no trial was aborted).
    pub reason: Option<AbortKind>,
    /// The reason as a sentence (empty while none).
    pub message: &'static str,
    /// What the lab saw, when more is known (e.g. how the FRI link was lost; else empty).
    pub detail: &'static str,
}

/// The kind of a trial's abort, as the API reports it (`abort_reason` of a
/// trial record, `/api/state`, the events): the controller's
/// [`AbortReason`](crate::control::AbortReason) grouped for operators (its
/// [`From`] conversion), plus the service's own
/// [`ServiceRestarted`](Self::ServiceRestarted).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum AbortKind {
    /// The operator pressed stop.
    Stop,
    /// The operator disarmed.
    Disarmed,
    /// The camera stopped delivering measurements.
    CameraLost,
    /// The FRI link was lost or degraded.
    FriLost,
    /// The magnet device is silent or faulty.
    MagnetFault,
    /// The operator's connection was lost.
    OperatorLost,
    /// The motion is not feasible within the limits.
    Infeasible,
    /// A joint limit would have been violated.
    LimitViolation,
    /// The interception condition was not met in time.
    Timeout,
    /// Anything else the control side detected.
    Internal,
    /// The service stopped (or crashed) while the trial ran; its record was
    /// closed when the service started again (never set by the control loop).
    ServiceRestarted,
}

impl From<crate::control::AbortReason> for AbortKind {
    fn from(r: crate::control::AbortReason) -> Self {
        use crate::control::AbortReason as R;
        match r {
            R::StopRequested => Self::Stop,
            R::Infeasible => Self::Infeasible,
            R::IkFailed | R::GuardTripped => Self::LimitViolation,
            R::CameraLost => Self::CameraLost,
            R::FriLost => Self::FriLost,
            R::PredictionTimeout | R::MissedWindow => Self::Timeout,
            R::MagnetFault => Self::MagnetFault,
            R::FilterFault => Self::Internal,
            R::OperatorLost => Self::OperatorLost,
            R::Disarmed => Self::Disarmed,
        }
    }
}

/// The flat state the API shows: an abort's reason is reported apart
/// ([`AbortView`], [`Event::Aborted`]).
impl AbortKind {
    /// The snake_case name, as in JSON.
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Stop => "stop",
            Self::Disarmed => "disarmed",
            Self::CameraLost => "camera_lost",
            Self::FriLost => "fri_lost",
            Self::MagnetFault => "magnet_fault",
            Self::OperatorLost => "operator_lost",
            Self::Infeasible => "infeasible",
            Self::LimitViolation => "limit_violation",
            Self::Timeout => "timeout",
            Self::Internal => "internal",
            Self::ServiceRestarted => "service_restarted",
        }
    }

    /// A sentence for people.
    pub const fn message(self) -> &'static str {
        match self {
            Self::Stop => "emergency stop",
            Self::Disarmed => "disarmed by the operator",
            Self::CameraLost => "the camera stopped delivering measurements",
            Self::FriLost => "the FRI link to the robot was lost",
            Self::MagnetFault => "the magnet device is silent or faulty",
            Self::OperatorLost => "the operator's connection was lost",
            Self::Infeasible => "the motion is not feasible within the joint limits",
            Self::LimitViolation => "a joint limit would have been violated",
            Self::Timeout => "the interception condition was not met in time",
            Self::Internal => "internal error in the control loop",
            Self::ServiceRestarted => "the service stopped while the trial ran",
        }
    }
}

/// The result of a finished trial (CONTRACT.md definitions, judged on ground truth
/// in the simulated lab).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
pub struct TrialResult {
    /// Position and timing within tolerance, no limit violation or abort.
    pub success: bool,
    /// |arrival - t*|, milliseconds.
    pub timing_error_ms: f64,
    /// Tool point to ball centre at t*, metres.
    pub position_error_m: f64,
    /// Arrival - start of the fitted profile, seconds.
    pub movement_time_s: f64,
    /// Robot base axis -> intercept point, horizontal, metres.
    pub distance_m: f64,
    /// When the ball centre passed the intercept point, control clock, seconds.
    pub t_star_s: f64,
    /// Fitted arrival time of the tool, control clock, seconds.
    pub arrival_t_s: f64,
    /// Filter's predicted crossing time minus the truth, at motion start, milliseconds.
    pub prediction_time_error_ms: f64,
    /// Joint limit violations during the trial.
    #[ts(type = "number")]
    pub limit_violations: u64,
    /// Why the outcome could not be judged (`null`: judged; then `success`
    /// is the verdict). A real lab, or a trial with no motion to judge.
    pub not_judged: Option<&'static str>,
    /// The measured judge's verdict (camera, measured joints, external
    /// torques; no ground truth), when there was a committed motion. The
    /// real lab's judgement; beside the true one in the simulated lab.
    pub measured: Option<crate::control::measured::MeasuredJudgement>,
    /// Which judge's verdict `success` and the figures above are (`null`:
    /// not judged, `not_judged` says why).
    pub judged_by: Option<JudgedBy>,
}

/// The judge whose verdict a trial's result carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JudgedBy {
    /// The ground-truth judge of a truthful simulated world: the true ball's
    /// pass and the fitted arrival of the tool (CONTRACT.md definitions).
    Truth,
    /// The physical judge of the reality lab (a scenario's `[world]`): the
    /// true ball meeting the true tool's contact disc.
    Physical,
    /// The measured judge (a real lab, no ground truth): the camera's
    /// detections, the measured joints and FRI's external joint torques
    /// (`result.measured`).
    Measured,
}

impl JudgedBy {
    /// The snake_case name (as in JSON and the records' `judged_by` column).
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Truth => "truth",
            Self::Physical => "physical",
            Self::Measured => "measured",
        }
    }

    /// The name read back (`None` for anything else).
    pub fn parse(s: &str) -> Option<Self> {
        [Self::Truth, Self::Physical, Self::Measured]
            .into_iter()
            .find(|j| j.as_str() == s)
    }
}

/// Something that happened, as the control thread reports it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
#[expect(
    clippy::large_enum_variant,
    reason = "events cross a bounded ring from the control thread by value: no box, no allocation"
)]
pub enum Event {
    /// The trial state changed.
    StateChanged {
        /// Before.
        from: TrialState,
        /// After.
        to: TrialState,
    },
    /// The trial (or the arming) was aborted and the arm stopped safely.
    Aborted {
        /// Why.
        reason: AbortKind,
        /// What the lab saw, when more is known (else empty), e.g. how the
        /// FRI link was lost.
        detail: &'static str,
    },
    /// A trial finished with a result.
    TrialFinished {
        /// The result.
        result: TrialResult,
    },
}

/// An [`Event`] with its time and trial.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, TS, ToSchema)]
pub struct EventRecord {
    /// Control clock, seconds.
    pub t_s: f64,
    /// The trial concerned (0: none).
    #[ts(type = "number")]
    pub trial_id: u64,
    /// What happened.
    pub event: Event,
}

/// What the server asks the control thread to do.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Move home, switch the magnet on, run the checks.
    Arm,
    /// Leave the armed state (the arm stays where it is; the magnet keeps holding).
    Disarm,
    /// Switch the magnet (`on: false` drops the ball).
    Magnet {
        /// On (hold) or off (release).
        on: bool,
    },
    /// Emergency stop: always accepted, from any state.
    Stop,
    /// Run one whole trial (arm, release, intercept) under this id.
    RunTrial {
        /// The id the server gave the trial (> 0).
        trial_id: u64,
        /// What this trial sets for itself (validated by the sender).
        setup: TrialSetup,
    },
    /// Replace the parameters (already validated by the sender). The control
    /// thread hands the old ones back in the [`Ack`] so that it never frees memory.
    SetParams(Box<Scenario>),
    /// Excite one joint with small steps from where the arm rests (the robot
    /// calibration step): accepted at rest, between trials, while the robot
    /// commands; the published states carry the commanded and measured joints.
    Excite(Excitation),
    /// Move the arm slowly to these joint angles (radians) and hold there
    /// (the camera-robot calibration's tour; `Controller::move_to`):
    /// accepted at rest, between trials, while the robot commands; a target
    /// within 5 degrees of a joint limit, or not finite, is refused.
    MoveTo([f64; JOINTS]),
    /// Move the arm to these joint angles as [`Self::MoveTo`] does, at
    /// [`crate::control::KNOCK_LIMIT_SHARE`] of the joints' limits instead
    /// (the contact step's knock on the hanging ball).
    Knock([f64; JOINTS]),
}

/// What one trial may set for itself (`POST /api/trials`): each `None`
/// keeps the lab's draw or parameters. Nothing here changes the parameters
/// in force.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TrialSetup {
    /// Robot base axis to the intercept point, horizontal, metres.
    pub distance_m: Option<f64>,
    /// The motion's planned duration, seconds.
    pub movement_time_s: Option<f64>,
    /// The release angle's magnitude, degrees (the side is drawn).
    pub release_deg: Option<f64>,
    /// The trial's task, stop or strike (`task.mode`).
    pub mode: Option<crate::trajectory::TaskMode>,
    /// A strike's tool speed at contact, m/s (`task.strike_speed_mps`).
    pub strike_speed_mps: Option<f64>,
    /// A strike's direction above the swing's horizontal, degrees
    /// (`task.strike_direction_deg`).
    pub strike_direction_deg: Option<f64>,
}

impl Command {
    /// A short snake_case name, for logs and errors.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Arm => "arm",
            Self::Disarm => "disarm",
            Self::Magnet { .. } => "magnet",
            Self::Stop => "stop",
            Self::RunTrial { .. } => "run_trial",
            Self::SetParams(_) => "set_params",
            Self::Excite(_) => "excite",
            Self::MoveTo(_) => "move_to",
            Self::Knock(_) => "knock",
        }
    }
}

/// Why the control thread refused a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Refusal {
    /// A trial or its preparation runs.
    Busy,
    /// The command needs the armed state.
    NotArmed,
    /// The arm moves; the change is not safe now.
    MotionRunning,
    /// A pre-motion check failed (limits, workspace, devices).
    ChecksFailed,
    /// The motion is not feasible within the limits.
    Infeasible,
    /// The device needed is not connected or silent.
    DeviceUnavailable,
    /// The robot's FRI session is not COMMANDING_ACTIVE (not yet after
    /// start-up, or the controller is silent or dropped out).
    RobotNotCommanding,
    /// The command makes no sense here (e.g. trial id 0).
    Invalid,
}

impl Refusal {
    /// The snake_case name, as in JSON.
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Busy => "busy",
            Self::NotArmed => "not_armed",
            Self::MotionRunning => "motion_running",
            Self::ChecksFailed => "checks_failed",
            Self::Infeasible => "infeasible",
            Self::DeviceUnavailable => "device_unavailable",
            Self::RobotNotCommanding => "robot_not_commanding",
            Self::Invalid => "invalid",
        }
    }

    /// A sentence for people.
    pub const fn message(self) -> &'static str {
        match self {
            Self::Busy => "a trial is running",
            Self::NotArmed => "the lab is not armed",
            Self::MotionRunning => "the arm is moving; this change is not safe now",
            Self::ChecksFailed => "a pre-motion check failed",
            Self::Infeasible => "the motion is not feasible within the joint limits",
            Self::DeviceUnavailable => "a device needed for this is not available",
            Self::RobotNotCommanding => {
                "the robot is not commanding (its FRI session is not COMMANDING_ACTIVE); wait for it"
            }
            Self::Invalid => "the command is not valid here",
        }
    }
}

/// A command with the id its answer will carry.
#[derive(Debug, Clone, PartialEq)]
pub struct CommandEnvelope {
    /// Chosen by the sender, unique per bridge.
    pub id: u64,
    /// What to do.
    pub command: Command,
}

/// The control thread's answer to a command.
#[derive(Debug, Clone, PartialEq)]
pub struct Ack {
    /// The command's id.
    pub id: u64,
    /// Accepted, or refused with a reason.
    pub outcome: Result<(), Refusal>,
    /// Memory handed back to be freed off the control thread (old parameters,
    /// or refused new ones).
    pub returned: Option<Box<Scenario>>,
}
