//! Foxglove: the live WebSocket server (`isochron serve --foxglove ADDR`) and the
//! per-trial MCAP recordings, one set of channels with Foxglove's well-known
//! schemas logged through one [`foxglove::Context`].
//!
//! Everything here runs on the bridge thread (`isochron-bridge`), which drains the
//! control thread's bounded, wait-free hand-offs; the FRI thread never sees it.
//! Messages are built at the state rate from the latest snapshot (only when a
//! sink, a Foxglove client or a recording, listens) and for every camera frame.
//!
//! | topic | schema | rate |
//! |---|---|---|
//! | `/tf` | `foxglove.FrameTransforms`: base -> link_1 .. link_7 -> flange -> tool (measured joints) | state rate |
//! | `/joint_states` | JSON `isochron.JointStates` (names, measured, commanded, limits) | state rate |
//! | `/pendulum` | `foxglove.SceneUpdate`: ball (estimate), true ball (simulated lab), string, predicted path, intercept point | state rate |
//! | `/series` | JSON `isochron.Series`: the dashboard's plotted scalars | state rate |
//! | `/camera/image` | `foxglove.CompressedImage` (JPEG) | camera stream rate |
//! | `/camera/annotations` | `foxglove.ImageAnnotations`: detection circle, predicted positions, intercept point | camera stream rate |
//! | `/robot_description` | JSON `std_msgs/String` with the URDF | when a recording opens, then 1 Hz |
//! | `/trial/strike` ([`STRIKE_TOPIC`]) | JSON `isochron.Strike`: a strike's tool speed at contact (planned, executed), its outgoing ball speed (predicted with the rebound's curve, seen) | once, at a strike trial's end (before its judgement) |
//! | `/trial/judgement` ([`JUDGEMENT_TOPIC`]) | JSON `isochron.TrialJudgement`: how the trial ended, which judge decided, the true figures (simulated lab) and the measured judge's | once, at the trial's end (the recording's last message) |
//!
//! Log times are the Unix clock (nanoseconds) when the bridge thread logs the
//! message; the header timestamps are the control-clock times of the data moved
//! onto the Unix clock (the offset is measured at each state tick). Positions are
//! in the robot base frame (`base`, x forward to the pendulum, z up), metres.

use std::{
    collections::BTreeMap,
    fs::File,
    io::BufWriter,
    path::{Path, PathBuf},
    sync::Arc,
    time::{Duration, Instant},
};

use foxglove::{
    Channel, Context, McapWriterHandle, RawChannel, Schema,
    messages::{
        CircleAnnotation, Color, CompressedImage, FrameTransform, FrameTransforms,
        ImageAnnotations, LinePrimitive, Point2, Point3, PointsAnnotation, Pose, Quaternion,
        SceneEntity, SceneUpdate, SpherePrimitive, Timestamp, Vector3, line_primitive,
        points_annotation,
    },
};
use rt_core::{
    bridge::{JudgedBy, Snapshot, TrialResult},
    control::measured::MeasuredJudgement,
    kinematics::iiwa7::{JOINT_NAMES, JOINTS, URDF_AXES, URDF_FRAMES, URDF_JOINT_Z_M},
    params::Scenario,
};
use serde::Serialize;

/// The topics, in the order [`Channels`] holds them.
pub const TOPICS: [&str; 7] = [
    "/tf",
    "/joint_states",
    "/pendulum",
    "/series",
    "/camera/image",
    "/camera/annotations",
    "/robot_description",
];

/// The trial's judgement, logged once when a trial ends (the last message of
/// its recording; live clients get it too). Not in [`TOPICS`]: those stream
/// at the state or camera rate, this one only at trials' ends.
pub const JUDGEMENT_TOPIC: &str = "/trial/judgement";

/// The schema name of [`JUDGEMENT_TOPIC`]'s messages.
pub const JUDGEMENT_SCHEMA_NAME: &str = "isochron.TrialJudgement";

/// A strike trial's figures (issue #38), logged once when it ends (before
/// its judgement): the tool's speed at contact planned and executed, the
/// ball's outgoing speed predicted (the controller's rebound at its commit,
/// with the curve of its first swing) and seen (the camera's rebound). Not in
/// [`TOPICS`]: only strike trials log it.
pub const STRIKE_TOPIC: &str = "/trial/strike";

/// The schema name of [`STRIKE_TOPIC`]'s messages.
pub const STRIKE_SCHEMA_NAME: &str = "isochron.Strike";

/// Points of the predicted rebound's curve: its first swing out and back.
const REBOUND_CURVE_POINTS: usize = 41;

/// The robot description is re-sent this often to live clients (they join any time).
const DESCRIPTION_PERIOD: Duration = Duration::from_secs(1);

const JOINT_STATES_SCHEMA: &str = r#"{"type":"object","title":"isochron.JointStates","properties":{
"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},
"name":{"type":"array","items":{"type":"string"}},
"position":{"type":"array","items":{"type":"number"},"description":"measured, rad"},
"commanded":{"type":"array","items":{"type":"number"},"description":"commanded, rad"},
"limit":{"type":"array","items":{"type":"number"},"description":"|q| <= limit, rad"}}}"#;

const SERIES_SCHEMA: &str = r#"{"type":"object","title":"isochron.Series","properties":{
"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}}},
"t_s":{"type":"number","description":"control clock, s"},
"trial_id":{"type":"integer"},
"trial_state":{"type":"string"},
"pendulum":{"type":"object","properties":{"measured_x_m":{"type":"number"},"x_m":{"type":"number"},"sigma_x_m":{"type":"number"},"phi_rad":{"type":"number"},"dphi_radps":{"type":"number"},"crossing_t_s":{"type":"number"},"crossing_sigma_s":{"type":"number"}}},
"path":{"type":"object","properties":{"speed_planned_mps":{"type":"number"},"speed_executed_mps":{"type":"number"},"progress_planned":{"type":"number"},"progress_executed":{"type":"number"}}},
"hopf":{"type":"object","properties":{"a":{"type":"number"},"b":{"type":"number"},"u_init":{"type":"number"},"u_hopf":{"type":"number"},"u_final":{"type":"number"}}},
"timing":{"type":"object","properties":{"step_us":{"type":"number"},"period_mean_us":{"type":"number"},"period_max_us":{"type":"number"},"reply_latency_us":{"type":"number"},"missed_cycles":{"type":"integer"},"deadline_misses":{"type":"integer"}}}}}"#;

