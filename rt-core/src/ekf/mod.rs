#![doc = include_str!("README.md")]

pub mod model;
mod predict;

use serde::{Deserialize, Serialize};

use model::{ALPHA, B, K};
pub use model::{ProcessModel, ProcessNoiseModel, StateCov, StateVec};
pub use predict::{Crossing, Doubt, MotionPlan, MotionRequest, PassDirection, Prediction};

use crate::check::{self, ParamError};
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumParams};

/// How many past measurements (with the posterior after each) the filter keeps, so
/// that a measurement arriving out of order is fused at its capture time.
pub const HISTORY_LEN: usize = 32;

/// Most relinearisations of one measurement update (iterated EKF).
const MAX_IEKF_ITERATIONS: usize = 4;

/// The iterated update stops when the angle moves less than this, radians.
const IEKF_TOLERANCE_RAD: f64 = 1e-7;

/// A filter that initialised itself from measurements restarts at its first
/// rejection until it has fused this many.
const YOUNG_FILTER_FUSED: u32 = 3;

/// Shortest spacing of the two measurements the filter initialises from, seconds.
const MIN_INIT_GAP_S: f64 = 1e-3;

/// The EKF and predictor: `[ekf]` (wired into scenarios by the closed-loop work).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EkfParams {
    /// Standard deviation of the lateral measurement noise `v` of eq. 10, metres
    /// (`R = measurement_noise_m^2`).
    pub measurement_noise_m: f64,
    /// How the state is carried over a step: `rk4` or the paper's `paper_taylor2` (eq. 9).
    pub process_model: ProcessModel,
    /// How process noise enters: `continuous` or the paper's `paper` (eqs. 16-19).
    pub process_noise_model: ProcessNoiseModel,
    /// Spectral density of the white angular-acceleration disturbance (`continuous`), rad^2/s^3.
    pub accel_psd_rad2ps3: f64,
    /// Variance `sigma` of the piecewise-constant angular acceleration (`paper`), rad^2/s^4.
    pub accel_var_rad2ps4: f64,
    /// Estimate the damping `alpha` online (state augmented to `[phi, phi', alpha]`).
    pub estimate_damping: bool,
    /// Prior standard deviation of `alpha` around the model's value, 1/s.
    pub damping_std_per_s: f64,
    /// Spectral density of the random walk of `alpha`, 1/s^3.
    pub damping_psd_per_s3: f64,
    /// Estimate the pendulum's frequency online: the state gains `k = g/l`
    /// (a string that stretched, a ball centre off the tape's reading).
    pub estimate_frequency: bool,
    /// Prior standard deviation of the effective length around the believed
    /// `pendulum.length_m` (sets `k`'s prior: `sigma_k = k sigma_l / l`), metres.
    pub length_std_m: f64,
    /// Estimate the lateral offset `b` of the measured rest point (camera pose,
    /// rest point off its belief): `z = l sin(phi) + b`; passes are predicted
    /// through the estimated rest.
    pub estimate_offset: bool,
    /// Prior standard deviation of `b`, metres.
    pub offset_std_m: f64,
    /// Prior standard deviation of `phi` when the state is set by hand, degrees.
    pub initial_angle_std_deg: f64,
    /// Prior standard deviation of `phi'` when the state is set by hand, degrees/s.
    pub initial_rate_std_degps: f64,
    /// Longest gap between the two measurements the filter initialises from, seconds.
    pub max_init_gap_s: f64,
    /// A measurement whose normalised innovation squared exceeds this is rejected.
    pub gate_nis: f64,
    /// After this many rejections in a row the filter re-initialises itself.
    pub max_consecutive_rejections: u32,
    /// Longest model sub-step (filter and predictor), seconds.
    pub max_step_s: f64,
    /// How far ahead the crossing search looks, seconds (the paper: 300 steps).
    pub horizon_s: f64,
    /// A motion plan is confident only after the filter has run this long, seconds.
    pub min_observation_s: f64,
    /// A motion plan is confident only if the last fused measurement is this recent, seconds.
    pub max_measurement_age_s: f64,
    /// A motion plan is confident only if its pass time's standard deviation is below this, ms.
    pub commit_max_time_std_ms: f64,
    /// How much a swing that leaves the believed plane bends the lateral
    /// reading, 1/m: the camera back-projects onto the believed plane, so a
    /// swing plane turned by `psi` about the vertical reads `y + y^2
    /// tan(psi) / D` (`D` the camera's distance), an error that grows with
    /// the square of the distance from the rest point and vanishes there.
    /// The measurement's variance gains `(plane_noise_per_m * y^2)^2`: the
    /// filter times the swing by the readings near the rest point and does not
    /// bend its offset or phase to fit the far ones. 0: off.
    pub plane_noise_per_m: f64,
}

