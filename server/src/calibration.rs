//! The calibration steps as the service runs them (`/api/calibration`, the
//! dashboard's Calibration panel, and `isochron calibrate` through a service
//! on a world): one procedure per step through the lab's own camera, robot
//! and magnet, its result stamped and recorded into the calibration file.

use anyhow::Context;
use rt_core::{
    calibration::{CalibrationFile, Chessboard, StepRecord},
    params::Scenario,
};

/// The steps, in the order a lab runs them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Step {
    /// Camera intrinsics and distortion from a chessboard.
    Camera,
    /// Camera latency by the magnet board's LED.
    Latency,
    /// Pendulum: rest point, free-swing fit (length, damping).
    Pendulum,
    /// The camera's pose in the robot base frame and the intercept point.
    CameraRobot,
    /// Robot command-to-motion latency and servo lag (a small excitation through FRI).
    Robot,
    /// How late the external torques show a contact and how long its pulse
    /// lasts (a knock on the hanging ball; issue #35).
    Contact,
}

impl Step {
    /// Every step, in the order a lab runs them.
    pub const ALL: [Self; 6] = [
        Self::Camera,
        Self::Latency,
        Self::Pendulum,
        Self::CameraRobot,
        Self::Robot,
        Self::Contact,
    ];

    /// The step by its name (`camera-robot`).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// The steps whose results this one builds on: the camera-robot step's
    /// marker is found through the calibrated lens, and its intercept point
    /// is the rest point the pendulum step found; the contact step's knock
    /// is timed by the calibrated pendulum's swing. The pendulum and latency
    /// steps need no camera step: the configuration's focal length and
    /// principal point stand in for it (the swing in the believed plane, the
    /// LED's brightness in its region).
    pub fn prerequisites(self) -> &'static [Self] {
        match self {
            Self::Camera | Self::Robot | Self::Latency | Self::Pendulum => &[],
            // The knock's geometry takes the pendulum's frequency (0.1% of
            // it is 1.3 ms of the result).
            Self::Contact => &[Self::Pendulum],
            Self::CameraRobot => &[Self::Camera, Self::Pendulum],
        }
    }

    /// The names of the prerequisites `file` does not hold yet.
    pub fn missing_in(self, file: &CalibrationFile) -> Vec<&'static str> {
        self.prerequisites()
            .iter()
            .filter(|p| !p.done_in(file))
            .map(|p| p.name())
            .collect()
    }

    /// Whether the calibration file holds this step's result.
    pub fn done_in(self, file: &CalibrationFile) -> bool {
        match self {
            Self::Camera => step_done_camera(file),
            Self::Latency => file.latency.is_some(),
            Self::Pendulum => file.pendulum.is_some(),
            Self::CameraRobot => step_done_camera_robot(file),
            Self::Robot => file.robot.is_some(),
            Self::Contact => file.contact.is_some(),
        }
    }

    /// The step's result in the file, as JSON (null: not calibrated).
    pub fn record_in(self, file: &CalibrationFile) -> serde_json::Value {
        let v = match self {
            Self::Camera => record_camera(file),
            Self::Latency => serde_json::to_value(&file.latency),
            Self::Pendulum => serde_json::to_value(&file.pendulum),
            Self::CameraRobot => record_camera_robot(file),
            Self::Robot => serde_json::to_value(&file.robot),
            Self::Contact => serde_json::to_value(&file.contact),
        };
        v.unwrap_or(serde_json::Value::Null)
    }

    /// What the step measures, for people.
    pub fn title(self) -> &'static str {
        match self {
            Self::Camera => "Camera intrinsics and distortion (chessboard)",
            Self::Latency => "Camera latency (the magnet board's LED)",
            Self::Pendulum => "Pendulum: rest point, length and damping (free swing)",
            Self::CameraRobot => "Camera to robot: camera pose and intercept point (tool marker)",
            Self::Robot => "Robot latency and servo lag (excitation through FRI)",
            Self::Contact => {
                "Contact: how late the external torques show a contact (a knock on the hanging ball)"
            }
        }
    }

    /// The step's name on the command line and in the API.
    pub fn name(self) -> &'static str {
        match self {
            Self::Camera => "camera",
            Self::Latency => "latency",
            Self::Pendulum => "pendulum",
            Self::CameraRobot => "camera-robot",
            Self::Robot => "robot",
            Self::Contact => "contact",
        }
    }
}

/// The acceptance targets (absolute error): pendulum length, m.
pub const TARGET_LENGTH_M: f64 = 0.003;
/// The target for the camera's radial distortion `k1`.
pub const TARGET_K1: f64 = 0.02;
/// The target for the camera latency, ms.
pub const TARGET_CAMERA_LATENCY_MS: f64 = 2.0;
/// The target for the robot latency, ms.
pub const TARGET_ROBOT_LATENCY_MS: f64 = 1.0;
/// The target for the camera's rotation in the base frame, degrees.
pub const TARGET_CAMERA_ROTATION_DEG: f64 = 0.3;
/// The target for the camera's position in the base frame, mm.
pub const TARGET_CAMERA_POSITION_MM: f64 = 5.0;
/// The target for the intercept point, mm.
pub const TARGET_INTERCEPT_MM: f64 = 3.0;
/// The target for the contact step's onset offset, ms (#35 names none:
/// one knock's spread on a truthful world is about 1 ms, the reality
/// world's offsets spread over 2.75 ms).
pub const TARGET_CONTACT_OFFSET_MS: f64 = 3.0;

/// Where a step's result was measured, when, by which software.
pub type Stamp = (String, String, String);

/// What a step gave on the simulated world: its result, the hidden truth and the
/// error (both for the report only; nothing of the truth goes into the file),
/// and how the result goes into the calibration file.
pub struct StepOutcome {
    /// The step's result (as written into the file).
    pub result: serde_json::Value,
    /// The hidden truth of the figures the step estimates.
    pub truth: serde_json::Value,
    /// Estimate minus truth, per figure.
    pub error: serde_json::Value,
    /// The headline figure: (name, estimate, truth, the target).
    pub figure: (&'static str, f64, f64, f64),
    write: Recorder,
}

/// Puts a step's result into the calibration file.
type Recorder = Box<dyn FnOnce(&mut CalibrationFile, Stamp) + Send>;

impl StepOutcome {
    /// Puts the result into `file` (replacing the step's previous result).
    pub fn record_into(self, file: &mut CalibrationFile, stamp: Stamp) {
        (self.write)(file, stamp);
    }
}

/// The pendulum step's outcome from a free swing recorded on the real lab,
/// its detections on the camera's frame grid (`on_frame_grid`: frames a busy
/// host delivered late are stamped at their capture slots): no truth to
/// compare with (`truth` and `error` null).
///
/// # Errors
///
/// When [`on_frame_grid`](rt_core::calibration::swing::on_frame_grid) (frames
/// too irregular) or
/// [`pendulum_from_swing`](rt_core::calibration::swing::pendulum_from_swing)
/// refuses the track ("calibrate pendulum"), or the result cannot be serialised.
pub fn real_pendulum_outcome(
    track: &[rt_core::calibration::swing::TrackedSwingSample],
    scenario: &Scenario,
) -> anyhow::Result<StepOutcome> {
    let p = &scenario.pendulum;
    let track = rt_core::calibration::swing::on_frame_grid(track, 1.0 / scenario.camera.fps)
        .context("calibrate pendulum")?;
    let c = rt_core::calibration::swing::pendulum_from_swing(&track, p.gravity_mps2, p.length_m)
        .context("calibrate pendulum")?;
    Ok(StepOutcome {
        result: serde_json::to_value(&c)?,
        truth: serde_json::Value::Null,
        error: serde_json::Value::Null,
        figure: ("length_m", c.swing.length_m, f64::NAN, TARGET_LENGTH_M),
        write: Box::new(move |file, stamp| {
            file.pendulum = Some(step_record(stamp, c));
        }),
    })
}

/// The camera step's result is in the file.
fn step_done_camera(file: &CalibrationFile) -> bool {
    file.camera.is_some()
}

/// The camera-to-robot step's result is in the file.
fn step_done_camera_robot(file: &CalibrationFile) -> bool {
    file.camera_robot.is_some()
}

/// The camera step's record as JSON.
fn record_camera(file: &CalibrationFile) -> serde_json::Result<serde_json::Value> {
    serde_json::to_value(&file.camera)
}

/// The camera-to-robot step's record as JSON.
fn record_camera_robot(file: &CalibrationFile) -> serde_json::Result<serde_json::Value> {
    serde_json::to_value(&file.camera_robot)
}

/// `date` as RFC 3339 UTC, from the system clock.
pub fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let days = i64::try_from(secs / 86_400).unwrap_or(0);
    let rem = secs % 86_400;
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        (rem / 60) % 60,
        rem % 60
    )
}

/// The stamp of a result measured now on `source`: the UTC date, this
/// software's version and revision, and where.
pub fn stamp(source: &str) -> Stamp {
    (utc_now(), crate::VERSION.to_owned(), source.to_owned())
}

fn step_record<T>((date, revision, source): Stamp, result: T) -> StepRecord<T> {
    StepRecord {
        date,
        revision,
        source,
        result,
    }
}

/// A step's state in `GET /api/calibration`.
#[derive(Debug, Clone, serde::Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct StepStatus {
    /// The step's name (`camera-robot`), as in `POST /api/calibration/{step}`.
    pub name: String,
    /// What it measures.
    pub title: String,
    /// The steps it builds on.
    pub prerequisites: Vec<String>,
    /// Of those, the ones the calibration file does not hold yet (the step is
    /// refused while any is missing).
    pub missing: Vec<String>,
    /// The file holds this step's result.
    pub done: bool,
    /// The step's record in the file (date, revision, source, result), or null.
    #[ts(type = "Record<string, unknown> | null")]
    #[schema(value_type = Option<Object>)]
    pub record: serde_json::Value,
}

/// The running or last calibration job.
#[derive(Debug, Clone, Default, serde::Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct CalibrationJob {
    /// The step (null: none has run since the service started).
    pub step: Option<String>,
    /// `idle`, `running`, `done` or `failed`.
    pub state: String,
    /// Fraction done, 0..=1.
    pub progress: f64,
    /// What the step is doing, or why it failed.
    pub message: String,
    /// What the step sees now (its last view), or null.
    pub view: Option<rt_core::calibration::StepView>,
    /// The result written (done), or null.
    #[ts(type = "Record<string, unknown> | null")]
    #[schema(value_type = Option<Object>)]
    pub result: Option<serde_json::Value>,
    /// Every number of the result that differs from the previous calibration
    /// of this step (empty: the first, or nothing changed).
    pub changes: Vec<Change>,
    /// The file had no result of this step before (done).
    pub first: bool,
    /// Job number since the service started (also the simulated world's noise seed).
    #[ts(type = "number")]
    pub id: u64,
}

/// One number of a step's result: before and after.
#[derive(Debug, Clone, PartialEq, serde::Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct Change {
    /// Dotted key in the step's result (`swing.length_m`).
    pub key: String,
    /// The previous calibration's value.
    pub before: f64,
    /// The new value.
    pub after: f64,
}

/// `GET /api/calibration`.
#[derive(Debug, Clone, serde::Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct CalibrationStatus {
    /// The calibration file the lab loads and the steps write.
    pub file: String,
    /// Where the steps run (`simulated world (truthful: the lab's own simulators)`, or
    /// the real lab).
    pub source: String,
    /// The steps in the order a lab runs them.
    pub steps: Vec<StepStatus>,
    /// The running or last job.
    pub job: CalibrationJob,
    /// Why trials are refused for want of calibration (null: they are not).
    pub trials_refused: Option<String>,
}