const JUDGEMENT_SCHEMA: &str = r#"{"type":"object","title":"isochron.TrialJudgement","properties":{
"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}},"description":"the trial's end, Unix time"},
"trial_id":{"type":"integer"},
"status":{"type":"string","description":"done or aborted (service_restarted: the service stopped while the trial ran)"},
"judged_by":{"type":["string","null"],"description":"truth (truthful simulated world), physical (reality lab), measured (real lab); null: not judged"},
"success":{"type":["boolean","null"],"description":"the verdict; null: not judged"},
"reason":{"type":"string","description":"the record's reason, a sentence"},
"truth":{"type":["object","null"],"description":"the true judge's figures (simulated lab, judged_by truth or physical)","properties":{"timing_error_ms":{"type":["number","null"],"description":"|arrival - t*|, ms"},"position_error_m":{"type":["number","null"]},"t_star_s":{"type":["number","null"],"description":"control clock, s"},"arrival_t_s":{"type":["number","null"],"description":"control clock, s"},"movement_time_s":{"type":["number","null"]}}},
"measured":{"type":["object","null"],"description":"the measured judge's verdict (camera, measured joints, external torques)","properties":{"pass_t_s":{"type":["number","null"]},"arrival_t_s":{"type":["number","null"]},"timing_error_ms":{"type":["number","null"],"description":"arrival - pass, signed (negative: early), ms"},"timing_std_ms":{"type":["number","null"]},"contact":{"type":"boolean"},"contact_t_s":{"type":["number","null"]},"success":{"type":"boolean"},"torque_signal":{"type":"boolean","description":"false: the robot reported no external torques, contact cannot be seen"},"robot_gap_ms":{"type":["number","null"],"description":"the robot's messages paused this long around the pass or arrival: not judged"}}}}}"#;

/// [`STRIKE_TOPIC`]'s JSON schema.
pub const STRIKE_SCHEMA: &str = r#"{"type":"object","title":"isochron.Strike","properties":{
"timestamp":{"type":"object","properties":{"sec":{"type":"integer"},"nsec":{"type":"integer"}},"description":"the trial's end, Unix time (a recording converted from CSV: the contact on the control clock)"},
"trial_id":{"type":"integer"},
"planned_tool_speed_mps":{"type":["number","null"],"description":"the tool's planned speed at contact (task.strike_speed_mps), m/s"},
"executed_tool_speed_mps":{"type":["number","null"],"description":"the measured tool point's speed at the contact's onset (FRI's joints), m/s"},
"target_ball_speed_mps":{"type":["number","null"],"description":"the outgoing ball speed aimed at, m/s"},
"predicted_ball_speed_mps":{"type":["number","null"],"description":"the controller's predicted outgoing speed (its beliefs at the commit), m/s"},
"seen_ball_speed_mps":{"type":["number","null"],"description":"the camera's rebound: the ball's outgoing speed at the contact's onset, m/s"},
"seen_ball_speed_std_mps":{"type":["number","null"]},
"returned":{"type":"boolean","description":"the ball left along the return"},
"speed_ok":{"type":"boolean","description":"returned, within 20% of the target"},
"contact_t_s":{"type":["number","null"],"description":"the contact's onset (external torques), control clock, s"},
"predicted":{"type":["object","null"],"description":"the predicted rebound and what it used (restitution, tool speed along the return, the ball's pass speed, frequency, damping, amplitude, turn)"},
"predicted_curve":{"type":"array","description":"the predicted rebound's first swing: the ball's lateral offset from the contact point along the return","items":{"type":"object","properties":{"tau_s":{"type":"number","description":"since the contact, s"},"t_s":{"type":["number","null"],"description":"control clock, s"},"lateral_m":{"type":"number"}}}}}}"#;

const STRING_SCHEMA: &str =
    r#"{"type":"object","title":"std_msgs/String","properties":{"data":{"type":"string"}}}"#;

fn json_channel(
    ctx: &Arc<Context>,
    topic: &str,
    name: &str,
    schema: &'static str,
) -> Arc<RawChannel> {
    // Building a channel fails only for a duplicate topic with another schema,
    // which this module never does on its own context.
    ctx.channel_builder(topic)
        .message_encoding("json")
        .schema(Schema::new(name, "jsonschema", schema.as_bytes()))
        .build_raw()
        .unwrap_or_else(|e| panic!("channel {topic}: {e}"))
}

/// The channels of one context.
struct Channels {
    tf: Channel<FrameTransforms>,
    joints: Arc<RawChannel>,
    pendulum: Channel<SceneUpdate>,
    series: Arc<RawChannel>,
    image: Channel<CompressedImage>,
    annotations: Channel<ImageAnnotations>,
    description: Arc<RawChannel>,
    judgement: Arc<RawChannel>,
    strike: Arc<RawChannel>,
}

/// What a recording's metadata says about the trial it records.
#[derive(Debug, Clone)]
pub struct RecordingContext {
    /// The scenario's name.
    pub scenario: String,
    /// The parameters in effect, as TOML.
    pub parameters_toml: String,
    /// The software revision (`0.1.0 (git ...)`).
    pub revision: String,
    /// `simulated` or `real`.
    pub lab_mode: &'static str,
}