impl Default for EkfParams {
    fn default() -> Self {
        Self {
            measurement_noise_m: 0.002,
            process_model: ProcessModel::Rk4,
            process_noise_model: ProcessNoiseModel::Continuous,
            accel_psd_rad2ps3: 1e-6,
            accel_var_rad2ps4: 3e-5,
            estimate_damping: true,
            damping_std_per_s: 0.03,
            damping_psd_per_s3: 1e-7,
            estimate_frequency: false,
            length_std_m: 0.02,
            estimate_offset: false,
            offset_std_m: 0.01,
            initial_angle_std_deg: 10.0,
            initial_rate_std_degps: 30.0,
            max_init_gap_s: 0.2,
            gate_nis: 25.0,
            max_consecutive_rejections: 8,
            max_step_s: 0.05,
            horizon_s: 6.0,
            min_observation_s: 0.5,
            max_measurement_age_s: 0.25,
            commit_max_time_std_ms: 5.0,
            plane_noise_per_m: 0.0,
        }
    }
}

impl EkfParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within(
            "ekf.measurement_noise_m",
            self.measurement_noise_m,
            1e-6,
            1.0,
        )?;
        check::within("ekf.accel_psd_rad2ps3", self.accel_psd_rad2ps3, 0.0, 100.0)?;
        check::within("ekf.accel_var_rad2ps4", self.accel_var_rad2ps4, 0.0, 1e4)?;
        check::within("ekf.damping_std_per_s", self.damping_std_per_s, 0.0, 5.0)?;
        check::within("ekf.damping_psd_per_s3", self.damping_psd_per_s3, 0.0, 1.0)?;
        check::within("ekf.length_std_m", self.length_std_m, 0.0, 1.0)?;
        check::within("ekf.offset_std_m", self.offset_std_m, 0.0, 0.5)?;
        check::within(
            "ekf.initial_angle_std_deg",
            self.initial_angle_std_deg,
            1e-3,
            90.0,
        )?;
        check::within(
            "ekf.initial_rate_std_degps",
            self.initial_rate_std_degps,
            1e-3,
            1000.0,
        )?;
        check::within("ekf.max_init_gap_s", self.max_init_gap_s, 0.002, 5.0)?;
        check::within("ekf.gate_nis", self.gate_nis, 1.0, 1e6)?;
        check::within_u32(
            "ekf.max_consecutive_rejections",
            self.max_consecutive_rejections,
            1,
            1000,
        )?;
        check::within("ekf.max_step_s", self.max_step_s, 1e-4, 0.1)?;
        check::within("ekf.horizon_s", self.horizon_s, 0.1, 60.0)?;
        check::within("ekf.min_observation_s", self.min_observation_s, 0.0, 60.0)?;
        check::within(
            "ekf.max_measurement_age_s",
            self.max_measurement_age_s,
            1e-3,
            10.0,
        )?;
        check::within(
            "ekf.commit_max_time_std_ms",
            self.commit_max_time_std_ms,
            1e-3,
            1000.0,
        )?;
        check::within("ekf.plane_noise_per_m", self.plane_noise_per_m, 0.0, 1.0)
    }
}

/// Errors of the filter's API: bad input, refused with nothing changed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum EkfError {
    /// A time, measurement or request value that is NaN or infinite.
    #[error("{what} is not a finite number")]
    NotFinite {
        /// Which input.
        what: &'static str,
    },
    /// A request value out of its range.
    #[error("{what} = {value} is out of range: {bound}")]
    OutOfRange {
        /// Which input.
        what: &'static str,
        /// The refused value.
        value: f64,
        /// The bound it broke.
        bound: &'static str,
    },
    /// The filter has no estimate yet (fewer than two measurements).
    #[error("the filter is not initialised yet")]
    NotInitialised,
    /// Invalid parameters.
    #[error(transparent)]
    Params(#[from] ParamError),
}