/// Every number in `before` and `after` (objects walked, arrays by index) that
/// differs, by dotted key; keys missing on either side are skipped.
pub fn changes(before: &serde_json::Value, after: &serde_json::Value) -> Vec<Change> {
    fn walk(a: &serde_json::Value, b: &serde_json::Value, key: String, out: &mut Vec<Change>) {
        use serde_json::Value as V;
        match (a, b) {
            (V::Object(x), V::Object(y)) => {
                for (k, vb) in y {
                    if let Some(va) = x.get(k) {
                        let key = if key.is_empty() {
                            k.clone()
                        } else {
                            format!("{key}.{k}")
                        };
                        walk(va, vb, key, out);
                    }
                }
            }
            (V::Array(x), V::Array(y)) => {
                for (i, (va, vb)) in x.iter().zip(y).enumerate() {
                    walk(va, vb, format!("{key}[{i}]"), out);
                }
            }
            (V::Number(x), V::Number(y)) => {
                if let (Some(x), Some(y)) = (x.as_f64(), y.as_f64())
                    && x != y
                {
                    out.push(Change {
                        key,
                        before: x,
                        after: y,
                    });
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(before, after, String::new(), &mut out);
    out
}

/// Why a step cannot start.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StartRefused {
    /// Another step runs.
    #[error("calibration step {0} is running; wait for it to finish")]
    Busy(String),
    /// A prerequisite's result is missing from the file.
    #[error("calibrate {step} needs {missing} first (the calibration file has no result of it)")]
    Prerequisites {
        /// The step asked for.
        step: String,
        /// The missing steps, comma-separated.
        missing: String,
    },
    /// The lab cannot run the step here.
    #[error("{0}")]
    NotAvailable(String),
}

/// Decides whether the lab must refuse trials with this calibration file.
pub type RefusalRule = Box<dyn Fn(&CalibrationFile) -> Option<String> + Send + Sync>;

/// The service's calibration desk: the file, the job, the refusal of trials.
pub struct CalibrationDesk {
    path: std::path::PathBuf,
    rule: RefusalRule,
    job: std::sync::Mutex<CalibrationJob>,
    refused: std::sync::Mutex<Option<String>>,
    /// From a step's start over the API until the lab has taken its result
    /// (the job says `done` a moment before the control loop has the new beliefs).
    taking: std::sync::atomic::AtomicBool,
    /// A real lab's `[calibration]` (what it believes of its camera and
    /// pendulum before the steps: the camera-robot step starts from it).
    geometry: std::sync::OnceLock<crate::config::Calibration>,
    /// What the steps run on, as a record says it (a real lab's default:
    /// "the real lab"; [`Self::named`]).
    source: Option<String>,
}

impl std::fmt::Debug for CalibrationDesk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CalibrationDesk")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl CalibrationDesk {
    /// A desk over the calibration file at `path` (it need not exist yet); `rule`
    /// says when trials are refused. The steps run through the lab's own
    /// robot, camera and magnet.
    pub fn new(path: std::path::PathBuf, rule: RefusalRule) -> Self {
        let file = CalibrationFile::load_or_empty(&path).unwrap_or_default();
        let refused = rule(&file);
        Self {
            path,
            rule,
            job: std::sync::Mutex::new(CalibrationJob {
                state: "idle".into(),
                ..CalibrationJob::default()
            }),
            refused: std::sync::Mutex::new(refused),
            taking: std::sync::atomic::AtomicBool::new(false),
            geometry: std::sync::OnceLock::new(),
            source: None,
        }
    }

    /// The desk of a lab whose steps run on `source` (a record's `source`
    /// and the status's): the simulated lab's world behind a real lab's
    /// interfaces says which world it is.
    #[must_use]
    pub fn named(mut self, source: impl Into<String>) -> Self {
        self.source = Some(source.into());
        self
    }

    /// What the steps run on, as records say it.
    pub fn source(&self) -> &str {
        match &self.source {
            Some(s) => s,
            None => "the real lab",
        }
    }

    /// Gives a real lab's `[calibration]` (set once, at the start).
    pub fn set_lab_geometry(&self, k: crate::config::Calibration) {
        let _ = self.geometry.set(k);
    }

    /// A real lab's `[calibration]`, when given.
    pub fn lab_geometry(&self) -> Option<&crate::config::Calibration> {
        self.geometry.get()
    }

    /// The calibration file.
    pub fn path(&self) -> &std::path::Path {
        &self.path
    }

    /// Why trials are refused now (none: allowed).
    pub fn trials_refused(&self) -> Option<String> {
        lock(&self.refused).clone()
    }

    /// A step runs, or the lab has not yet taken the result of the one that
    /// just ended ([`Self::set_taking`]): trials wait for both.
    pub fn running(&self) -> bool {
        self.taking.load(std::sync::atomic::Ordering::Acquire) || lock(&self.job).state == "running"
    }

    /// Marks a step started over the API (`true`) until the lab has taken its
    /// result, or the step gave none (`false`).
    pub fn set_taking(&self, on: bool) {
        self.taking.store(on, std::sync::atomic::Ordering::Release);
    }

    /// The file's steps and the job.
    ///
    /// # Errors
    ///
    /// The [`ParamError`](rt_core::params::ParamError) of
    /// [`CalibrationFile::load_or_empty`] when the file cannot be read or parsed.
    pub fn status(&self) -> Result<CalibrationStatus, rt_core::params::ParamError> {
        let file = CalibrationFile::load_or_empty(&self.path)?;
        let steps = Step::ALL
            .iter()
            .map(|&s| StepStatus {
                name: s.name().into(),
                title: s.title().into(),
                prerequisites: s.prerequisites().iter().map(|p| p.name().into()).collect(),
                missing: s.missing_in(&file).into_iter().map(Into::into).collect(),
                done: s.done_in(&file),
                record: s.record_in(&file),
            })
            .collect();
        Ok(CalibrationStatus {
            file: self.path.display().to_string(),
            source: self.source().into(),
            steps,
            job: lock(&self.job).clone(),
            trials_refused: self.trials_refused(),
        })
    }

    /// Claims the job for `step` if nothing runs, the prerequisites are in the
    /// file and the lab can run it; returns the job's number.
    ///
    /// # Errors
    ///
    /// [`StartRefused::NotAvailable`] when the file cannot be read; [`StartRefused::Prerequisites`] when steps it needs are
    /// missing; [`StartRefused::Busy`] while another step runs.
    pub fn claim(&self, step: Step) -> Result<u64, StartRefused> {
        let file = CalibrationFile::load_or_empty(&self.path)
            .map_err(|e| StartRefused::NotAvailable(format!("the calibration file: {e}")))?;
        let missing = step.missing_in(&file);
        if !missing.is_empty() {
            return Err(StartRefused::Prerequisites {
                step: step.name().into(),
                missing: missing.join(", "),
            });
        }
        let mut job = lock(&self.job);
        if job.state == "running" {
            return Err(StartRefused::Busy(job.step.clone().unwrap_or_default()));
        }
        let id = job.id + 1;
        *job = CalibrationJob {
            step: Some(step.name().into()),
            state: "running".into(),
            progress: 0.0,
            message: format!("{} ...", step.title()),
            id,
            ..CalibrationJob::default()
        };
        Ok(id)
    }

    /// Shows what the running job `id` sees.
    pub fn progress(&self, id: u64, view: rt_core::calibration::StepView) {
        let mut job = lock(&self.job);
        if job.id == id {
            job.progress = view.progress.clamp(0.0, 1.0);
            job.message.clone_from(&view.message);
            job.view = Some(view);
        }
    }

    /// Ends job `id` with the step's outcome measured on `source`: a result is
    /// written into the file (atomically, validated against the scenario) and
    /// the lab's beliefs with it are returned; on failure the file is
    /// unchanged and the job says why.
    pub fn conclude(
        &self,
        id: u64,
        step: Step,
        scenario: &Scenario,
        outcome: anyhow::Result<StepOutcome>,
        source: &str,
    ) -> Option<Scenario> {
        let outcome = (|| -> anyhow::Result<(Scenario, serde_json::Value, Vec<Change>, bool)> {
            let out = outcome?;
            let mut file = CalibrationFile::load_or_empty(&self.path)?;
            let before = step.record_in(&file);
            let result = out.result.clone();
            out.record_into(&mut file, stamp(source));
            let beliefs = file
                .apply(scenario)
                .with_context(|| format!("calibrate {}: the result", step.name()))?;
            file.write(&self.path)?;
            let after = step.record_in(&file);
            let first = before.is_null();
            let changes = if first {
                Vec::new()
            } else {
                changes(&before["result"], &after["result"])
            };
            *lock(&self.refused) = (self.rule)(&file);
            Ok((beliefs, result, changes, first))
        })();
        let mut job = lock(&self.job);
        if job.id != id {
            // Not this job's to end (claimed jobs run one at a time).
            return None;
        }
        match outcome {
            Ok((beliefs, result, changes, first)) => {
                job.state = "done".into();
                job.progress = 1.0;
                job.result = Some(result);
                job.changes = changes;
                job.first = first;
                Some(beliefs)
            }
            Err(e) => {
                job.state = "failed".into();
                job.message = format!("{e:#}");
                None
            }
        }
    }

    /// Ends the job `id` with a message (the lab could not take the result).
    pub fn note(&self, id: u64, message: String) {
        let mut job = lock(&self.job);
        if job.id == id {
            job.message = message;
        }
    }
}

/// How long the real lab's pendulum step records the free swing, seconds.
pub const REAL_SWING_RECORD_S: f64 = 20.0;
/// How long the real lab's pendulum step waits for the ball held on the magnet, seconds.
pub const REAL_HOLD_WAIT_S: f64 = 60.0;
/// Time given to hang the ball before a ball the camera does not see counts
/// as held out of its view, seconds.
pub const HANG_TIME_S: f64 = 5.0;
/// How long the real-lab pendulum step waits for the camera's first
/// [`CAMERA_WAIT_FRAMES`] frames before it hangs the ball, seconds.
pub const CAMERA_WAIT_S: f64 = 10.0;
/// Frames the camera must deliver before the pendulum step hangs the ball.
pub const CAMERA_WAIT_FRAMES: usize = 10;
/// No detection for this long (after [`HANG_TIME_S`]): the ball is held out
/// of the camera's view, seconds.
pub const HELD_UNSEEN_S: f64 = 3.0;

/// The pendulum step on the real lab, through its own robot, camera and
/// magnet (job `id`, claimed): the arm moves home, out of the swing (arm,
/// then disarm: an operator's heartbeat must come meanwhile when the lab's
/// dead-man is on), the camera must deliver [`CAMERA_WAIT_FRAMES`] frames
/// within [`CAMERA_WAIT_S`], the magnet is switched on and the step waits (at most
/// [`REAL_HOLD_WAIT_S`]) until the camera sees the ball held still at least
/// 5 cm from the rest point, at least [`HANG_TIME_S`] after the magnet went
/// on (an operator hangs it there: the job's message says so, with the
/// angle when the step was given one; held still nearer is refused then as
/// a swing too small), or, after [`HANG_TIME_S`], sees no ball for [`HELD_UNSEEN_S`]
/// (held out of its view); then the magnet lets go and the free swing is recorded for
/// `record_s` (the lab's detections: capture time, lateral on the believed
/// plane, image centre) and fitted ([`real_pendulum_outcome`]). Refused,
/// nothing written, when the camera or the magnet does not deliver, the ball
/// is never seen held, or the fit refuses the swing.
pub async fn run_real_pendulum(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
    record_s: f64,
    release_deg: Option<f64>,
) -> Option<Scenario> {
    use rt_core::bridge::Command;
    use rt_core::calibration::{StepView, ViewKind, swing::TrackedSwingSample};
    use std::time::{Duration, Instant};
    let view = |progress: f64, message: String, track: &[TrackedSwingSample]| StepView {
        progress,
        message,
        kind: ViewKind::Series,
        points: rt_core::calibration::view::thin(
            &track
                .iter()
                .map(|s| [s.t_s, s.lateral_m])
                .collect::<Vec<_>>(),
            400,
        ),
        fit: Vec::new(),
    };
    let outcome = async {
        if let Some(p) = lab.device_problems().into_iter().find(|p| p.device != "robot") {
            anyhow::bail!("calibrate pendulum: {}", p.message);
        }
        // 0. The arm out of the swing: armed (home, in the coming motion's
        // posture, the magnet on), then disarmed where it stands.
        desk.progress(
            id,
            view(
                0.01,
                "moving the arm home, out of the ball's swing (arm, then disarm)".into(),
                &[],
            ),
        );
        // A robot that leaves commanding on the way (the move ends where it
        // is; the lab asks it to command again) is sent home again once it
        // commands, [`MOVE_RESENDS`] times at most (as the tour's moves).
        let mut tries = 0;
        'home: loop {
            tries += 1;
            if tries > 1 {
                robot_commands_again(lab).await.map_err(|why| {
                    anyhow::anyhow!(
                        "calibrate pendulum: moving the arm home was stopped and the robot did \
                         not command again within {RECOMMAND_WAIT_S:.0} s ({why}): nothing \
                         written; run the step again"
                    )
                })?;
            }
            lab.command(Command::Arm).await.map_err(|e| {
                anyhow::anyhow!(
                    "calibrate pendulum: the arm must move home first, out of the swing: {e}"
                )
            })?;
            // The acknowledgement comes before the next state: what the lab
            // published until then is from before the command.
            let acked = lab.latest().map_or(0, |(s, _)| s.counters.steps);
            let deadline = Instant::now() + Duration::from_secs(60);
            loop {
                match lab
                    .latest()
                    .filter(|(s, _)| s.counters.steps > acked)
                    .map(|(s, _)| (s.trial_state, s.abort))
                {
                    Some((rt_core::bridge::TrialState::Armed, _)) => break 'home,
                    Some((rt_core::bridge::TrialState::Aborted, abort))
                        if abort.reason == Some(rt_core::bridge::AbortKind::FriLost)
                            && tries <= MOVE_RESENDS as usize =>
                    {
                        desk.progress(
                            id,
                            view(
                                0.01,
                                format!(
                                    "moving the arm home was stopped ({}): sending it home again \
                                     once the robot commands ({} of {MOVE_RESENDS})",
                                    abort.message,
                                    tries
                                ),
                                &[],
                            ),
                        );
                        continue 'home;
                    }
                    Some((rt_core::bridge::TrialState::Aborted, abort)) => anyhow::bail!(
                        "calibrate pendulum: moving the arm home was stopped: {} (nothing \
                         written; run the step again)",
                        abort.message
                    ),
                    _ if Instant::now() > deadline => {
                        anyhow::bail!("calibrate pendulum: the arm did not reach home within 60 s")
                    }
                    _ => tokio::time::sleep(Duration::from_millis(20)).await,
                }
            }
        }
        lab.command(Command::Disarm)
            .await
            .map_err(|e| anyhow::anyhow!("calibrate pendulum: disarm: {e}"))?;
        let mut next = camera_detections(lab);
        // The camera must deliver before the ball is hung: a swing recorded
        // while it does not is a swing never seen.
        let wait_from = Instant::now();
        let mut frames = 0_usize;
        while frames < CAMERA_WAIT_FRAMES {
            if wait_from.elapsed().as_secs_f64() > CAMERA_WAIT_S {
                anyhow::bail!(
                    "calibrate pendulum: the camera delivered {frames} frames in {CAMERA_WAIT_S:.0} s \
                     (GET /api/health's devices says why)"
                );
            }
            if next().is_some() {
                frames += 1;
            }
            tokio::time::sleep(Duration::from_millis(4)).await;
        }
        // 1. The ball held on the magnet, away from the rest point.
        let min_cm = rt_core::calibration::swing::MIN_AMPLITUDE_M * 100.0;
        desk.progress(
            id,
            view(
                0.02,
                match release_deg {
                    Some(d) => format!(
                        "magnet on: {}; the swing is recorded when it lets go",
                        hang_prompt(d)
                    ),
                    None => format!(
                        "magnet on: hang the ball on the magnet (at least {min_cm:.0} cm from where \
                         it hangs at rest); the swing is recorded when it lets go"
                    ),
                },
                &[],
            ),
        );
        lab.command(Command::Magnet { on: true })
            .await
            .map_err(|e| anyhow::anyhow!("calibrate pendulum: the magnet: {e}"))?;
        let on_at = Instant::now();
        let deadline = on_at + Duration::from_secs_f64(REAL_HOLD_WAIT_S);
        let mut last_seen = on_at;
        let mut recent = std::collections::VecDeque::<TrackedSwingSample>::default();
        loop {
            // Held where the camera does not see it (a magnet at the view's
            // edge): no detection for HELD_UNSEEN_S, at least HANG_TIME_S
            // after the magnet went on. An empty magnet shows in the
            // recording: no swing, refused.
            let now = Instant::now();
            if now.duration_since(on_at).as_secs_f64() >= HANG_TIME_S
                && now.duration_since(last_seen).as_secs_f64() >= HELD_UNSEEN_S
            {
                break;
            }
            if let Some(Some(s)) = next() {
                last_seen = Instant::now();
                recent.push_back(s);
                while recent.front().is_some_and(|f| s.t_s - f.t_s > 1.0) {
                    recent.pop_front();
                }
                let (lo, hi) = recent.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
                    (a.min(r.lateral_m), b.max(r.lateral_m))
                });
                let span_s = recent.back().map_or(0.0, |b| b.t_s) - recent.front().map_or(0.0, |f| f.t_s);
                // Held still, given the person HANG_TIME_S to hang it
                // (a ball still held from the arm's move home is not yet
                // where this prompt asks).
                let still = recent.len() >= 8
                    && span_s >= 0.8
                    && hi - lo < 0.003
                    && now.duration_since(on_at).as_secs_f64() >= HANG_TIME_S;
                let out_m = lo.abs().min(hi.abs());
                if still && out_m >= rt_core::calibration::swing::MIN_AMPLITUDE_M {
                    break;
                }
                if still {
                    // Hung, and held too near the rest point: its swing
                    // would be too small to fit. Refused now, not after
                    // the whole wait.
                    let _ = lab.command(Command::Magnet { on: false }).await;
                    return Err(rt_core::calibration::CalibrationError::SwingTooSmall {
                        amplitude_m: out_m,
                        min_m: rt_core::calibration::swing::MIN_AMPLITUDE_M,
                    }
                    .into());
                }
            }
            if Instant::now() > deadline {
                let _ = lab.command(Command::Magnet { on: false }).await;
                anyhow::bail!(
                    "calibrate pendulum: the ball moved in view for {REAL_HOLD_WAIT_S:.0} s and was \
                     never held still on the magnet at least {:.0} cm from the rest point (is it hung \
                     on the magnet, and the pendulum otherwise still?)",
                    rt_core::calibration::swing::MIN_AMPLITUDE_M * 100.0
                );
            }
            tokio::time::sleep(Duration::from_millis(4)).await;
        }
        // 2. The free swing.
        lab.command(Command::Magnet { on: false })
            .await
            .map_err(|e| anyhow::anyhow!("calibrate pendulum: the magnet: {e}"))?;
        let start = Instant::now();
        let mut track = Vec::new();
        let mut frames = 0_usize;
        let mut shown = 0.0;
        while start.elapsed().as_secs_f64() < record_s {
            match next() {
                Some(Some(s)) => {
                    frames += 1;
                    track.push(s);
                }
                Some(None) => frames += 1,
                None => {}
            }
            let t = start.elapsed().as_secs_f64();
            if t - shown >= 1.0 {
                shown = t;
                desk.progress(
                    id,
                    view(
                        0.05 + 0.9 * t / record_s,
                        format!("free swing: {t:.0} of {record_s:.0} s recorded, {} detections", track.len()),
                        &track,
                    ),
                );
            }
            tokio::time::sleep(Duration::from_millis(4)).await;
        }
        real_pendulum_outcome(&track, scenario).map_err(|e| {
            anyhow::anyhow!(
                "{e:#} (the camera's frames in the free swing: {frames}, the ball found in {})",
                track.len()
            )
        })
    }
    .await;
    desk.conclude(id, Step::Pendulum, scenario, outcome, desk.source())
}