struct Recording {
    trial_id: u64,
    path: PathBuf,
    writer: McapWriterHandle<BufWriter<File>>,
    /// The true ball at release (simulated lab): the world's draw as it happened.
    truth_at_release: Option<(f64, [f64; 3])>,
    states: u64,
}

/// The Foxglove side of the bridge thread.
pub struct Foxglove {
    ctx: Arc<Context>,
    ch: Channels,
    urdf: String,
    ball_radius_m: f64,
    length_m: f64,
    /// Unix seconds minus control-clock seconds, measured at the last state tick.
    unix_offset_s: f64,
    last_description: Option<Instant>,
    recording: Option<Recording>,
    last: Option<Snapshot>,
}

impl std::fmt::Debug for Foxglove {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Foxglove")
            .field("recording", &self.recording.as_ref().map(|r| r.trial_id))
            .finish_non_exhaustive()
    }
}

fn unix_now_s() -> f64 {
    crate::records::unix_now_s()
}

fn stamp(unix_s: f64) -> Option<Timestamp> {
    if !unix_s.is_finite() || unix_s < 0.0 {
        return None;
    }
    let sec = unix_s.floor();
    let nsec = ((unix_s - sec) * 1e9).round().min(999_999_999.0);
    Some(Timestamp::new(sec as u32, nsec as u32))
}

#[expect(
    clippy::unnecessary_wraps,
    reason = "the Foxglove messages' fields are optional: built where they are set"
)]
fn v3(p: [f64; 3]) -> Option<Vector3> {
    Some(Vector3 {
        x: p[0],
        y: p[1],
        z: p[2],
    })
}

fn p3(p: [f64; 3]) -> Point3 {
    Point3 {
        x: p[0],
        y: p[1],
        z: p[2],
    }
}

#[expect(
    clippy::unnecessary_wraps,
    reason = "the Foxglove messages' fields are optional: built where they are set"
)]
fn color(r: f64, g: f64, b: f64, a: f64) -> Option<Color> {
    Some(Color { r, g, b, a })
}

fn finite3(p: [f64; 3]) -> bool {
    p.iter().all(|v| v.is_finite())
}

#[expect(
    clippy::unnecessary_wraps,
    reason = "the Foxglove messages' fields are optional: built where they are set"
)]
fn identity_pose(at: [f64; 3]) -> Option<Pose> {
    Some(Pose {
        position: v3(at),
        orientation: Some(Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }),
    })
}

#[derive(Serialize)]
struct Stamp {
    sec: u32,
    nsec: u32,
}

#[derive(Serialize)]
struct JointStates<'a> {
    timestamp: Stamp,
    name: &'a [&'a str; JOINTS],
    position: [f64; JOINTS],
    commanded: [f64; JOINTS],
    limit: [f64; JOINTS],
}

#[derive(Serialize)]
struct Series {
    timestamp: Stamp,
    t_s: f64,
    trial_id: u64,
    trial_state: &'static str,
    pendulum: serde_json::Value,
    path: serde_json::Value,
    hopf: serde_json::Value,
    timing: serde_json::Value,
}

/// A trial's judgement ([`JUDGEMENT_TOPIC`]).
#[derive(Serialize)]
struct TrialJudgement {
    timestamp: Stamp,
    trial_id: u64,
    status: &'static str,
    judged_by: Option<JudgedBy>,
    success: Option<bool>,
    reason: String,
    truth: Option<TrueFigures>,
    measured: Option<MeasuredJudgement>,
}

/// The true judge's figures of a simulated trial (`TrialResult`'s).
#[derive(Serialize)]
struct TrueFigures {
    timing_error_ms: f64,
    position_error_m: f64,
    t_star_s: f64,
    arrival_t_s: f64,
    movement_time_s: f64,
}

impl TrialJudgement {
    fn of(trial_id: u64, end: Option<&crate::records::TrialEnd>, unix_s: f64) -> Self {
        use crate::records::TrialEnd;
        let (status, judged_by, success, truth, measured) = match end {
            Some(TrialEnd::Done(r)) => (
                "done",
                r.judged_by,
                r.not_judged.is_none().then_some(r.success),
                matches!(r.judged_by, Some(JudgedBy::Truth | JudgedBy::Physical)).then_some(
                    TrueFigures {
                        timing_error_ms: r.timing_error_ms,
                        position_error_m: r.position_error_m,
                        t_star_s: r.t_star_s,
                        arrival_t_s: r.arrival_t_s,
                        movement_time_s: r.movement_time_s,
                    },
                ),
                r.measured,
            ),
            // None: the service stopped mid-trial; the record is closed so at its next start.
            Some(TrialEnd::Aborted(..)) | None => ("aborted", None, Some(false), None, None),
        };
        Self {
            timestamp: js(stamp(unix_s)),
            trial_id,
            status,
            judged_by,
            success,
            reason: end.map_or_else(
                || crate::records::abort_sentence(rt_core::bridge::AbortKind::ServiceRestarted, ""),
                crate::records::end_reason,
            ),
            truth,
            measured,
        }
    }
}

/// One point of the predicted rebound's curve.
#[derive(Serialize)]
pub struct CurvePoint {
    /// Since the contact, s.
    pub tau_s: f64,
    /// On the control clock (the measured contact plus `tau_s`), s.
    pub t_s: Option<f64>,
    /// The ball's lateral offset from the contact point along the return, m.
    pub lateral_m: f64,
}

/// A strike trial's message on [`STRIKE_TOPIC`].
#[derive(Serialize)]
pub struct StrikeMessage {
    timestamp: Stamp,
    trial_id: u64,
    planned_tool_speed_mps: f64,
    executed_tool_speed_mps: Option<f64>,
    target_ball_speed_mps: f64,
    predicted_ball_speed_mps: Option<f64>,
    seen_ball_speed_mps: Option<f64>,
    seen_ball_speed_std_mps: Option<f64>,
    returned: bool,
    speed_ok: bool,
    contact_t_s: Option<f64>,
    predicted: Option<rt_core::control::PredictedRebound>,
    predicted_curve: Vec<CurvePoint>,
}