/// What happened to one measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MeasureOutcome {
    /// Kept; the filter needs one more measurement to initialise.
    Initialising,
    /// The filter initialised itself from this and the previous measurement.
    Initialised,
    /// Fused at its capture time; `nis` is its normalised innovation squared.
    Fused {
        /// Normalised innovation squared.
        nis: f64,
    },
    /// Gated out as an outlier (counted); the estimate did not move.
    Rejected {
        /// Normalised innovation squared (infinite when `|z| >= l`).
        nis: f64,
    },
    /// Too many rejections in a row: the filter restarted from this measurement.
    Reinitialising,
    /// Captured before everything the history still holds: dropped (counted).
    TooOld,
}

/// Counters the filter keeps instead of logging.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct EkfCounters {
    /// Measurements fused.
    pub fused: u64,
    /// Measurements gated out as outliers.
    pub rejected: u64,
    /// Measurements that arrived out of order and were fused at their capture time.
    pub out_of_order: u64,
    /// Measurements older than the history: dropped.
    pub too_old: u64,
    /// Automatic re-initialisations (rejections in a row, or a covariance that lost
    /// positive definiteness).
    pub reinitialisations: u64,
    /// Initialisations from measurements.
    pub initialisations: u64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum EntryKind {
    Init,
    Fused,
    Rejected,
}

/// One processed measurement and the posterior after it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Entry {
    t: f64,
    z: f64,
    kind: EntryKind,
    x: StateVec,
    p: StateCov,
}

const EMPTY_ENTRY: Entry = Entry {
    t: 0.0,
    z: 0.0,
    kind: EntryKind::Init,
    x: StateVec::from_array_storage(nalgebra::ArrayStorage([[0.0; model::N]])),
    p: StateCov::from_array_storage(nalgebra::ArrayStorage([[0.0; model::N]; model::N])),
};

/// Fixed-capacity ring of entries in capture-time order (oldest first).
#[derive(Debug, Clone, PartialEq)]
struct History {
    buf: [Entry; HISTORY_LEN],
    start: usize,
    len: usize,
}