/// The lab's camera frames from now on, one call each: `None` while no new
/// frame came, `Some(None)` for a frame without the ball, `Some(Some(d))`
/// for one with it (its capture time, lateral position and pixel).
fn camera_detections(
    lab: &crate::Lab,
) -> impl FnMut() -> Option<Option<rt_core::calibration::swing::TrackedSwingSample>> + '_ {
    use rt_core::calibration::swing::TrackedSwingSample;
    let mut last_frame = lab.latest().map_or(0, |(s, _)| s.camera.frame);
    move || {
        let (s, _) = lab.latest()?;
        if s.camera.frame == last_frame {
            return None;
        }
        last_frame = s.camera.frame;
        let m = s.pendulum.measured;
        Some(
            (s.camera.found && m.valid && m.t_s == s.camera.t_s).then_some(TrackedSwingSample {
                t_s: m.t_s,
                lateral_m: m.x_m,
                px: [s.camera.x_px, s.camera.y_px],
            }),
        )
    }
}

/// What the pendulum step asks of the person who hangs the ball when the
/// release angle is given (`POST /api/calibration/pendulum
/// {"release_deg": D}`); the simulated lab's hands read it back
/// ([`crate::world::asked_hang_deg`]).
pub fn hang_prompt(release_deg: f64) -> String {
    format!("hang the ball on the magnet {release_deg:.1} deg out")
}

/// Board views the real-lab camera step asks for.
pub const REAL_CAMERA_VIEWS: usize = 16;
/// How long the real-lab camera step waits for the board held still at one
/// pose, seconds (then the pose is skipped; at the first pose without any
/// board seen, the step is refused).
pub const REAL_BOARD_WAIT_S: f64 = 20.0;
/// Held still: no corner moved more than this between two frames, pixels.
pub const BOARD_STILL_PX: f64 = 0.5;
/// A new pose: its corners at least this far (mean) from the last view's, pixels.
pub const BOARD_NEW_POSE_PX: f64 = 20.0;