impl StrikeMessage {
    /// The message of a trial whose measured judge saw a strike (`None`
    /// for a stop), stamped `unix_s`.
    pub fn of(trial_id: u64, m: &MeasuredJudgement, unix_s: f64) -> Option<Self> {
        let k = m.strike?;
        let predicted_curve = k.predicted.map_or_else(Vec::new, |p| {
            // Out to the turn and back to the contact point.
            let span = p.back_s();
            (0..REBOUND_CURVE_POINTS)
                .map(|i| {
                    let tau_s = span * i as f64 / (REBOUND_CURVE_POINTS - 1) as f64;
                    CurvePoint {
                        tau_s,
                        t_s: m.contact_t_s.map(|c| c + tau_s),
                        lateral_m: p.lateral_at(tau_s),
                    }
                })
                .collect()
        });
        Some(Self {
            timestamp: js(stamp(unix_s)),
            trial_id,
            planned_tool_speed_mps: k.planned_tool_speed_mps,
            executed_tool_speed_mps: k.tool_speed_mps,
            target_ball_speed_mps: k.target_ball_speed_mps,
            predicted_ball_speed_mps: k.predicted.map(|p| p.ball_speed_mps),
            seen_ball_speed_mps: k.ball_speed_mps,
            seen_ball_speed_std_mps: k.ball_speed_std_mps,
            returned: k.returned,
            speed_ok: k.speed_ok,
            contact_t_s: m.contact_t_s,
            predicted: k.predicted,
            predicted_curve,
        })
    }
}

fn js(t: Option<Timestamp>) -> Stamp {
    t.map_or(Stamp { sec: 0, nsec: 0 }, |t| Stamp {
        sec: t.sec(),
        nsec: t.nsec(),
    })
}

/// `base_from_link` transforms of the URDF's chain for joints `q`, each relative
/// to its parent (what `FrameTransforms` carries).
pub fn link_transforms(
    q: &[f64; JOINTS],
    tool_length_m: f64,
) -> [([f64; 3], [f64; 4]); JOINTS + 2] {
    let mut out = [([0.0; 3], [0.0, 0.0, 0.0, 1.0]); JOINTS + 2];
    for i in 0..JOINTS {
        let a = URDF_AXES[i];
        let (s, c) = (q[i] / 2.0).sin_cos();
        out[i] = (
            [0.0, 0.0, URDF_JOINT_Z_M[i]],
            [a[0] * s, a[1] * s, a[2] * s, c],
        );
    }
    out[JOINTS] = ([0.0, 0.0, URDF_JOINT_Z_M[JOINTS]], [0.0, 0.0, 0.0, 1.0]);
    out[JOINTS + 1] = ([0.0, 0.0, tool_length_m], [0.0, 0.0, 0.0, 1.0]);
    out
}

impl Foxglove {
    /// Channels on a new context, for the scenario's arm, tool and pendulum.
    pub fn new(scenario: &Scenario) -> Self {
        let ctx = Context::new();
        let ch = Channels {
            tf: ctx.channel_builder(TOPICS[0]).build(),
            joints: json_channel(&ctx, TOPICS[1], "isochron.JointStates", JOINT_STATES_SCHEMA),
            pendulum: ctx.channel_builder(TOPICS[2]).build(),
            series: json_channel(&ctx, TOPICS[3], "isochron.Series", SERIES_SCHEMA),
            image: ctx.channel_builder(TOPICS[4]).build(),
            annotations: ctx.channel_builder(TOPICS[5]).build(),
            description: json_channel(&ctx, TOPICS[6], "std_msgs/String", STRING_SCHEMA),
            judgement: json_channel(
                &ctx,
                JUDGEMENT_TOPIC,
                JUDGEMENT_SCHEMA_NAME,
                JUDGEMENT_SCHEMA,
            ),
            strike: json_channel(&ctx, STRIKE_TOPIC, STRIKE_SCHEMA_NAME, STRIKE_SCHEMA),
        };
        let mut f = Self {
            ctx,
            ch,
            urdf: String::new(),
            ball_radius_m: 0.0,
            length_m: 1.0,
            unix_offset_s: f64::NAN,
            last_description: None,
            recording: None,
            last: None,
        };
        f.set_scenario(scenario);
        f
    }

    /// Takes new parameters (tool length, pendulum).
    pub fn set_scenario(&mut self, scenario: &Scenario) {
        self.urdf = rt_core::kinematics::iiwa7::urdf_with_tool(scenario.task.tool_length_m);
        self.ball_radius_m = scenario.pendulum.ball_radius_m;
        self.length_m = scenario.pendulum.length_m;
    }

    /// The context the live server and the recordings log through.
    pub fn context(&self) -> &Arc<Context> {
        &self.ctx
    }

    /// The trial being recorded, if any.
    pub fn recording(&self) -> Option<u64> {
        self.recording.as_ref().map(|r| r.trial_id)
    }

    fn tool_length_m(&self) -> f64 {
        // The URDF's tool joint carries it; kept in one place.
        self.urdf
            .split("<child link=\"tool\"/>")
            .nth(1)
            .and_then(|s| s.split("xyz=\"0 0 ").nth(1))
            .and_then(|s| s.split('"').next())
            .and_then(|s| s.parse().ok())
            .unwrap_or(0.10)
    }

    fn unix_of(&self, t_s: f64) -> f64 {
        t_s + self.unix_offset_s
    }