impl History {
    fn new() -> Self {
        Self {
            buf: [EMPTY_ENTRY; HISTORY_LEN],
            start: 0,
            len: 0,
        }
    }
    fn idx(&self, i: usize) -> usize {
        (self.start + i) % HISTORY_LEN
    }
    fn get(&self, i: usize) -> &Entry {
        &self.buf[self.idx(i)]
    }
    fn set(&mut self, i: usize, e: Entry) {
        let k = self.idx(i);
        self.buf[k] = e;
    }
    fn clear(&mut self) {
        self.start = 0;
        self.len = 0;
    }
    fn last(&self) -> Option<&Entry> {
        self.len.checked_sub(1).map(|i| self.get(i))
    }
    fn drop_oldest(&mut self) {
        if self.len > 0 {
            self.start = (self.start + 1) % HISTORY_LEN;
            self.len -= 1;
        }
    }
    fn push(&mut self, e: Entry) {
        if self.len == HISTORY_LEN {
            self.drop_oldest();
        }
        self.len += 1;
        self.set(self.len - 1, e);
    }
    /// Inserts at logical position `pos` (1..=len), dropping the oldest entry when
    /// full; returns the position the entry ended up at.
    fn insert(&mut self, mut pos: usize, e: Entry) -> usize {
        if self.len == HISTORY_LEN {
            self.drop_oldest();
            pos = pos.saturating_sub(1);
        }
        self.len += 1;
        let mut i = self.len - 1;
        while i > pos {
            let prev = *self.get(i - 1);
            self.set(i, prev);
            i -= 1;
        }
        self.set(pos, e);
        pos
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Empty,
    Pending { t: f64, z: f64 },
    Running,
}

/// The extended Kalman filter over the damped pendulum (eqs. 1-16) with a predictor.
///
/// Step API with explicit timestamps; no allocation after construction. Feed each
/// camera measurement with [`Ekf::measure`] (capture time, lateral position); ask
/// [`Ekf::predict_at`], [`Ekf::crossings`] and [`Ekf::plan_motion`] at any time
/// without disturbing the filter.
#[derive(Debug, Clone, PartialEq)]
pub struct Ekf {
    params: EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
    r: f64,
    phase: Phase,
    history: History,
    t_init: f64,
    t_last_fused: f64,
    consecutive_rejections: u32,
    fused_since_init: u32,
    counters: EkfCounters,
    /// Priors of `k` and `b` (mean, variance) set by [`Ekf::set_constant_priors`]
    /// (what earlier trials learned); `None`: from the model and the parameters.
    k_prior: Option<(f64, f64)>,
    b_prior: Option<(f64, f64)>,
}

impl Ekf {
    /// A filter for a pendulum of `model` (its damping is the prior for `alpha`) hanging
    /// as `geometry` describes. The lengths of both must agree.
    ///
    /// # Errors
    ///
    /// [`EkfError::Params`] when `params` are invalid, the model's length, gravity or
    /// damping is out of range, or the geometry's length differs from the model's.
    pub fn new(
        params: EkfParams,
        model: PendulumModel,
        geometry: PendulumGeometry,
    ) -> Result<Self, EkfError> {
        params.validate()?;
        check::within("pendulum.length_m", model.length_m, 0.1, 10.0)?;
        check::within("pendulum.gravity_mps2", model.gravity_mps2, 0.1, 100.0)?;
        check::within("pendulum.damping_per_s", model.damping_per_s, -5.0, 5.0)?;
        if (model.length_m - geometry.length_m).abs() > 1e-9 {
            return Err(ParamError::OutOfRange {
                field: "pendulum.length_m".to_owned(),
                value: check::Value::Number(geometry.length_m),
                bound: check::Bound::Rule(format!(
                    "the geometry's length must equal the model's {}",
                    model.length_m
                )),
            }
            .into());
        }
        let r = params.measurement_noise_m * params.measurement_noise_m;
        Ok(Self {
            params,
            model,
            geometry,
            r,
            phase: Phase::Empty,
            history: History::new(),
            t_init: 0.0,
            t_last_fused: 0.0,
            consecutive_rejections: 0,
            fused_since_init: 0,
            counters: EkfCounters::default(),
            k_prior: None,
            b_prior: None,
        })
    }

    /// A filter for one trial of a scenario: the `[pendulum]` section, and the
    /// intercept point drawn for the trial (`task.distance_m`, `task.intercept_height_m`).
    ///
    /// # Errors
    ///
    /// [`EkfError::Params`] when the pendulum section, the distance or the intercept
    /// height is out of range, or as [`Ekf::new`].
    pub fn for_trial(
        params: EkfParams,
        pendulum: &PendulumParams,
        distance_m: f64,
        intercept_height_m: f64,
    ) -> Result<Self, EkfError> {
        let model = PendulumModel::from_params(pendulum)?;
        let geometry = PendulumGeometry::new(model.length_m, distance_m, intercept_height_m)?;
        Self::new(params, model, geometry)
    }

    /// The parameters in use.
    pub fn params(&self) -> &EkfParams {
        &self.params
    }

    /// The pendulum model (its damping is the prior for `alpha`).
    pub fn model(&self) -> &PendulumModel {
        &self.model
    }

    /// The pendulum's geometry in the robot base frame.
    pub fn geometry(&self) -> &PendulumGeometry {
        &self.geometry
    }

    /// Counters since construction.
    pub fn counters(&self) -> EkfCounters {
        self.counters
    }

    /// Whether the filter has an estimate.
    pub fn is_initialised(&self) -> bool {
        self.phase == Phase::Running
    }

    /// Forgets the estimate (e.g. when the ball is released); counters are kept.
    pub fn reset(&mut self) {
        self.phase = Phase::Empty;
        self.history.clear();
        self.consecutive_rejections = 0;
    }