/// The camera step on the real lab, through its own camera (job `id`,
/// claimed): for each of [`REAL_CAMERA_VIEWS`] poses the job's message asks
/// for the chessboard (9 x 6 inner corners, 30 mm squares) held still there;
/// full-resolution frames are taken until two in a row show its corners
/// within [`BOARD_STILL_PX`] of each other and at least [`BOARD_NEW_POSE_PX`]
/// from the last view's (an operator moved it); then the corners of all views
/// are fitted (`fit_intrinsics`). A pose where the board is not seen held
/// still within [`REAL_BOARD_WAIT_S`] is skipped. Refused, nothing written,
/// when the camera does not deliver, no board is seen at all within
/// [`REAL_BOARD_WAIT_S`] of the first pose, or the fit refuses the views
/// (fewer than 8 seen).
pub async fn run_real_camera(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> Option<Scenario> {
    let outcome = real_camera(lab, desk, id).await;
    desk.conclude(id, Step::Camera, scenario, outcome, desk.source())
}

/// Asks the vision thread for its next full-resolution frame and waits for it.
async fn take_still(
    stills: &rt_core::lab::StillSlot,
    timeout: std::time::Duration,
    colour: bool,
) -> anyhow::Result<rt_core::lab::Still> {
    let start = std::time::Instant::now();
    if colour {
        stills.request_colour();
    } else {
        stills.request();
    }
    loop {
        if let Some(s) = stills.take() {
            return Ok(s);
        }
        if start.elapsed() > timeout {
            anyhow::bail!(
                "the camera delivered no frame in {:.0} s (GET /api/health's devices says why)",
                timeout.as_secs_f64()
            );
        }
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    }
}

/// The largest and the mean distance between two views' corners, pixels.
fn corner_shift_px(a: &[[f64; 2]], b: &[[f64; 2]]) -> (f64, f64) {
    let d: Vec<f64> = a
        .iter()
        .zip(b)
        .map(|(p, q)| (p[0] - q[0]).hypot(p[1] - q[1]))
        .collect();
    let max = d.iter().copied().fold(0.0, f64::max);
    (max, d.iter().sum::<f64>() / d.len().max(1) as f64)
}

async fn real_camera(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
) -> anyhow::Result<StepOutcome> {
    use rt_core::calibration::intrinsics::detect_corners;
    use rt_core::calibration::{BoardView, StepView, ViewKind, fit_intrinsics};
    use std::time::{Duration, Instant};
    let devices = lab
        .devices()
        .context("calibrate camera: the lab's devices have not started")?;
    let Some(stills) = devices.stills.clone() else {
        anyhow::bail!("calibrate camera: this lab's camera gives no full frames");
    };
    if let Some(p) = lab
        .device_problems()
        .into_iter()
        .find(|p| p.device == "camera")
    {
        anyhow::bail!("calibrate camera: {}", p.message);
    }
    let board = Chessboard::default();
    let views = REAL_CAMERA_VIEWS;
    let mut seen: Vec<BoardView> = Vec::with_capacity(views);
    let mut size = (0_u32, 0_u32);
    let mut last_view: Option<Vec<[f64; 2]>> = None;
    let mut seen_any = false;
    for k in 0..views {
        let prompt = format!(
            "hold the chessboard ({} x {} inner corners, {:.0} mm squares) still at pose {} of \
             {views}: all of it in view, somewhere else in the image than the last, tilted \
             another way",
            board.inner_cols,
            board.inner_rows,
            board.square_m * 1e3,
            k + 1
        );
        desk.progress(
            id,
            StepView {
                progress: k as f64 / (views + 1) as f64,
                message: prompt,
                kind: ViewKind::Image,
                points: last_view.clone().unwrap_or_default(),
                fit: Vec::new(),
            },
        );
        let deadline = Instant::now() + Duration::from_secs_f64(REAL_BOARD_WAIT_S);
        let (mut frames, mut found) = (0_usize, 0_usize);
        let mut previous: Option<Vec<[f64; 2]>> = None;
        let corners = loop {
            if Instant::now() > deadline {
                break None;
            }
            let still = take_still(&stills, Duration::from_secs(5), false)
                .await
                .context("calibrate camera")?;
            size = (still.width_px, still.height_px);
            let c = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
                Ok(detect_corners(&still.to_gray_mat()?, &board)?)
            })
            .await
            .context("calibrate camera: the corner search")??;
            frames += 1;
            let Some(c) = c else {
                previous = None;
                continue;
            };
            found += 1;
            let new_pose = last_view
                .as_ref()
                .is_none_or(|l| corner_shift_px(&c, l).1 >= BOARD_NEW_POSE_PX);
            let still_held = previous
                .as_ref()
                .is_some_and(|p| corner_shift_px(&c, p).0 <= BOARD_STILL_PX);
            if new_pose && still_held {
                break Some(c);
            }
            previous = Some(c);
        };
        seen_any |= found > 0;
        if corners.is_none() && !seen_any {
            anyhow::bail!(
                "calibrate camera: no chessboard ({} x {} inner corners) seen at pose {} of {views} \
                 in {REAL_BOARD_WAIT_S:.0} s ({frames} frames looked at)",
                board.inner_cols,
                board.inner_rows,
                k + 1
            );
        }
        // A pose where the board was not seen held still is skipped (the
        // fit needs enough of the others).
        seen.push(BoardView {
            corners_px: corners.clone(),
        });
        if corners.is_some() {
            last_view = corners;
        }
    }
    let fit = fit_intrinsics(&board, &seen, size.0, size.1).context("calibrate camera")?;
    for v in fit.views(&seen, views) {
        desk.progress(id, v);
    }
    let result = fit.calibration;
    Ok(StepOutcome {
        result: serde_json::to_value(&result)?,
        truth: serde_json::Value::Null,
        error: serde_json::Value::Null,
        figure: ("k1", result.intrinsics.k1, f64::NAN, TARGET_K1),
        write: Box::new(move |file, stamp| {
            file.camera = Some(step_record(stamp, result));
        }),
    })
}

/// Switches of the LED the real-lab latency step makes.
pub const REAL_LED_SWITCHES: usize = 40;
/// How long the real-lab latency step watches the frames before its first
/// switch (the frame grid), seconds.
pub const REAL_LED_GRID_S: f64 = 2.0;