    /// Logs one state tick's messages (skipped when nobody listens).
    pub fn publish_state(&mut self, s: &Snapshot) {
        self.unix_offset_s = unix_now_s() - s.t_s;
        self.last = Some(*s);
        if let Some(r) = self.recording.as_mut() {
            r.states += 1;
            if r.truth_at_release.is_none()
                && !matches!(
                    s.trial_state,
                    rt_core::bridge::TrialState::Idle
                        | rt_core::bridge::TrialState::Arming
                        | rt_core::bridge::TrialState::Armed
                )
                && finite3(s.pendulum.truth_ball_m)
            {
                r.truth_at_release = Some((s.t_s, s.pendulum.truth_ball_m));
            }
        }
        let now = Instant::now();
        if self.ch.description.has_sinks()
            && self
                .last_description
                .is_none_or(|t| now.duration_since(t) >= DESCRIPTION_PERIOD)
        {
            self.log_description();
            self.last_description = Some(now);
        }
        let ts = stamp(self.unix_of(s.t_s));
        if self.ch.tf.has_sinks() {
            let q: [f64; JOINTS] = s.robot.q_rad;
            let links = link_transforms(&q, self.tool_length_m());
            let transforms = links
                .iter()
                .enumerate()
                .map(|(i, (t, r))| FrameTransform {
                    timestamp: ts,
                    parent_frame_id: URDF_FRAMES[i].to_owned(),
                    child_frame_id: URDF_FRAMES[i + 1].to_owned(),
                    translation: v3(*t),
                    rotation: Some(Quaternion {
                        x: r[0],
                        y: r[1],
                        z: r[2],
                        w: r[3],
                    }),
                })
                .collect();
            self.ch.tf.log(&FrameTransforms { transforms });
        }
        if self.ch.joints.has_sinks() {
            let msg = JointStates {
                timestamp: js(ts),
                name: &JOINT_NAMES,
                position: s.robot.q_rad,
                commanded: s.robot.q_cmd_rad,
                limit: s.robot.q_limit_rad,
            };
            if let Ok(b) = serde_json::to_vec(&msg) {
                self.ch.joints.log(&b);
            }
        }
        if self.ch.pendulum.has_sinks() {
            self.ch.pendulum.log(&self.scene(s, ts));
        }
        if self.ch.series.has_sinks() {
            let p = &s.pendulum;
            let msg = Series {
                timestamp: js(ts),
                t_s: s.t_s,
                trial_id: s.trial_id,
                trial_state: s.trial_state.as_str(),
                pendulum: serde_json::json!({
                    "measured_x_m": if p.measured.valid { p.measured.x_m } else { f64::NAN },
                    "x_m": p.x_m, "sigma_x_m": p.sigma_x_m, "phi_rad": p.phi_rad,
                    "dphi_radps": p.dphi_radps, "crossing_t_s": p.crossing_t_s,
                    "crossing_sigma_s": p.crossing_sigma_s,
                }),
                path: serde_json::json!({
                    "speed_planned_mps": s.path.speed_planned_mps,
                    "speed_executed_mps": s.path.speed_executed_mps,
                    "progress_planned": s.path.progress_planned,
                    "progress_executed": s.path.progress_executed,
                }),
                hopf: serde_json::json!({
                    "a": s.hopf.a, "b": s.hopf.b, "u_init": s.hopf.u_init,
                    "u_hopf": s.hopf.u_hopf, "u_final": s.hopf.u_final,
                }),
                timing: serde_json::json!({
                    "step_us": s.timing.step_us, "period_mean_us": s.timing.period_mean_us,
                    "period_max_us": s.timing.period_max_us,
                    "reply_latency_us": s.fri.reply_latency_us,
                    "missed_cycles": s.fri.missed_cycles,
                    "deadline_misses": s.timing.deadline_misses,
                }),
            };
            if let Ok(b) = serde_json::to_vec(&msg) {
                self.ch.series.log(&b);
            }
        }
    }

    fn log_description(&self) {
        if let Ok(b) = serde_json::to_vec(&serde_json::json!({ "data": self.urdf })) {
            self.ch.description.log(&b);
        }
    }

    /// The pendulum as a scene: the ball (estimate), the true ball (simulated lab),
    /// the string from the pivot, the predicted path and the intercept point.
    fn scene(&self, s: &Snapshot, ts: Option<Timestamp>) -> SceneUpdate {
        let p = &s.pendulum;
        let l = self.length_m;
        let d = 2.0 * self.ball_radius_m;
        let mut entities = Vec::with_capacity(4);
        let entity = |id: &str| SceneEntity {
            timestamp: ts,
            frame_id: "base".to_owned(),
            id: id.to_owned(),
            ..Default::default()
        };
        let sphere = |at: [f64; 3], size: f64, c: Option<Color>| SpherePrimitive {
            pose: identity_pose(at),
            size: v3([size, size, size]),
            color: c,
        };
        let line = |points: Vec<Point3>, c: Option<Color>, thickness: f64| LinePrimitive {
            r#type: line_primitive::Type::LineStrip as i32,
            pose: identity_pose([0.0; 3]),
            thickness,
            scale_invariant: false,
            points,
            color: c,
            ..Default::default()
        };
        if finite3(p.ball_m) {
            // ball = pivot + l (0, sin phi, -cos phi).
            let (sp, cp) = p.phi_rad.sin_cos();
            let pivot = [p.ball_m[0], p.ball_m[1] - l * sp, p.ball_m[2] + l * cp];
            let mut ball = entity("ball");
            ball.spheres
                .push(sphere(p.ball_m, d, color(0.85, 0.95, 0.2, 1.0)));
            ball.lines.push(line(
                vec![p3(pivot), p3(p.ball_m)],
                color(0.8, 0.8, 0.8, 1.0),
                0.004,
            ));
            entities.push(ball);
            let horizon = p.horizon.as_slice();
            if !horizon.is_empty() {
                let pts = horizon
                    .iter()
                    .filter(|h| h.x_m.is_finite() && h.x_m.abs() <= l)
                    .map(|h| {
                        let lift = l - (l * l - h.x_m * h.x_m).sqrt();
                        p3([pivot[0], pivot[1] + h.x_m, pivot[2] - l + lift])
                    })
                    .collect();
                let mut path = entity("predicted_path");
                path.lines.push(line(pts, color(0.3, 0.6, 1.0, 0.9), 0.006));
                entities.push(path);
            }
        }
        if finite3(p.truth_ball_m) {
            let mut truth = entity("true_ball");
            truth
                .spheres
                .push(sphere(p.truth_ball_m, d, color(0.2, 0.9, 0.3, 0.35)));
            entities.push(truth);
        }
        if finite3(s.path.intercept_m) {
            let mut x = entity("intercept");
            x.spheres
                .push(sphere(s.path.intercept_m, 0.03, color(1.0, 0.2, 0.2, 0.8)));
            entities.push(x);
        }
        SceneUpdate {
            deletions: Vec::new(),
            entities,
        }
    }