    /// The current posterior: capture time of the last processed measurement, state
    /// and covariance; `None` before initialisation.
    pub fn posterior(&self) -> Option<(f64, StateVec, StateCov)> {
        match self.phase {
            Phase::Running => self.history.last().map(|e| (e.t, e.x, e.p)),
            _ => None,
        }
    }

    /// Capture time of the last fused measurement (or of initialisation).
    pub fn last_fused_s(&self) -> Option<f64> {
        self.is_initialised().then_some(self.t_last_fused)
    }

    /// When the filter (last) initialised, seconds.
    pub fn initialised_at_s(&self) -> Option<f64> {
        self.is_initialised().then_some(self.t_init)
    }

    /// Sets the state by hand at time `t_s` with angle and rate; the covariance comes
    /// from `initial_angle_std_deg`, `initial_rate_std_degps` and the priors of the
    /// estimated constants; `alpha`, `k` and `b` start at the model's values.
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] when `t_s`, `phi_rad` or `rate_radps` is NaN or infinite.
    pub fn initialise(&mut self, t_s: f64, phi_rad: f64, rate_radps: f64) -> Result<(), EkfError> {
        finite("t_s", t_s)?;
        finite("phi_rad", phi_rad)?;
        finite("rate_radps", rate_radps)?;
        let sa = self.params.initial_angle_std_deg.to_radians();
        let sr = self.params.initial_rate_std_degps.to_radians();
        let x = self.prior_state(phi_rad, rate_radps);
        let mut p = self.prior_cov();
        p[(0, 0)] = sa * sa;
        p[(1, 1)] = sr * sr;
        self.start_running(t_s, x, p);
        // A state set by hand is not suspected of coming from an outlier.
        self.fused_since_init = YOUNG_FILTER_FUSED;
        Ok(())
    }