/// The latency step on the real lab, through its own camera and magnet
/// board (job `id`, claimed): the LED off, the frames' delivery times
/// watched for [`REAL_LED_GRID_S`] (the frame grid), then
/// [`REAL_LED_SWITCHES`] switches sent at random phases of the frame period
/// (`latency::plan_switches`), each stamped when the driver wrote it, with
/// its round trip and both lines' wire times; the LED region's brightness
/// in every frame (`calibration.led_px`, read by the vision thread) bounds
/// the camera's exposure -> delivery latency (`estimate_led_latency`).
/// Refused, nothing written, without `calibration.led_px`, when the camera
/// or the board does not deliver, or when the camera never sees the LED
/// switch.
pub async fn run_real_latency(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> Option<Scenario> {
    let outcome = real_latency(lab, desk, id, scenario).await;
    desk.conclude(id, Step::Latency, scenario, outcome, desk.source())
}

async fn real_latency(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> anyhow::Result<StepOutcome> {
    use rand::{RngExt, SeedableRng};
    use rt_core::calibration::latency::{LedEdge, LedFrame, estimate_led_latency, plan_switches};
    use rt_core::calibration::{StepView, ViewKind};
    use rt_core::magnet::OkReply;
    use std::time::Duration;
    let devices = lab
        .devices()
        .context("calibrate latency: the lab's devices have not started")?;
    let (Some(feed), Some(magnet), Some(epoch)) =
        (devices.led.clone(), devices.magnet.clone(), devices.epoch)
    else {
        anyhow::bail!(
            "calibrate latency: the lab configuration does not say where the magnet board's LED \
             shows in the camera's image: set [calibration] led_px = [column, row, radius] in pixels"
        );
    };
    if let Some(p) = lab
        .device_problems()
        .into_iter()
        .find(|p| p.device != "robot")
    {
        anyhow::bail!("calibrate latency: {}", p.message);
    }
    let now_s = move || epoch.elapsed().as_secs_f64();
    let period_s = 1.0 / scenario.camera.fps;
    let view = |progress: f64, message: String, frames: &[LedFrame]| StepView {
        progress,
        message,
        kind: ViewKind::Series,
        points: rt_core::calibration::view::thin(
            &frames
                .iter()
                .map(|f| [f.t_delivered_s, f.brightness])
                .collect::<Vec<_>>(),
            600,
        ),
        fit: Vec::new(),
    };
    let switch = |on: bool| {
        let magnet = magnet.clone();
        async move {
            tokio::task::spawn_blocking(move || magnet.set_led(on).map(|a| (a, magnet)))
                .await
                .context("calibrate latency: the magnet board's thread")?
                .map_err(|e| anyhow::anyhow!("calibrate latency: the LED: {e}"))
        }
    };
    let mut readings = Vec::new();
    let mut frames: Vec<LedFrame> = Vec::new();
    let mut take = |frames: &mut Vec<LedFrame>| {
        readings.clear();
        feed.drain(&mut readings);
        frames.extend(readings.iter().map(|r| LedFrame {
            t_delivered_s: r.t_delivered_s,
            brightness: r.level,
        }));
    };
    // 1. The LED off (asked up to three times: a starved board may miss
    // one answer); the frame grid.
    let mut tries = 0;
    while let Err(e) = switch(false).await {
        tries += 1;
        if tries == 3 {
            return Err(e);
        }
    }
    take(&mut Vec::new());
    desk.progress(
        id,
        view(0.02, "LED off: watching the camera's frames".into(), &[]),
    );
    let t0 = now_s();
    while now_s() - t0 < REAL_LED_GRID_S {
        tokio::time::sleep(Duration::from_millis(10)).await;
        take(&mut frames);
    }
    if frames.len() < 10 {
        anyhow::bail!(
            "calibrate latency: the camera delivered {} frames in {REAL_LED_GRID_S:.0} s \
             (is the LED's region in the image? calibration.led_px = {:?})",
            frames.len(),
            feed.roi_px()
        );
    }
    let deliveries: Vec<f64> = frames.iter().map(|f| f.t_delivered_s).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(id ^ 0x1ed);
    let sends = plan_switches(&deliveries, period_s, REAL_LED_SWITCHES, || {
        rng.random_range(0.0..1.0)
    });
    // 2. The switches at their planned times.
    let mut edges = Vec::with_capacity(sends.len());
    let mut unanswered = 0;
    for (i, &t) in sends.iter().enumerate() {
        let on = i % 2 == 0;
        loop {
            take(&mut frames);
            let left = t - now_s();
            if left <= 0.0 {
                break;
            }
            tokio::time::sleep(Duration::from_secs_f64(left.min(0.01))).await;
        }
        // A switch the board did not answer in time (a starved machine) is
        // left out: the frames around it then show no clean edge of the
        // switches recorded, which the estimate drops; most must answer.
        let (a, m) = match switch(on).await {
            Ok(r) => r,
            Err(e) => {
                unanswered += 1;
                if unanswered * 2 > sends.len() {
                    return Err(e.context(format!(
                        "calibrate latency: {unanswered} of {} LED switches were not answered",
                        i + 1
                    )));
                }
                continue;
            }
        };
        let uptime_ms = match a.reply {
            OkReply::Led { uptime_ms, .. } => uptime_ms,
            _ => 0,
        };
        let command = if on { "LED ON\n" } else { "LED OFF\n" };
        let answer = format!(
            "OK LED led={} uptime_ms={uptime_ms}\r\n",
            if on { "on" } else { "off" }
        );
        edges.push(LedEdge {
            t_sent_s: a.sent.saturating_duration_since(epoch).as_secs_f64(),
            round_trip_s: a.rtt.as_secs_f64(),
            command_wire_s: m.wire_s(command.len()),
            answer_wire_s: m.wire_s(answer.len()),
            on,
        });
        if i % 4 == 3 {
            desk.progress(
                id,
                view(
                    0.05 + 0.85 * (i + 1) as f64 / sends.len() as f64,
                    format!("LED switched {} of {} times", i + 1, sends.len()),
                    &frames,
                ),
            );
        }
    }
    // 3. The frames of the last switch, the LED off again.
    let t_end = now_s() + 10.0 * period_s + 0.3;
    while now_s() < t_end {
        tokio::time::sleep(Duration::from_millis(10)).await;
        take(&mut frames);
    }
    let _ = switch(false).await;
    frames.sort_by(|a, b| a.t_delivered_s.total_cmp(&b.t_delivered_s));
    let result = estimate_led_latency(&frames, &edges, period_s).context("calibrate latency")?;
    desk.progress(
        id,
        view(
            0.98,
            format!(
                "camera latency {:.1} ms (+- {:.1} ms), {} of {} switches seen",
                result.latency_ms, result.bound_ms, result.edges_seen, result.edges
            ),
            &frames,
        ),
    );
    Ok(StepOutcome {
        result: serde_json::to_value(&result)?,
        truth: serde_json::Value::Null,
        error: serde_json::Value::Null,
        figure: (
            "camera_latency_ms",
            result.latency_ms,
            f64::NAN,
            TARGET_CAMERA_LATENCY_MS,
        ),
        write: Box::new(move |file, stamp| {
            file.latency = Some(step_record(stamp, result));
        }),
    })
}

/// The joint the real-lab robot step excites (A7, the wrist: the smallest
/// moving mass, far from its limits in any posture the lab rests in).
pub const REAL_ROBOT_JOINT: usize = 6;
/// The real-lab robot step's steps, radians.
pub const REAL_ROBOT_AMPLITUDE_RAD: f64 = 0.02;
/// How long the real-lab robot step excites the joint, seconds.
pub const REAL_ROBOT_DURATION_S: f64 = 8.0;
/// The least excitation the robot step fits when the robot left commanding
/// during it, seconds (8 of its moves: four out and back).
pub const REAL_ROBOT_MIN_S: f64 = 3.2;
/// How many excitations the robot step starts at most, each cut short by
/// the robot leaving commanding.
pub const REAL_ROBOT_EXCITATIONS: usize = 3;
/// How long a step waits for the robot to command again after it left
/// commanding during the step's motion, seconds.
pub const RECOMMAND_WAIT_S: f64 = 30.0;

/// The robot step on the real lab, through its own FRI session (job `id`,
/// claimed): the control loop moves A7 by [`REAL_ROBOT_AMPLITUDE_RAD`] and
/// back every 0.4 s for [`REAL_ROBOT_DURATION_S`] from where the arm rests
/// (`Command::Excite`: minimum-jerk moves within every joint's speed and
/// acceleration limits, through the command guard), every published state's
/// commanded and measured A7 is recorded ([`crate::Lab::tap_joint`]) and
/// [`fit_robot_latency`](rt_core::calibration::fit_robot_latency) finds the
/// command-to-measurement delay and the servo lag. The lab's beliefs take
/// their sum as `control.latency_prior_ms` (what the online estimate starts
/// from). The joint moves: an operator's heartbeat must come meanwhile when
/// the lab's dead-man is on. When the robot leaves commanding during it
/// (the excitation ends there), what was recorded until then is fitted if
/// it holds [`REAL_ROBOT_MIN_S`]; otherwise the step waits for commanding
/// again and excites anew, [`REAL_ROBOT_EXCITATIONS`] times at most.
/// Refused, nothing written, when the robot does not command, a stop or the
/// dead-man interrupts it, every excitation was cut short, or the fit
/// refuses (the joint did not follow).
pub async fn run_real_robot(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> Option<Scenario> {
    let outcome = real_robot(lab, desk, id).await;
    // A tap left by a step that failed half-way is let go.
    let _ = lab.take_tap();
    desk.conclude(id, Step::Robot, scenario, outcome, desk.source())
}

async fn real_robot(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
) -> anyhow::Result<StepOutcome> {
    use rt_core::calibration::robot::JointSample;
    use rt_core::calibration::{StepView, ViewKind, fit_robot_latency};
    let joint = REAL_ROBOT_JOINT;
    let series = |s: &[JointSample], t0: f64| -> Vec<[f64; 2]> {
        rt_core::calibration::view::thin(
            &s.iter().map(|j| [j.t_s - t0, j.q_rad]).collect::<Vec<_>>(),
            800,
        )
    };
    if let Some(p) = lab
        .device_problems()
        .into_iter()
        .find(|p| p.device == "robot")
    {
        anyhow::bail!("calibrate robot: the robot does not command: {}", p.message);
    }
    // Excitations cut short by the robot leaving commanding (its seconds).
    let mut cut_short: Vec<f64> = Vec::new();
    let tap = loop {
        if !cut_short.is_empty() {
            // A real session's quality dips now and then: the step waits
            // for commanding again and excites anew, as a person would.
            robot_commands_again(lab).await.map_err(|why| {
                anyhow::anyhow!(
                    "calibrate robot: the robot left commanding during the excitation and did \
                     not command again within {RECOMMAND_WAIT_S:.0} s ({why}): nothing written; \
                     run the step again once it commands"
                )
            })?;
        }
        let tap = excite_and_tap(lab, desk, id, joint).await?;
        if !tap.idle {
            anyhow::bail!("calibrate robot: a trial ran during the excitation: not used");
        }
        let Some(cut) = tap.cut_s else {
            break tap;
        };
        let excited_s = cut - tap.commands.first().map_or(cut, |c| c.t_s);
        if excited_s >= REAL_ROBOT_MIN_S {
            // What was recorded before the robot left commanding is the
            // excitation's response: the fit takes that much.
            break tap;
        }
        cut_short.push(excited_s);
        if cut_short.len() >= REAL_ROBOT_EXCITATIONS {
            anyhow::bail!(
                "calibrate robot: the robot left commanding during each of {} excitations \
                 (after {} s; the fit needs {REAL_ROBOT_MIN_S:.1} s): nothing written; run the \
                 step again once it commands steadily",
                cut_short.len(),
                cut_short
                    .iter()
                    .map(|s| format!("{s:.1}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        desk.progress(
            id,
            StepView {
                progress: 0.02,
                message: format!(
                    "the robot left commanding {excited_s:.1} s into the excitation (the fit \
                     needs {REAL_ROBOT_MIN_S:.1} s): exciting A{} again once it commands \
                     ({} of {REAL_ROBOT_EXCITATIONS})",
                    joint + 1,
                    cut_short.len() + 1
                ),
                kind: ViewKind::Series,
                points: Vec::new(),
                fit: Vec::new(),
            },
        );
    };
    let result = fit_robot_latency(&tap.commands, &tap.measured).context("calibrate robot")?;
    let t0 = tap.commands.first().map_or(0.0, |c| c.t_s);
    desk.progress(
        id,
        StepView {
            progress: 0.98,
            message: format!(
                "A{} excited: latency {:.2} ms, servo lag {:.2} ms ({:.1} Hz), from {} states{}",
                joint + 1,
                result.latency_ms,
                result.servo_time_constant_ms,
                result.bandwidth_hz,
                tap.measured.len(),
                tap.cut_s.map_or(String::new(), |cut| format!(
                    " (the first {:.1} s: the robot left commanding then)",
                    cut - t0
                ))
            ),
            kind: ViewKind::Series,
            points: series(&tap.measured, t0),
            fit: series(&tap.commands, t0),
        },
    );
    Ok(StepOutcome {
        result: serde_json::to_value(&result)?,
        truth: serde_json::Value::Null,
        error: serde_json::Value::Null,
        figure: (
            "robot_latency_ms",
            result.latency_ms,
            f64::NAN,
            TARGET_ROBOT_LATENCY_MS,
        ),
        write: Box::new(move |file, stamp| {
            file.robot = Some(step_record(stamp, result));
        }),
    })
}

/// One excitation of `joint` ([`REAL_ROBOT_DURATION_S`], then 0.5 s of rest)
/// with its tap: the whole of it, or what was recorded until the robot left
/// commanding ([`crate::lab::JointTap::cut_s`]: the controller ends the
/// excitation where it is then).
async fn excite_and_tap(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    joint: usize,
) -> anyhow::Result<crate::lab::JointTap> {
    use rt_core::bridge::{Command, Excitation};
    use rt_core::calibration::{StepView, ViewKind};
    use std::time::{Duration, Instant};
    lab.tap_joint(joint);
    lab.command(Command::Excite(Excitation {
        joint,
        amplitude_rad: REAL_ROBOT_AMPLITUDE_RAD,
        duration_s: REAL_ROBOT_DURATION_S,
    }))
    .await
    .map_err(|e| {
        anyhow::anyhow!("calibrate robot: the control loop did not start the excitation: {e}")
    })?;
    let start = Instant::now();
    let lost = lab.latest().map_or(0, |(s, _)| s.fri.commanding_lost);
    // The excitation, then 0.5 s of rest (the last move's settling).
    let total_s = REAL_ROBOT_DURATION_S + 0.5;
    let mut shown = 0.0;
    while start.elapsed().as_secs_f64() < total_s {
        tokio::time::sleep(Duration::from_millis(50)).await;
        let Some((s, _)) = lab.latest() else {
            continue;
        };
        if s.fri.commanding_lost > lost {
            // The tap stopped at the first state after the loss (the lab's
            // thread records the states it publishes: wait for it).
            let seen = Instant::now();
            while lab.tap_cut().is_none() && seen.elapsed() < Duration::from_secs(2) {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            break;
        }
        if s.trial_state != rt_core::bridge::TrialState::Idle {
            anyhow::bail!(
                "calibrate robot: the excitation was interrupted ({}: a stop, no operator's \
                 heartbeat while the lab's dead-man is on, or the robot left COMMANDING_ACTIVE)",
                s.trial_state.as_str()
            );
        }
        let t = start.elapsed().as_secs_f64();
        if t - shown >= 1.0 {
            shown = t;
            desk.progress(
                id,
                StepView {
                    progress: 0.02 + 0.9 * t / total_s,
                    message: format!(
                        "A{} excited: {t:.0} of {REAL_ROBOT_DURATION_S:.0} s, {} states recorded",
                        joint + 1,
                        lab.tap_len()
                    ),
                    kind: ViewKind::Series,
                    points: Vec::new(),
                    fit: Vec::new(),
                },
            );
        }
    }
    let tap = lab
        .take_tap()
        .context("calibrate robot: the recording of the joint went missing")?;
    let lost_now = lab.latest().map_or(0, |(s, _)| s.fri.commanding_lost);
    if tap.cut_s.is_none() && lost_now > lost {
        anyhow::bail!(
            "calibrate robot: the robot left commanding during the excitation and its recording \
             did not show where: nothing written; run the step again once it commands"
        );
    }
    Ok(tap)
}

/// How long the real-lab camera-robot step waits for the arm to reach a
/// tour pose (its slow move plus settling), seconds.
pub const REAL_TOUR_MOVE_WAIT_S: f64 = 60.0;
/// How near the commanded and the measured joints must be to the pose, rad
/// (0.2 degrees).
const REAL_TOUR_AT_POSE_RAD: f64 = 0.0035;

/// The camera-robot step on the real lab, through its own robot, camera and
/// magnet (job `id`, claimed): the magnet hangs the ball out of the arm's
/// way; the operator fits the green marker disc to the tool (the job's
/// message asks for it); the arm tours the marker poses
/// (`calibration::marker::tour_targets` over the pendulum's region) by slow
/// joint moves through the control loop (`Command::MoveTo`, every target 5
/// degrees inside the limits, checked by the controller); at each, after
/// [`marker::SETTLE_S`], the disc is found in full colour frames
/// (`find_marker`, near where the believed camera expects it) and the
/// measured joints are averaged; then back where it started. The camera's
/// pose is fitted to the sightings (`fit_pose`: with `k1` unless the camera
/// step gave the lens); the intercept point is the pendulum step's rest
/// pixel (the calibration file) seen through the fitted camera, met with
/// the believed swing plane (`x` of the pivot: the touch that measures the
/// depth on the simulated world needs hands on the robot, not built here).
/// Refused, nothing written, when the robot does not command, the camera
/// gives no colour frames, the pendulum step is missing, a move is refused
/// or interrupted, or the marker is seen at fewer than [`marker::MIN_POSES`]
/// poses.
///
/// [`marker::SETTLE_S`]: rt_core::calibration::marker::SETTLE_S
/// [`marker::MIN_POSES`]: rt_core::calibration::marker::MIN_POSES
pub async fn run_real_camera_robot(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> Option<Scenario> {
    let start = lab.latest().map(|(s, _)| s.robot.q_cmd_rad);
    let outcome = real_camera_robot(lab, desk, id, scenario).await;
    // Wherever the tour stopped, the arm goes back where it started; never
    // after a stop or an abort (the lab's state is then not idle: the arm
    // stays where the stop left it).
    if let Some(q) = start
        && let Some((s, _)) = lab.latest()
        && s.trial_state == rt_core::bridge::TrialState::Idle
        && s.robot.q_cmd_rad != q
    {
        let _ = move_to_pose(lab, &q).await;
    }
    desk.conclude(id, Step::CameraRobot, scenario, outcome, desk.source())
}

/// Waits until the robot commands again (no device problem of the robot's),
/// at most [`RECOMMAND_WAIT_S`]; otherwise the problem's message.
async fn robot_commands_again(lab: &crate::Lab) -> Result<(), String> {
    use std::time::{Duration, Instant};
    let since = Instant::now();
    while let Some(p) = lab
        .device_problems()
        .into_iter()
        .find(|p| p.device == "robot")
    {
        if since.elapsed().as_secs_f64() > RECOMMAND_WAIT_S {
            return Err(p.message);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Ok(())
}

/// How many times [`move_to_pose`] sends a move again after the robot left
/// commanding during it.
pub const MOVE_RESENDS: u32 = 3;

/// Moves the arm to `target` through the control loop and waits until the
/// commanded and the measured joints are there (at most
/// [`REAL_TOUR_MOVE_WAIT_S`] from the last send). The robot leaving
/// COMMANDING_ACTIVE ends a move where it is (the controller's rule); once it
/// commands again the move is sent again from there, at most
/// [`MOVE_RESENDS`] times, as an operator would restart it.
///
/// # Errors
///
/// When the control loop refuses the move, a stop or a trial state ends it,
/// or the arm is not at the pose in time (the message says how often the
/// robot left commanding meanwhile).
pub async fn move_to_pose(
    lab: &crate::Lab,
    target: &[f64; rt_core::kinematics::iiwa7::JOINTS],
) -> anyhow::Result<()> {
    use rt_core::bridge::{Command, FriSessionState, TrialState};
    use std::time::{Duration, Instant};
    let lost_now = || lab.latest().map_or(0, |(s, _)| s.fri.commanding_lost);
    let mut lost = lost_now();
    lab.command(Command::MoveTo(*target))
        .await
        .map_err(|e| anyhow::anyhow!("the control loop refused the move: {e}"))?;
    let mut resends = 0;
    let mut deadline = Instant::now() + Duration::from_secs_f64(REAL_TOUR_MOVE_WAIT_S);
    loop {
        tokio::time::sleep(Duration::from_millis(20)).await;
        if let Some((s, _)) = lab.latest() {
            if s.trial_state != TrialState::Idle {
                anyhow::bail!(
                    "the move was interrupted ({}: a stop, no operator's heartbeat while the \
                     lab's dead-man is on, or the robot left COMMANDING_ACTIVE)",
                    s.trial_state.as_str()
                );
            }
            let near =
                |q: &[f64; 7], tol: f64| q.iter().zip(target).all(|(a, b)| (a - b).abs() <= tol);
            if near(&s.robot.q_cmd_rad, 1e-9) && near(&s.robot.q_rad, REAL_TOUR_AT_POSE_RAD) {
                return Ok(());
            }
            // The robot left commanding since the move was sent: the move
            // ended where it was. Send it again once the robot commands (a
            // refusal meanwhile, e.g. still settling, is tried again).
            if s.fri.commanding_lost > lost
                && s.fri.session == FriSessionState::CommandingActive
                && resends < MOVE_RESENDS
                && lab.command(Command::MoveTo(*target)).await.is_ok()
            {
                lost = s.fri.commanding_lost;
                resends += 1;
                deadline = Instant::now() + Duration::from_secs_f64(REAL_TOUR_MOVE_WAIT_S);
            }
        }
        if Instant::now() > deadline {
            let left = lost_now().saturating_sub(lost);
            anyhow::bail!(
                "the arm did not reach the pose in {REAL_TOUR_MOVE_WAIT_S:.0} s (the move sent \
                 {} times, the robot leaving commanding {left} times since the last; GET \
                 /api/health's devices says why)",
                resends + 1
            );
        }
    }
}

async fn real_camera_robot(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> anyhow::Result<StepOutcome> {
    use nalgebra::{Vector2, Vector3};
    use rt_core::bridge::Command;
    use rt_core::calibration::extrinsics::{
        CameraRobotCalibration, camera_pose_of, ray_b, reproject,
    };
    use rt_core::calibration::marker::{
        FRAMES_PER_POSE, MARKER_OFFSET_M, MARKER_RADIUS_M, MIN_POSES, SETTLE_S, TOUR_SEED_DEG,
        find_marker, fit_pose, marker_believed, tour_points, tour_targets,
    };
    use rt_core::calibration::{StepView, ViewKind};
    use std::time::Duration;
    let k = desk
        .lab_geometry()
        .context("calibrate camera-robot: the lab's [calibration] is not known")?
        .clone();
    let devices = lab
        .devices()
        .context("calibrate camera-robot: the lab's devices have not started")?;
    let Some(stills) = devices.stills.clone() else {
        anyhow::bail!("calibrate camera-robot: this lab's camera gives no full frames");
    };
    if let Some(p) = lab.device_problems().into_iter().next() {
        anyhow::bail!("calibrate camera-robot: {}: {}", p.device, p.message);
    }
    let file = CalibrationFile::load_or_empty(desk.path()).context("calibrate camera-robot")?;
    let Some(pendulum) = file.pendulum.as_ref() else {
        anyhow::bail!(
            "calibrate camera-robot: the pendulum step's rest point is missing (run it first)"
        );
    };
    let rest_px = Vector2::from(pendulum.result.rest_px);
    // The swing plane where the pendulum hangs now: a stand that trials
    // moved carries the pivot with it (as the detector's plane moves,
    // `CameraBasis::at_distance`); the rest pixel's ray is met there.
    let mut basis = crate::serve::camera_basis(&k, scenario);
    if let Some(d) = lab
        .latest()
        .map(|(s, _)| s.pendulum.rest_distance_m)
        .filter(|d| d.is_finite() && *d > 0.0)
    {
        basis = basis.at_distance(d);
    }
    let (intrinsics, believed_pose, rest_b) = basis.believed(scenario);
    // The camera step's lens, when the file has it; else k1 is fitted here.
    let k1_fixed = scenario.camera.intrinsics.map(|i| i.k1);
    // The tour starts where the arm is (each move the shortest to the next
    // pose), or from the tour's seed posture before the lab's first state.
    let seed: [f64; 7] = lab.latest().map_or_else(
        || std::array::from_fn(|j| TOUR_SEED_DEG[j].to_radians()),
        |(s, _)| s.robot.q_cmd_rad,
    );
    let targets = tour_targets(&tour_points(scenario), &seed);
    let n = targets.len();
    if n < MIN_POSES {
        anyhow::bail!(
            "calibrate camera-robot: {n} marker poses are within reach ({MIN_POSES} needed)"
        );
    }
    // The ball out of the tour's way: held on the magnet.
    lab.command(Command::Magnet { on: true })
        .await
        .map_err(|e| {
            anyhow::anyhow!("calibrate camera-robot: the magnet did not switch on: {e}")
        })?;
    let progress = |p: f64, message: String, points: Vec<[f64; 2]>, fit: Vec<[f64; 2]>| {
        desk.progress(
            id,
            StepView {
                progress: p,
                message,
                kind: ViewKind::Image,
                points,
                fit,
            },
        );
    };
    let ask = format!(
        "fit the green marker disc (radius {:.0} mm) to the tool, {:.0} mm out along it, and hang \
         the ball on the magnet: the arm tours {n} poses in the camera's view",
        MARKER_RADIUS_M * 1e3,
        MARKER_OFFSET_M[2] * 1e3
    );
    progress(0.0, ask.clone(), Vec::new(), Vec::new());
    let mut points_b: Vec<Vector3<f64>> = Vec::new();
    let mut pixels: Vec<Vector2<f64>> = Vec::new();
    for (i, target) in targets.iter().enumerate() {
        move_to_pose(lab, target)
            .await
            .with_context(|| format!("calibrate camera-robot: pose {} of {n}", i + 1))?;
        tokio::time::sleep(Duration::from_secs_f64(SETTLE_S)).await;
        let (mut seen, mut q_sum, mut q_n) = (Vec::new(), [0.0; 7], 0_usize);
        for _ in 0..2 * FRAMES_PER_POSE {
            if seen.len() >= FRAMES_PER_POSE {
                break;
            }
            let still = take_still(&stills, Duration::from_secs(5), true)
                .await
                .context("calibrate camera-robot")?;
            let Some((s, _)) = lab.latest() else { continue };
            for (a, b) in q_sum.iter_mut().zip(s.robot.q_rad) {
                *a += b;
            }
            q_n += 1;
            let (c_b, _) = marker_believed(&s.robot.q_rad);
            let pc = believed_pose.to_camera(&c_b);
            let Some(guess) = intrinsics.project(&pc) else {
                continue;
            };
            let r_px = intrinsics.fx_px * MARKER_RADIUS_M / pc.z.max(0.1);
            let found = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
                Ok(find_marker(&still.to_mat()?, &guess, r_px)?)
            })
            .await
            .context("calibrate camera-robot: the marker search")??;
            if let Some(px) = found {
                seen.push(px);
            }
        }
        if seen.len() > FRAMES_PER_POSE / 2 && q_n > 0 {
            let q: [f64; 7] = std::array::from_fn(|j| q_sum[j] / q_n as f64);
            points_b.push(marker_believed(&q).0);
            pixels.push(seen.iter().fold(Vector2::zeros(), |a, p| a + p) / seen.len() as f64);
        }
        progress(
            0.9 * (i + 1) as f64 / n as f64,
            format!(
                "{ask}; marker pose {} of {n}: seen in {} frames ({} poses seen)",
                i + 1,
                seen.len(),
                pixels.len()
            ),
            pixels.iter().map(|p| [p.x, p.y]).collect(),
            Vec::new(),
        );
    }
    if pixels.len() < MIN_POSES {
        anyhow::bail!(
            "calibrate camera-robot: marker never seen: {} of {n} poses ({MIN_POSES} needed; is \
             the green disc on the tool and in the camera's view?)",
            pixels.len()
        );
    }
    let fit = fit_pose(&intrinsics, &points_b, &pixels, &believed_pose, k1_fixed)
        .context("calibrate camera-robot: the pose fit")?;
    // The intercept point: the rest pixel's ray through the fitted camera met
    // with the believed swing plane (x of the ball at rest).
    let ray = ray_b(&intrinsics, &fit, rest_px.x, rest_px.y);
    if ray.x <= 0.05 {
        anyhow::bail!("calibrate camera-robot: the rest point's ray misses the swing plane");
    }
    let s = (rest_b.x - fit.position_m.x) / ray.x;
    let intercept = fit.position_m + ray * s;
    let distance = rest_b.x.hypot(rest_b.y);
    let nominal = Vector3::new(distance, 0.0, scenario.task.intercept_height_m);
    let pose = camera_pose_of(&fit.base_from_camera, &fit.position_m);
    let fitted = reproject(&intrinsics, &fit, &points_b);
    progress(
        1.0,
        format!(
            "camera at ({:.4}, {:.4}, {:.4}) m from {} marker poses (reprojection rms {:.2} px), \
             intercept point ({:.4}, {:.4}, {:.4}) m; the marker may come off",
            pose.position_m[0],
            pose.position_m[1],
            pose.position_m[2],
            pixels.len(),
            fit.rms_px,
            intercept.x,
            intercept.y,
            intercept.z
        ),
        pixels.iter().map(|p| [p.x, p.y]).collect(),
        fitted,
    );
    let std_mm = fit.position_std_m.norm() * 1e3;
    let result = CameraRobotCalibration {
        camera_pose: pose,
        base_from_camera_rows: std::array::from_fn(|r| {
            std::array::from_fn(|c| fit.base_from_camera[(r, c)])
        }),
        reprojection_rms_px: fit.rms_px,
        poses: pixels.len(),
        poses_commanded: n,
        k1: fit.k1,
        k1_fitted: k1_fixed.is_none(),
        position_std_m: fit.position_std_m.into(),
        marker_offset_m: MARKER_OFFSET_M,
        intercept_m: intercept.into(),
        intercept_offset_m: (intercept - nominal).into(),
        rest_px: [rest_px.x, rest_px.y],
        intercept_depth_from: "plane".into(),
    };
    Ok(StepOutcome {
        result: serde_json::to_value(&result)?,
        truth: serde_json::Value::Null,
        error: serde_json::Value::Null,
        figure: (
            "camera_position_std_mm",
            std_mm,
            f64::NAN,
            TARGET_CAMERA_POSITION_MM,
        ),
        write: Box::new(move |file, stamp| {
            file.camera_robot = Some(step_record(stamp, result));
        }),
    })
}

/// The contact step's knock starts this far before the tool touches the
/// hanging ball, along the swing, m.
pub const KNOCK_BEFORE_M: f64 = 0.15;
/// ... and ends (the tool stops) this far past the touch, m.
pub const KNOCK_PAST_M: f64 = 0.02;
/// The ball hangs still enough for a knock when its swing, fitted over
/// [`KNOCK_WATCH_S`], is at most this, m (a swing of `a0` moves the learned
/// offset by up to `2 a0 / v`: 3 ms at 0.3 m/s).
pub const KNOCK_STILL_M: f64 = 0.0005;
/// How long the step watches the ball before the knock, s.
pub const KNOCK_WATCH_S: f64 = 2.0;
/// How long the step waits for the ball to hang still, s.
pub const KNOCK_STILL_WAIT_S: f64 = 30.0;
/// The still ball must hang this near its believed rest point along the
/// swing, m (a ball held on the magnet hangs tens of cm aside).
pub const KNOCK_REST_M: f64 = 0.05;
/// What the contact step asks of the person beside the pendulum while the
/// ball swings (the simulated lab's hands read it: `world::asked_steady`).
pub const STEADY_PROMPT: &str = "steady it by hand";
/// Robot messages of the arm at rest before the knock (the torques' baseline).
const KNOCK_BASELINE: usize = 100;
/// Knocks per step, averaged (each on the ball hanging still again).
pub const KNOCKS: usize = 3;

/// The contact step on the lab, through its own robot and camera (job
/// `id`, claimed; `rt_core::calibration::contact` says what it measures):
/// a magnet holding the ball lets go; the arm takes the tool beside the
/// hanging ball, [`KNOCK_BEFORE_M`] before it along the swing, in the
/// posture the trajectory planner gives the line through the ball's rest
/// point (its believed intercept point where the pendulum hangs:
/// `PendulumView::rest_distance_m`); the camera must see the ball hang
/// still at its rest point ([`KNOCK_STILL_M`], [`KNOCK_REST_M`]; the job
/// asks for it to be stopped by hand meanwhile, [`STEADY_PROMPT`]); the arm
/// knocks it (`Command::Knock`, a minimum-jerk joint move at
/// `control::KNOCK_LIMIT_SHARE` of the joints' limits, stopping
/// [`KNOCK_PAST_M`] past the touch) and holds while the ball swings out and
/// back onto the tool; the measured tool point, the external torques and
/// the camera's detections are fitted (`fit_knock`); [`KNOCKS`] times from
/// beside the ball, averaged (`contact::combine`); then the arm goes back
/// beside the ball and to where it started. Refused, nothing written, when
/// the robot does not command or sends no external torques, the camera
/// does not deliver, the arm cannot knock there, the ball does not hang
/// still in [`KNOCK_STILL_WAIT_S`], or a contact is not seen.
pub async fn run_real_contact(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
) -> Option<Scenario> {
    let start = lab.latest().map(|(s, _)| s.robot.q_cmd_rad);
    let mut beside = None;
    let outcome = real_contact(lab, desk, id, scenario, &mut beside).await;
    let _ = lab.take_tap();
    // Away from the ball along the knock's line, then where it started;
    // never after a stop or an abort.
    for q in [beside, start].into_iter().flatten() {
        let Some((s, _)) = lab.latest() else {
            break;
        };
        if s.trial_state != rt_core::bridge::TrialState::Idle {
            break;
        }
        if s.robot.q_cmd_rad != q && move_to_pose(lab, &q).await.is_err() {
            break;
        }
    }
    desk.conclude(id, Step::Contact, scenario, outcome, desk.source())
}

/// The joints that knock along base `y` (`sigma`) through `rest`: beside
/// it and past the touch, both 5 degrees inside the limits.
fn knock_joints(
    scenario: &Scenario,
    rest: &nalgebra::Vector3<f64>,
    sigma: f64,
) -> Option<([f64; 7], [f64; 7])> {
    use rt_core::trajectory::profile::ProfileKind;
    use rt_core::trajectory::{MotionRequest, TrajectoryParams, plan};
    let task = &scenario.task;
    // The ball first touches the tool disc's rim (the tool points down).
    let reach = scenario.pendulum.ball_radius_m + task.tool_contact_radius_m;
    let y = nalgebra::Vector3::y();
    let req = MotionRequest {
        start_m: rest - y * sigma * (reach + KNOCK_BEFORE_M),
        end_m: rest - y * sigma * (reach - KNOCK_PAST_M),
        movement_time_s: 1.0,
        profile: ProfileKind::MinJerk,
        tool: rt_core::kinematics::Tool::along_z(task.tool_length_m),
    };
    let traj = TrajectoryParams {
        position_margin_deg: 6.0,
        ..TrajectoryParams::default()
    };
    let mp = plan(&req, &traj).ok()?;
    let qa = mp.home_q;
    let mut qb = qa;
    mp.joints_at(1.0, &qa, &mut qb).ok()?;
    let inside = |q: &rt_core::kinematics::Joints| {
        q.iter()
            .zip(rt_core::kinematics::iiwa7::POSITION_LIMIT_RAD)
            .all(|(v, l)| v.abs() <= l - rt_core::control::MOVE_TO_MARGIN_RAD)
    };
    (inside(&qa) && inside(&qb)).then(|| {
        (
            std::array::from_fn(|j| qa[j]),
            std::array::from_fn(|j| qb[j]),
        )
    })
}

async fn real_contact(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    scenario: &Scenario,
    beside: &mut Option<[f64; 7]>,
) -> anyhow::Result<StepOutcome> {
    use rt_core::calibration::{StepView, ViewKind};
    let progress = |p: f64, message: String, points: Vec<[f64; 2]>| {
        desk.progress(
            id,
            StepView {
                progress: p,
                message,
                kind: ViewKind::Series,
                points,
                fit: Vec::new(),
            },
        );
    };
    if let Some(p) = lab
        .device_problems()
        .into_iter()
        .find(|p| p.device != "magnet")
    {
        anyhow::bail!("calibrate contact: {}", p.message);
    }
    if !lab
        .latest()
        .is_some_and(|(s, _)| s.robot.tau_ext_nm.iter().all(|v| v.is_finite()))
    {
        anyhow::bail!(
            "calibrate contact: the robot sends no external joint torques (its monitoring \
             messages carry none): a contact cannot be seen"
        );
    }
    // Where the pendulum hangs (the stand's place, or the lab's fixed one).
    let distance = lab
        .latest()
        .map(|(s, _)| s.pendulum.rest_distance_m)
        .filter(|d| d.is_finite())
        .or(lab.options().fixed_distance_m)
        .unwrap_or_else(|| scenario.task.distance_m.lerp(0.5));
    let rest = scenario.task.intercept_m(distance);
    let (sigma, (qa, qb)) = [1.0, -1.0]
        .into_iter()
        .find_map(|s| knock_joints(scenario, &rest, s).map(|q| (s, q)))
        .ok_or_else(|| {
            anyhow::anyhow!(
                "calibrate contact: the arm cannot knock along the swing through the ball's rest \
                 point ({:.3}, {:.3}, {:.3}) m in reach and 5 degrees inside its limits",
                rest.x,
                rest.y,
                rest.z
            )
        })?;
    // The ball must hang free: a magnet holding it lets go.
    if lab
        .latest()
        .is_some_and(|(s, _)| s.magnet == rt_core::bridge::MagnetState::On)
    {
        progress(
            0.01,
            "magnet off: the ball must hang free at its rest point".into(),
            Vec::new(),
        );
        lab.command(rt_core::bridge::Command::Magnet { on: false })
            .await
            .map_err(|e| anyhow::anyhow!("calibrate contact: the magnet: {e}"))?;
    }
    let mut knocks = Vec::with_capacity(KNOCKS);
    let mut points = Vec::new();
    for k in 0..KNOCKS {
        // 1. Beside the ball (again after a knock: the tool off it).
        progress(
            0.02 + 0.9 * k as f64 / KNOCKS as f64,
            format!(
                "knock {} of {KNOCKS}: moving the tool beside the hanging ball, {:.0} cm before \
                 it along the swing",
                k + 1,
                KNOCK_BEFORE_M * 100.0
            ),
            Vec::new(),
        );
        move_to_pose(lab, &qa)
            .await
            .map_err(|e| anyhow::anyhow!("calibrate contact: moving beside the ball: {e}"))?;
        *beside = Some(qa);
        let (one, seen) = knock_once(lab, desk, id, &qb, sigma, scenario, k).await?;
        knocks.push(one);
        points = seen;
    }
    let result =
        rt_core::calibration::contact::combine(&knocks).context("calibrate contact: no knock")?;
    progress(
        0.98,
        format!(
            "{KNOCKS} knocks at {:.2} m/s, the ball back after {:.3} s: the torques show a \
             contact {:.1} ± {:.1} ms late at the pulse's centre (lag {:.1} ms = {:.2} periods, \
             pulse {:.1} ms)",
            result.knock_speed_mps,
            result.return_s,
            result.onset_offset_ms,
            result.onset_offset_std_ms,
            result.torque_lag_ms,
            result.torque_lag_periods,
            result.pulse_ms,
        ),
        points,
    );
    Ok(StepOutcome {
        result: serde_json::to_value(&result)?,
        truth: serde_json::Value::Null,
        error: serde_json::Value::Null,
        figure: (
            "contact_onset_offset_ms",
            result.onset_offset_ms,
            f64::NAN,
            TARGET_CONTACT_OFFSET_MS,
        ),
        write: Box::new(move |file, stamp| {
            file.contact = Some(step_record(stamp, result));
        }),
    })
}

/// One knock from beside the ball (the tool there, the arm at rest): waits
/// for the ball to hang still (asking the hands to stop it), records the
/// torques' baseline, knocks (`Command::Knock` to `qb`), records until the
/// ball has come back onto the tool, and fits it. Returns the fit and the
/// view's points (the torques' departure from their rest, norm, N m, over
/// time from the knock).
async fn knock_once(
    lab: &crate::Lab,
    desk: &CalibrationDesk,
    id: u64,
    qb: &[f64; 7],
    sigma: f64,
    scenario: &Scenario,
    k: usize,
) -> anyhow::Result<(rt_core::calibration::ContactCalibration, Vec<[f64; 2]>)> {
    use rt_core::bridge::{Command, TrialState};
    use rt_core::calibration::contact::{KnockRecording, fit_knock};
    use rt_core::calibration::{StepView, ViewKind};
    use rt_core::control::measured::Sighting;
    use std::time::{Duration, Instant};
    let progress = |p: f64, message: String| {
        desk.progress(
            id,
            StepView {
                progress: (k as f64 + p) / KNOCKS as f64 * 0.9 + 0.05,
                message: format!("knock {} of {KNOCKS}: {message}", k + 1),
                kind: ViewKind::Series,
                points: Vec::new(),
                fit: Vec::new(),
            },
        );
    };
    let p = &scenario.pendulum;
    let omega = (p.gravity_mps2 / p.length_m.max(1e-3)).sqrt();
    let qa = lab
        .latest()
        .map(|(s, _)| s.robot.q_cmd_rad)
        .context("calibrate contact: the lab published no state")?;
    // The camera's detections from now on (frames without the ball skipped).
    let mut frames = camera_detections(lab);
    let mut next = move || -> Option<Sighting> {
        frames().flatten().map(|d| Sighting {
            t_s: d.t_s,
            x_m: d.lateral_m,
        })
    };
    // 2. The ball hangs still: its swing over the last KNOCK_WATCH_S.
    let mut sightings: Vec<Sighting> = Vec::with_capacity(4096);
    let watch_from = Instant::now();
    let mut shown = 0.0;
    let mut tapped = false;
    // The swing over the last KNOCK_WATCH_S: its amplitude at the pendulum's
    // frequency and where it centres (the ball's lateral from the believed
    // rest point), m.
    let swing_of = |seen: &[Sighting]| -> Option<(f64, f64)> {
        let last = seen.last()?.t_s;
        let recent: Vec<&Sighting> = seen
            .iter()
            .filter(|s| s.t_s > last - KNOCK_WATCH_S)
            .collect();
        if recent.len() < 20 || last - recent[0].t_s < 0.9 * KNOCK_WATCH_S {
            return None;
        }
        let mut ata = nalgebra::Matrix3::<f64>::zeros();
        let mut atb = nalgebra::Vector3::<f64>::zeros();
        for s in &recent {
            let ph = omega * s.t_s;
            let a = nalgebra::Vector3::new(1.0, ph.sin(), ph.cos());
            ata += a * a.transpose();
            atb += a * s.x_m;
        }
        let c = ata.lu().solve(&atb)?;
        Some((c[1].hypot(c[2]), c[0]))
    };
    // Still, and where it hangs at rest (not held on the magnet).
    let at_rest = |w: (f64, f64)| w.0 <= KNOCK_STILL_M && w.1.abs() <= KNOCK_REST_M;
    let why = |w: Option<(f64, f64)>| match w {
        Some((_, x)) if x.abs() > KNOCK_REST_M => format!(
            "the ball hangs {:.0} mm aside of its rest point (held?)",
            x.abs() * 1e3
        ),
        Some((a, _)) => format!("the ball swings by {:.1} mm", a * 1e3),
        None => "the camera does not see the ball steadily".into(),
    };
    loop {
        if let Some(s) = next() {
            sightings.push(s);
        }
        let waited = watch_from.elapsed().as_secs_f64();
        let swing = swing_of(&sightings);
        if swing.is_some_and(at_rest) {
            if !tapped {
                // The torques' baseline while the ball is watched; the
                // prompt goes (the hands keep off from now on); the
                // detections before the still window go.
                progress(0.15, "the ball hangs still: the torques at rest".into());
                let last = sightings.last().map_or(f64::NEG_INFINITY, |s| s.t_s);
                sightings.retain(|s| s.t_s > last - KNOCK_WATCH_S);
                lab.tap_joint(0);
                tapped = true;
            }
            if lab.tap_len() >= KNOCK_BASELINE {
                break;
            }
        }
        if waited > KNOCK_STILL_WAIT_S {
            anyhow::bail!(
                "calibrate contact: {}: nothing written; stop it by hand at its rest point (it \
                 must hang still within {:.1} mm) and run the step again",
                match swing {
                    None => format!(
                        "the camera saw the ball {} times in {KNOCK_STILL_WAIT_S:.0} s",
                        sightings.len()
                    ),
                    w => why(w),
                },
                KNOCK_STILL_M * 1e3
            );
        }
        if waited - shown >= 1.0 && !tapped {
            shown = waited;
            progress(
                0.1,
                match swing {
                    Some(w) if !at_rest(w) => {
                        format!(
                            "waiting for the ball to hang still: {} ({STEADY_PROMPT})",
                            why(swing)
                        )
                    }
                    _ => "watching the hanging ball".into(),
                },
            );
        }
        tokio::time::sleep(Duration::from_millis(4)).await;
    }
    // 3. The knock, and the ball's return (said first: the hands keep off).
    progress(0.2, "knocking the ball".into());
    let knock_start_s = lab.latest().map_or(f64::NAN, |(s, _)| s.t_s);
    let lost = lab.latest().map_or(0, |(s, _)| s.fri.commanding_lost);
    lab.command(Command::Knock(*qb)).await.map_err(|e| {
        anyhow::anyhow!("calibrate contact: the control loop refused the knock: {e}")
    })?;
    let knock_s = rt_core::control::step::move_duration_s(
        &rt_core::kinematics::Joints::from(qa),
        &rt_core::kinematics::Joints::from(*qb),
        rt_core::control::KNOCK_LIMIT_SHARE,
        rt_core::control::KNOCK_MIN_S,
    );
    let until_s = knock_start_s + knock_s + std::f64::consts::PI / omega + 0.8;
    let record_from = Instant::now();
    let mut shown = 0.0;
    loop {
        if let Some(s) = next() {
            sightings.push(s);
        }
        let Some((s, _)) = lab.latest() else {
            anyhow::bail!("calibrate contact: the lab published no state");
        };
        if s.fri.commanding_lost > lost {
            anyhow::bail!(
                "calibrate contact: the robot left commanding during the knock: nothing written; \
                 run the step again once it commands (the ball must hang still again)"
            );
        }
        if s.trial_state != TrialState::Idle {
            anyhow::bail!(
                "calibrate contact: the knock was interrupted ({}: a stop, or no operator's \
                 heartbeat while the lab's dead-man is on)",
                s.trial_state.as_str()
            );
        }
        if s.t_s >= until_s {
            break;
        }
        let waited = record_from.elapsed().as_secs_f64();
        if waited > until_s - knock_start_s + 30.0 {
            anyhow::bail!(
                "calibrate contact: the lab's clock did not reach the knock's end in {waited:.0} s"
            );
        }
        if waited - shown >= 0.5 {
            shown = waited;
            progress(
                0.2 + 0.7 * ((s.t_s - knock_start_s) / (until_s - knock_start_s)).clamp(0.0, 1.0),
                "knocked: the ball swings out and back onto the tool".into(),
            );
        }
        tokio::time::sleep(Duration::from_millis(4)).await;
    }
    let tap = lab
        .take_tap()
        .context("calibrate contact: the recording of the knock went missing")?;
    if tap.cut_s.is_some() {
        anyhow::bail!(
            "calibrate contact: the robot left commanding during the knock: nothing written; run \
             the step again once it commands (the ball must hang still again)"
        );
    }
    let t_s: Vec<f64> = tap.measured.iter().map(|m| m.t_s).collect();
    let tool_y_m: Vec<f64> = tap.tool_m.iter().map(|p| p[1]).collect();
    let result = fit_knock(&KnockRecording {
        t_s: &t_s,
        tool_y_m: &tool_y_m,
        torques_nm: &tap.tau_ext_nm,
        sightings: &sightings,
        knock_start_s,
        omega_radps: omega,
        length_m: p.length_m,
        damping_per_s: p.damping_per_s,
        sigma,
    })
    .map_err(|e| {
        // Where the tool went and where the camera saw the ball: what a
        // person checks when no contact was seen.
        let (lo, hi) = tool_y_m
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &y| {
                (a.min(y), b.max(y))
            });
        let at = tap.tool_m.last().copied().unwrap_or([f64::NAN; 3]);
        let rest = sightings
            .iter()
            .filter(|s| s.t_s < knock_start_s)
            .map(|s| s.x_m)
            .sum::<f64>()
            / sightings
                .iter()
                .filter(|s| s.t_s < knock_start_s)
                .count()
                .max(1) as f64;
        anyhow::anyhow!(
            "calibrate contact: {e} (the tool along y from {lo:.3} to {hi:.3} m at x {:.3}, z \
             {:.3} m; the ball seen at rest {:.1} mm aside of its believed rest point)",
            at[0],
            at[2],
            rest * 1e3
        )
    })?;
    // The view: the torques' departure from their rest (norm), over time.
    let base: [f64; 7] = {
        let n = t_s.partition_point(|&t| t < knock_start_s).max(1);
        std::array::from_fn(|j| tap.tau_ext_nm[..n].iter().map(|v| v[j]).sum::<f64>() / n as f64)
    };
    let points = rt_core::calibration::view::thin(
        &t_s.iter()
            .zip(&tap.tau_ext_nm)
            .map(|(t, v)| {
                let d = v
                    .iter()
                    .zip(&base)
                    .map(|(a, b)| (a - b).powi(2))
                    .sum::<f64>()
                    .sqrt();
                [t - knock_start_s, d]
            })
            .collect::<Vec<_>>(),
        800,
    );
    Ok((result, points))
}