    /// Logs a camera frame (JPEG, `width_px` wide) and its annotations: the
    /// latest detection, the predicted positions and the intercept point, scaled
    /// from the full camera image to the frame.
    pub fn publish_frame(&mut self, t_capture_s: f64, jpeg: &[u8], width_px: Option<u32>) {
        if !self.ch.image.has_sinks() && !self.ch.annotations.has_sinks() {
            return;
        }
        let ts = stamp(self.unix_of(t_capture_s));
        self.ch.image.log(&CompressedImage {
            timestamp: ts,
            frame_id: "camera".to_owned(),
            data: foxglove::bytes::Bytes::copy_from_slice(jpeg),
            format: "jpeg".to_owned(),
        });
        let Some(s) = self.last else {
            return;
        };
        let cam = &s.camera;
        let mut a = ImageAnnotations {
            timestamp: ts,
            ..Default::default()
        };
        if cam.width_px > 0 {
            let k = width_px.map_or(1.0, |w| f64::from(w) / f64::from(cam.width_px));
            if cam.found {
                a.circles.push(CircleAnnotation {
                    timestamp: ts,
                    position: Some(Point2 {
                        x: cam.x_px * k,
                        y: cam.y_px * k,
                    }),
                    diameter: 2.0 * cam.r_px * k,
                    thickness: 2.0,
                    fill_color: color(0.0, 0.0, 0.0, 0.0),
                    outline_color: color(0.1, 1.0, 0.3, 1.0),
                    metadata: Vec::new(),
                });
            }
            let predicted: Vec<Point2> = s
                .pendulum
                .horizon
                .as_slice()
                .iter()
                .filter_map(|h| cam.project_lateral(h.x_m, self.length_m))
                .map(|[x, y]| Point2 { x: x * k, y: y * k })
                .collect();
            if !predicted.is_empty() {
                a.points.push(PointsAnnotation {
                    timestamp: ts,
                    r#type: points_annotation::Type::LineStrip as i32,
                    points: predicted,
                    outline_color: color(0.3, 0.6, 1.0, 1.0),
                    thickness: 2.0,
                    ..Default::default()
                });
            }
            if let Some([x, y]) = cam.project_lateral(0.0, self.length_m) {
                a.circles.push(CircleAnnotation {
                    timestamp: ts,
                    position: Some(Point2 { x: x * k, y: y * k }),
                    diameter: 10.0,
                    thickness: 2.0,
                    fill_color: color(1.0, 0.2, 0.2, 0.6),
                    outline_color: color(1.0, 0.2, 0.2, 1.0),
                    metadata: Vec::new(),
                });
            }
        }
        self.ch.annotations.log(&a);
    }

    /// Starts recording trial `trial_id` into `path` (MCAP, written live) with
    /// its metadata; a recording still open is finished first.
    ///
    /// # Errors
    ///
    /// When the MCAP file cannot be created or its metadata cannot be written.
    pub fn start_recording(
        &mut self,
        trial_id: u64,
        path: &Path,
        meta: &RecordingContext,
    ) -> anyhow::Result<()> {
        self.finish_recording(None);
        let file = File::create(path)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", path.display()))?;
        let writer = self.ctx.mcap_writer().create(BufWriter::new(file))?;
        let map = |kv: &[(&str, String)]| -> BTreeMap<String, String> {
            kv.iter()
                .map(|(k, v)| ((*k).to_owned(), v.clone()))
                .collect()
        };
        writer.write_metadata(
            "trial",
            map(&[
                ("trial_id", trial_id.to_string()),
                ("scenario", meta.scenario.clone()),
                ("revision", meta.revision.clone()),
                ("lab_mode", meta.lab_mode.to_owned()),
                ("started_unix_s", format!("{:.6}", unix_now_s())),
            ]),
        )?;
        writer.write_metadata("parameters", map(&[("toml", meta.parameters_toml.clone())]))?;
        let cal = self
            .last
            .map(|s| serde_json::to_string(&s.camera).unwrap_or_default())
            .unwrap_or_default();
        writer.write_metadata(
            "calibration",
            map(&[
                ("camera_json", cal),
                ("tool_length_m", self.tool_length_m().to_string()),
                ("pendulum_length_m", self.length_m.to_string()),
            ]),
        )?;
        self.recording = Some(Recording {
            trial_id,
            path: path.to_path_buf(),
            writer,
            truth_at_release: None,
            states: 0,
        });
        // The robot description once per recording (its URDF layer reads it).
        self.log_description();
        Ok(())
    }