    /// Replaces the priors of `k = g/l` and of the rest offset `b` (mean,
    /// variance) for the next initialisation, e.g. with what the earlier trials
    /// of a session learned; a constant whose switch is off keeps its model
    /// value. Non-finite or negative values are refused and change nothing.
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] for a non-finite mean or variance;
    /// [`EkfError::OutOfRange`] for a negative variance or a `k` mean that is not `> 0`.
    pub fn set_constant_priors(
        &mut self,
        k: Option<(f64, f64)>,
        b: Option<(f64, f64)>,
    ) -> Result<(), EkfError> {
        for (what, v) in [("k prior", k), ("b prior", b)] {
            if let Some((m, var)) = v {
                finite(what, m)?;
                finite(what, var)?;
                if var < 0.0 || (what == "k prior" && m <= 0.0) {
                    return Err(EkfError::OutOfRange {
                        what,
                        value: if var < 0.0 { var } else { m },
                        bound: "variance >= 0 and k > 0",
                    });
                }
            }
        }
        self.k_prior = k;
        self.b_prior = b;
        Ok(())
    }

    /// A state with the prior constants.
    fn prior_state(&self, phi: f64, rate: f64) -> StateVec {
        let k = match (self.params.estimate_frequency, self.k_prior) {
            (true, Some((m, _))) => m,
            _ => self.model.omega0_sq(),
        };
        let b = match (self.params.estimate_offset, self.b_prior) {
            (true, Some((m, _))) => m,
            _ => 0.0,
        };
        model::state(phi, rate, self.model.damping_per_s, k, b)
    }

    /// The priors of the constants (`alpha`, `k`, `b`) on the diagonal; zero for
    /// a constant that is not estimated.
    fn prior_cov(&self) -> StateCov {
        let mut p = StateCov::zeros();
        if self.params.estimate_damping {
            p[(ALPHA, ALPHA)] = self.params.damping_std_per_s * self.params.damping_std_per_s;
        }
        if self.params.estimate_frequency {
            let sk = self.model.omega0_sq() * self.params.length_std_m / self.model.length_m;
            p[(K, K)] = self.k_prior.map_or(sk * sk, |(_, v)| v);
        }
        if self.params.estimate_offset {
            p[(B, B)] = self.b_prior.map_or(
                self.params.offset_std_m * self.params.offset_std_m,
                |(_, v)| v,
            );
        }
        p
    }

    fn start_running(&mut self, t: f64, x: StateVec, p: StateCov) {
        self.history.clear();
        self.history.push(Entry {
            t,
            z: 0.0,
            kind: EntryKind::Init,
            x,
            p,
        });
        self.phase = Phase::Running;
        self.t_init = t;
        self.t_last_fused = t;
        self.consecutive_rejections = 0;
        self.fused_since_init = 0;
    }

    /// Fuses one lateral measurement `z_m` (base-frame y of the ball centre, metres)
    /// captured at `t_capture_s`. Measurements may arrive late and out of order: one
    /// captured before the newest fused one is fused at its capture time and the
    /// later ones are re-fused after it (within [`HISTORY_LEN`]). Non-finite input is
    /// refused and changes nothing.
    ///
    /// ```
    /// use rt_core::ekf::{Ekf, EkfParams};
    /// use rt_core::pendulum::{PendulumGeometry, PendulumModel};
    /// let model = PendulumModel { length_m: 1.93, gravity_mps2: 9.81, damping_per_s: 0.03 };
    /// let geometry = PendulumGeometry::new(1.93, 0.6, 0.3).unwrap();
    /// let mut ekf = Ekf::new(EkfParams::default(), model, geometry).unwrap();
    /// ekf.measure(0.0, 0.40).unwrap();
    /// ekf.measure(0.033, 0.38).unwrap();
    /// assert!(ekf.is_initialised());
    /// let before = ekf.posterior();
    /// // A NaN reading is refused and changes nothing.
    /// assert!(ekf.measure(0.066, f64::NAN).is_err());
    /// assert_eq!(ekf.posterior(), before);
    /// ```
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] when `t_capture_s` or `z_m` is NaN or infinite (an
    /// implausible measurement is `Ok(MeasureOutcome::Rejected)`).
    pub fn measure(&mut self, t_capture_s: f64, z_m: f64) -> Result<MeasureOutcome, EkfError> {
        finite("t_capture_s", t_capture_s)?;
        finite("z_m", z_m)?;
        let l = self.model.length_m;
        match self.phase {
            Phase::Empty => {
                if z_m.abs() >= l {
                    self.counters.rejected += 1;
                    return Ok(MeasureOutcome::Rejected { nis: f64::INFINITY });
                }
                self.phase = Phase::Pending {
                    t: t_capture_s,
                    z: z_m,
                };
                Ok(MeasureOutcome::Initialising)
            }
            Phase::Pending { t, z } => {
                if z_m.abs() >= l {
                    self.counters.rejected += 1;
                    return Ok(MeasureOutcome::Rejected { nis: f64::INFINITY });
                }
                let gap = (t_capture_s - t).abs();
                if gap < MIN_INIT_GAP_S || gap > self.params.max_init_gap_s {
                    // Too close to difference, or too far apart: keep the newer one.
                    if t_capture_s >= t {
                        self.phase = Phase::Pending {
                            t: t_capture_s,
                            z: z_m,
                        };
                    }
                    return Ok(MeasureOutcome::Initialising);
                }
                let ((t1, z1), (t2, z2)) = if t_capture_s > t {
                    ((t, z), (t_capture_s, z_m))
                } else {
                    ((t_capture_s, z_m), (t, z))
                };
                self.init_from_pair(t1, z1, t2, z2);
                Ok(MeasureOutcome::Initialised)
            }
            Phase::Running => Ok(self.measure_running(t_capture_s, z_m)),
        }
    }

    /// Initialises from two measurements: `phi = asin(z/l)`, `phi'` from their difference
    /// (taken at the midpoint and carried to `t2` with the model's acceleration).
    fn init_from_pair(&mut self, t1: f64, z1: f64, t2: f64, z2: f64) {
        let l = self.model.length_m;
        let prior = self.prior_state(0.0, 0.0);
        let (k, b0) = (prior[K], prior[B]);
        let alpha = self.model.damping_per_s;
        let p1 = ((z1 - b0) / l).clamp(-1.0, 1.0).asin();
        let p2 = ((z2 - b0) / l).clamp(-1.0, 1.0).asin();
        let dt = t2 - t1;
        let w_mid = (p2 - p1) / dt;
        let w2 = w_mid + 0.5 * dt * (-k * p2.sin() - alpha * w_mid);
        let c2 = l * p2.cos();
        let c1 = l * p1.cos();
        let var2 = self.r_at(z2) / (c2 * c2);
        let var1 = self.r_at(z1) / (c1 * c1);
        // Rate variance from the difference, plus a floor for the model's error.
        let var_w = (var1 + var2) / (dt * dt) + (0.05 * k * dt).powi(2);
        let cov_pw = var2 / dt;
        let mut p = self.prior_cov();
        p[(0, 0)] = var2;
        p[(0, 1)] = cov_pw;
        p[(1, 0)] = cov_pw;
        p[(1, 1)] = var_w;
        if self.params.estimate_offset {
            // The angle was read with b = 0: it carries b's uncertainty
            // (d phi / d b = -1 / (l cos phi); the rate's cancels in the difference).
            let vb = p[(B, B)];
            p[(0, 0)] += vb / (c2 * c2);
            p[(0, B)] = -vb / c2;
            p[(B, 0)] = -vb / c2;
        }
        self.start_running(t2, self.prior_state(p2, w2), p);
        self.counters.initialisations += 1;
    }

    fn measure_running(&mut self, t: f64, z: f64) -> MeasureOutcome {
        let Some(last) = self.history.last().copied() else {
            self.phase = Phase::Empty;
            return MeasureOutcome::Initialising;
        };
        if t - last.t > self.params.horizon_s {
            // Coasted longer than the horizon: the estimate is stale, start again.
            self.counters.reinitialisations += 1;
            self.reset();
            if z.abs() < self.model.length_m {
                self.phase = Phase::Pending { t, z };
            }
            return MeasureOutcome::Reinitialising;
        }
        let (pos, outcome) = if t >= last.t {
            let (entry, nis) = self.filter_step(&last, t, z);
            self.history.push(entry);
            (None, (entry.kind, nis))
        } else {
            // Late: find the newest entry captured at or before t.
            let mut j = None;
            for i in (0..self.history.len).rev() {
                if self.history.get(i).t <= t {
                    j = Some(i);
                    break;
                }
            }
            let Some(j) = j else {
                self.counters.too_old += 1;
                return MeasureOutcome::TooOld;
            };
            let prev = *self.history.get(j);
            let (entry, nis) = self.filter_step(&prev, t, z);
            let pos = self.history.insert(j + 1, entry);
            self.counters.out_of_order += 1;
            (Some(pos), (entry.kind, nis))
        };
        if let Some(pos) = pos {
            self.refilter_after(pos);
        }
        let (kind, nis) = outcome;
        if !self.covariance_ok() {
            self.counters.reinitialisations += 1;
            self.reset();
            self.phase = Phase::Pending { t, z };
            return MeasureOutcome::Reinitialising;
        }
        if kind == EntryKind::Fused {
            self.counters.fused += 1;
            self.fused_since_init = self.fused_since_init.saturating_add(1);
            self.consecutive_rejections = 0;
            self.t_last_fused = self.t_last_fused.max(t);
            MeasureOutcome::Fused { nis }
        } else {
            self.counters.rejected += 1;
            self.consecutive_rejections += 1;
            // A young filter that rejects was most likely started from an outlier.
            let young = self.fused_since_init < YOUNG_FILTER_FUSED;
            if young || self.consecutive_rejections >= self.params.max_consecutive_rejections {
                self.counters.reinitialisations += 1;
                self.reset();
                if z.abs() < self.model.length_m {
                    self.phase = Phase::Pending { t, z };
                }
                return MeasureOutcome::Reinitialising;
            }
            MeasureOutcome::Rejected { nis }
        }
    }

    /// Re-runs every entry after `pos` from the posterior at `pos`.
    fn refilter_after(&mut self, pos: usize) {
        for i in (pos + 1)..self.history.len {
            let prev = *self.history.get(i - 1);
            let cur = *self.history.get(i);
            let (entry, _) = self.filter_step(&prev, cur.t, cur.z);
            self.history.set(i, entry);
        }
    }

    fn covariance_ok(&self) -> bool {
        self.history.last().is_some_and(|e| {
            e.x.iter().all(|v| v.is_finite())
                && e.p.iter().all(|v| v.is_finite())
                && e.p[(0, 0)] > 0.0
                && e.p[(1, 1)] > 0.0
                && (2..model::N).all(|i| e.p[(i, i)] >= 0.0)
        })
    }

    /// Predict from `prev` to `t`, then the gated Joseph-form update with `z`.
    /// The measurement's variance at lateral reading `z`: the noise's, plus
    /// the out-of-plane bend's (`plane_noise_per_m`).
    fn r_at(&self, z: f64) -> f64 {
        let bend = self.params.plane_noise_per_m * z * z;
        self.r + bend * bend
    }

    fn filter_step(&self, prev: &Entry, t: f64, z: f64) -> (Entry, f64) {
        let (x, p) = self.propagate(&prev.x, &prev.p, t - prev.t);
        let l = self.model.length_m;
        let mut entry = Entry {
            t,
            z,
            kind: EntryKind::Rejected,
            x,
            p,
        };
        if z.abs() >= l {
            return (entry, f64::INFINITY);
        }
        let (zh, c) = model::measure(l, &x);
        let pct = p * c.transpose();
        let r = self.r_at(z);
        let s = (c * pct)[0] + r;
        let innov = z - zh;
        let nis = innov * innov / s;
        if nis.is_nan() || nis > self.params.gate_nis {
            return (entry, nis);
        }
        // Iterated EKF (Gauss-Newton on the measurement): relinearise `h` at the
        // updated estimate until the angle settles, so a large first correction is not
        // distorted by `cos` taken at the wrong angle.
        let mut xi = x + pct * (innov / s);
        let mut c_i = c;
        let mut s_i = s;
        for _ in 0..MAX_IEKF_ITERATIONS {
            let (zi, ci) = model::measure(l, &xi);
            let pci = p * ci.transpose();
            let si = (ci * pci)[0] + r;
            let next = x + pci * ((z - zi - (ci * (x - xi))[0]) / si);
            let change = (next[0] - xi[0]).abs();
            xi = next;
            c_i = ci;
            s_i = si;
            if change < IEKF_TOLERANCE_RAD {
                break;
            }
        }
        let k = p * c_i.transpose() / s_i;
        // Joseph form (I - k c) P (I - k c)^T + k r k^T, with the two products
        // by I - k c done as rank-one updates: (I - k c) P = P - k (c P), then
        // M (I - k c)^T = M - (M c^T) k^T.
        let m = p - k * (c_i * p);
        let pn = m - (m * c_i.transpose()) * k.transpose() + k * k.transpose() * r;
        entry.x = xi;
        entry.p = (pn + pn.transpose()) * 0.5;
        entry.kind = EntryKind::Fused;
        (entry, nis)
    }

    /// Carries `(x, p)` over `dt` (either sign) in sub-steps of at most `max_step_s`.
    fn propagate(&self, x: &StateVec, p: &StateCov, dt: f64) -> (StateVec, StateCov) {
        let n = (dt.abs() / self.params.max_step_s).ceil().max(1.0);
        let h = dt / n;
        let mut x = *x;
        let mut p = *p;
        if dt == 0.0 {
            return (x, p);
        }
        let q = self.q(h);
        // `n` is a whole number >= 1 bounded by the finite time span.
        for _ in 0..(n as u64) {
            let (xn, f) = model::step(self.params.process_model, &x, h);
            x = xn;
            p = model::carry_cov(&f, &p) + q;
        }
        (x, (p + p.transpose()) * 0.5)
    }

    fn q(&self, h: f64) -> StateCov {
        let accel = match self.params.process_noise_model {
            ProcessNoiseModel::Continuous => self.params.accel_psd_rad2ps3,
            ProcessNoiseModel::Paper => self.params.accel_var_rad2ps4,
        };
        let damping = if self.params.estimate_damping {
            self.params.damping_psd_per_s3
        } else {
            0.0
        };
        model::process_noise(self.params.process_noise_model, accel, damping, h)
    }
}

fn finite(what: &'static str, v: f64) -> Result<(), EkfError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(EkfError::NotFinite { what })
    }
}

#[cfg(test)]
mod tests;