    /// Finishes the open recording with the judged result (or the abort reason)
    /// and the world's draw; returns the trial, the file and the state ticks recorded.
    pub fn finish_recording(
        &mut self,
        end: Option<&crate::records::TrialEnd>,
    ) -> Option<(u64, PathBuf, u64)> {
        let r = self.recording.take()?;
        // A strike's figures, then the judgement, go into the recording
        // before it closes.
        if let Some(crate::records::TrialEnd::Done(TrialResult {
            measured: Some(m), ..
        })) = end
            && let Some(k) = StrikeMessage::of(r.trial_id, m, unix_now_s())
        {
            match serde_json::to_vec(&k) {
                Ok(b) => self.ch.strike.log(&b),
                Err(e) => {
                    tracing::error!(trial = r.trial_id, error = %e, "cannot encode the strike");
                }
            }
        }
        let judgement = TrialJudgement::of(r.trial_id, end, unix_now_s());
        match serde_json::to_vec(&judgement) {
            Ok(b) => self.ch.judgement.log(&b),
            Err(e) => {
                tracing::error!(trial = r.trial_id, error = %e, "cannot encode the judgement");
            }
        }
        let mut result = BTreeMap::new();
        match end {
            Some(crate::records::TrialEnd::Done(TrialResult {
                success,
                timing_error_ms,
                position_error_m,
                movement_time_s,
                distance_m,
                t_star_s,
                arrival_t_s,
                prediction_time_error_ms,
                limit_violations,
                ..
            })) => {
                for (k, v) in [
                    ("status", "done".to_owned()),
                    ("success", success.to_string()),
                    ("timing_error_ms", timing_error_ms.to_string()),
                    ("position_error_m", position_error_m.to_string()),
                    ("movement_time_s", movement_time_s.to_string()),
                    ("distance_m", distance_m.to_string()),
                    ("t_star_s", t_star_s.to_string()),
                    ("arrival_t_s", arrival_t_s.to_string()),
                    (
                        "prediction_time_error_ms",
                        prediction_time_error_ms.to_string(),
                    ),
                    ("limit_violations", limit_violations.to_string()),
                ] {
                    result.insert(k.to_owned(), v);
                }
            }
            Some(crate::records::TrialEnd::Aborted(reason, detail)) => {
                result.insert("status".to_owned(), "aborted".to_owned());
                result.insert("abort_reason".to_owned(), reason.as_str().to_owned());
                result.insert(
                    "reason".to_owned(),
                    crate::records::abort_sentence(*reason, detail),
                );
            }
            None => {
                let r = rt_core::bridge::AbortKind::ServiceRestarted;
                result.insert("status".to_owned(), "aborted".to_owned());
                result.insert("abort_reason".to_owned(), r.as_str().to_owned());
                result.insert("reason".to_owned(), crate::records::abort_sentence(r, ""));
            }
        }
        result.insert("finished_unix_s".to_owned(), format!("{:.6}", unix_now_s()));
        result.insert("state_ticks".to_owned(), r.states.to_string());
        let _ = r.writer.write_metadata("result", result);
        let mut world = BTreeMap::new();
        match r.truth_at_release {
            Some((t_s, b)) => {
                // ball = pivot + l (0, sin phi, -cos phi): the pivot's distance and
                // the release angle the simulated world drew.
                let l = self.length_m;
                let phi = (b[1] / l).clamp(-1.0, 1.0).asin();
                world.insert(
                    "source".to_owned(),
                    "simulated world (ground truth)".to_owned(),
                );
                world.insert("distance_m".to_owned(), b[0].to_string());
                world.insert("release_angle_deg".to_owned(), phi.to_degrees().to_string());
                world.insert("first_swing_t_s".to_owned(), t_s.to_string());
            }
            None => {
                world.insert(
                    "source".to_owned(),
                    "none (real lab, or no release)".to_owned(),
                );
            }
        }
        let _ = r.writer.write_metadata("world", world);
        if let Err(e) = r.writer.close() {
            tracing::error!(trial = r.trial_id, error = %e, "cannot finish the MCAP recording");
        }
        Some((r.trial_id, r.path, r.states))
    }
}

/// The width of a baseline or progressive JPEG (its SOF segment), if found.
pub fn jpeg_width(jpeg: &[u8]) -> Option<u32> {
    let mut i = 2;
    while i + 9 < jpeg.len() {
        if jpeg[i] != 0xFF {
            return None;
        }
        let marker = jpeg[i + 1];
        let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
        if matches!(marker, 0xC0..=0xC3) {
            return Some(u32::from(u16::from_be_bytes([jpeg[i + 7], jpeg[i + 8]])));
        }
        i += 2 + len;
    }
    None
}

/// The text of the comment segment `/ws/camera` puts in each JPEG: the frame's
/// number (the `camera.frame` of its detection in the state stream) and its
/// capture time on the control clock.
pub fn frame_tag(frame: u64, t_us: u64) -> String {
    format!("isochron frame={frame} t_us={t_us}")
}

/// `jpeg` with a COM segment (0xFFFE) carrying [`frame_tag`] right after its
/// start-of-image marker: still a valid JPEG (decoders skip comments), and the
/// dashboard pairs the picture with its own detection instead of guessing by
/// arrival time. Bytes that do not start with SOI are passed through unchanged.
pub fn jpeg_tagged(jpeg: &[u8], frame: u64, t_us: u64) -> Vec<u8> {
    if jpeg.len() < 2 || jpeg[..2] != [0xFF, 0xD8] {
        return jpeg.to_vec();
    }
    let text = frame_tag(frame, t_us);
    // The length counts itself (2 bytes) and the text; the text is < 64 bytes.
    let len = (text.len() + 2) as u16;
    let mut out = Vec::with_capacity(jpeg.len() + 4 + text.len());
    out.extend_from_slice(&[0xFF, 0xD8, 0xFF, 0xFE]);
    out.extend_from_slice(&len.to_be_bytes());
    out.extend_from_slice(text.as_bytes());
    out.extend_from_slice(&jpeg[2..]);
    out
}

/// Refuses a Foxglove address that is not loopback: the Foxglove WebSocket
/// protocol carries no credentials, so the service's bearer token cannot guard
/// it, and the service's rule is loopback-only without a token.
///
/// # Errors
///
/// When `addr` is not a loopback address.
pub fn check_addr(addr: std::net::SocketAddr) -> anyhow::Result<()> {
    if !addr.ip().is_loopback() {
        anyhow::bail!(
            "--foxglove {addr}: the Foxglove WebSocket protocol has no authentication, so it \
             listens on loopback only (use e.g. 127.0.0.1:8765 and an SSH tunnel)"
        );
    }
    Ok(())
}

/// Starts the Foxglove WebSocket server on `addr` (loopback only) over the lab's
/// channels; the robot description is also served as the `/robot_description` topic.
///
/// # Errors
///
/// When `addr` is not loopback or the Foxglove server cannot start there.
pub async fn start_server(
    lab: &crate::Lab,
    addr: std::net::SocketAddr,
) -> anyhow::Result<foxglove::WebSocketServerHandle> {
    check_addr(addr)?;
    let handle = foxglove::WebSocketServer::new()
        .name(format!("isochron {}", crate::VERSION))
        .context(lab.foxglove_context())
        .bind(addr.ip().to_string(), addr.port())
        .start()
        .await
        .map_err(|e| anyhow::anyhow!("cannot start the Foxglove server on {addr}: {e}"))?;
    Ok(handle)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rt_core::control::measured::MeasuredStrike;

    fn strike_result(strike: Option<MeasuredStrike>) -> TrialResult {
        TrialResult {
            success: true,
            timing_error_ms: 3.0,
            position_error_m: f64::NAN,
            movement_time_s: 1.5,
            distance_m: 0.7,
            t_star_s: 10.0,
            arrival_t_s: 10.003,
            prediction_time_error_ms: 0.5,
            limit_violations: 0,
            not_judged: None,
            measured: Some(MeasuredJudgement {
                pass_t_s: Some(10.0),
                arrival_t_s: Some(10.003),
                timing_error_ms: Some(3.0),
                timing_std_ms: Some(0.8),
                contact: true,
                contact_t_s: Some(9.99),
                success: true,
                torque_signal: true,
                robot_gap_ms: None,
                camera_clock_error_ms: None,
                camera_clock_error_std_ms: None,
                strike,
            }),
            judged_by: Some(JudgedBy::Measured),
        }
    }

    /// The live recording of a strike trial ends with its strike on
    /// `/trial/strike` (planned and executed tool speed at contact, the
    /// predicted rebound with its curve, the seen outgoing speed), then its
    /// judgement; a stop trial's has no strike message.
    #[test]
    fn a_live_strike_recording_carries_the_strike_before_its_judgement() {
        let dir = tempfile::tempdir().unwrap();
        let predicted = rt_core::control::PredictedRebound::new(0.0, 0.47, 1.8, 9.81 / 1.93, 0.03);
        let strike = MeasuredStrike {
            planned_tool_speed_mps: 0.5,
            tool_speed_mps: Some(0.497),
            target_ball_speed_mps: 0.47,
            ball_speed_mps: Some(0.49),
            ball_speed_std_mps: Some(0.01),
            speed_error: Some(0.04),
            returned: true,
            rebound_used: 11,
            in_time: true,
            speed_ok: true,
            predicted,
        };
        let meta = RecordingContext {
            scenario: "strike".into(),
            parameters_toml: String::new(),
            revision: "test".into(),
            lab_mode: "simulated",
        };
        for (id, k) in [(1u64, Some(strike)), (2, None)] {
            let mut fox = Foxglove::new(&Scenario::default());
            let path = dir.path().join(format!("{id}.mcap"));
            fox.start_recording(id, &path, &meta).unwrap();
            let end = crate::records::TrialEnd::Done(strike_result(k));
            fox.finish_recording(Some(&end)).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let topics: Vec<(String, serde_json::Value)> = mcap::MessageStream::new(&bytes)
                .unwrap()
                .map(|m| {
                    let m = m.unwrap();
                    let j = serde_json::from_slice(&m.data).unwrap_or(serde_json::Value::Null);
                    (m.channel.topic.clone(), j)
                })
                .filter(|(t, _)| t.starts_with("/trial/"))
                .collect();
            let names: Vec<&str> = topics.iter().map(|(t, _)| t.as_str()).collect();
            if k.is_none() {
                assert_eq!(names, [JUDGEMENT_TOPIC], "a stop");
                continue;
            }
            assert_eq!(names, [STRIKE_TOPIC, JUDGEMENT_TOPIC]);
            let j = &topics[0].1;
            assert_eq!(j["trial_id"], 1);
            assert_eq!(j["planned_tool_speed_mps"], 0.5);
            assert_eq!(j["executed_tool_speed_mps"], 0.497);
            assert_eq!(j["seen_ball_speed_mps"], 0.49);
            assert_eq!(j["predicted_ball_speed_mps"], 0.47);
            let curve = j["predicted_curve"].as_array().unwrap();
            assert_eq!(curve.len(), REBOUND_CURVE_POINTS);
            // On the control clock from the measured contact.
            assert_eq!(curve[0]["t_s"], 9.99);
            let peak = curve
                .iter()
                .filter_map(|p| p["lateral_m"].as_f64())
                .fold(f64::NEG_INFINITY, f64::max);
            let amplitude = predicted.map_or(f64::NAN, |p| p.amplitude_m);
            // Sampled: at most the amplitude, within a percent of it.
            assert!(
                peak <= amplitude + 1e-12 && peak > 0.99 * amplitude,
                "{peak} vs {amplitude}"
            );
            let schema = mcap::MessageStream::new(&bytes)
                .unwrap()
                .filter_map(Result::ok)
                .find(|m| m.channel.topic == STRIKE_TOPIC)
                .and_then(|m| m.channel.schema.as_ref().map(|s| s.name.clone()));
            assert_eq!(schema.as_deref(), Some(STRIKE_SCHEMA_NAME));
        }
    }
}
