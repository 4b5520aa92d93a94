//! Batch runs (`POST /api/runs`): `n` trials one after another, each with the
//! distance, movement time and release angle the run gives it, started when
//! the lab can take it (`GET /api/health`'s readiness, never by retrying
//! refusals), each recorded as any trial is. Progress goes to the WebSocket
//! (`{"type":"run", ...}` after every trial) and `GET /api/runs/{id}`;
//! `DELETE /api/runs/{id}` stops the run after its current trial. Runs live
//! in memory: their trials are in the trial records.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rt_core::bridge::TrialSetup;
use rt_core::control::stats::{quantile_sorted, wilson_ci95};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::AppState;
use crate::error::AppError;

/// Longest a run waits for the lab to take its next trial, seconds.
const READY_TIMEOUT_S: f64 = 120.0;
/// Longest one trial of a run may take to finish its record, seconds.
const TRIAL_TIMEOUT_S: f64 = 120.0;
/// Trials the control loop may refuse after answering their start late
/// (each never ran, and is started again) before a run gives up.
const MAX_LATE_REFUSALS: u32 = 3;
/// Runs kept (the oldest finished ones are forgotten first).
const KEEP: usize = 64;
/// Most trials one run may have.
pub const MAX_TRIALS: u32 = 10_000;

/// `POST /api/runs` body.
#[derive(Debug, Clone, Deserialize, ToSchema, ts_rs::TS)]
#[serde(deny_unknown_fields)]
pub struct RunRequest {
    /// How many trials (1..=10000).
    #[schema(minimum = 1, maximum = 10000)]
    pub n: u32,
    /// The trials' distances, metres: one for all, or a list the trials take
    /// in turn (trial i: `distance_m[i % len]`). Absent: drawn as usual.
    pub distance_m: Option<Distances>,
    /// Distances spread evenly over `[lo, hi]` metres across the run
    /// (trial i: `lo + (hi - lo) i / (n - 1)`); not with `distance_m`.
    pub distance_range_m: Option<[f64; 2]>,
    /// Every trial's planned movement time, seconds (else the lab's).
    pub movement_time_s: Option<f64>,
    /// Every trial's release angle magnitude, degrees (else drawn).
    pub release_deg: Option<f64>,
    /// Every trial's task, `stop` or `strike` (else the lab's `task.mode`).
    pub mode: Option<rt_core::trajectory::TaskMode>,
    /// Every strike's tool speed at contact, m/s (else the lab's); only
    /// for strikes.
    #[schema(minimum = 0.0, maximum = 5.0)]
    pub strike_speed_mps: Option<f64>,
    /// Every strike's direction above the swing's horizontal, degrees (else
    /// the lab's); only for strikes.
    #[schema(minimum = -60.0, maximum = 60.0)]
    pub strike_direction_deg: Option<f64>,
}

/// One distance, or a list of them.
#[derive(Debug, Clone, Deserialize, ToSchema, ts_rs::TS)]
#[serde(untagged)]
pub enum Distances {
    /// The same distance for every trial, metres.
    One(f64),
    /// Distances the trials take in turn, metres.
    List(Vec<f64>),
}

/// A run as `GET /api/runs/{id}` shows it.
#[derive(Debug, Clone, Serialize, ToSchema, ts_rs::TS)]
pub struct RunStatus {
    /// The run's id.
    #[ts(type = "number")]
    pub id: u64,
    /// `running`, `done` (all trials ran), `stopped` (by `DELETE`) or
    /// `failed` (the lab could not take a trial; `message` says why).
    pub status: &'static str,
    /// Trials asked for.
    pub n: u32,
    /// Trials started so far, in order (their records: `/api/trials/{id}`).
    #[ts(type = "number[]")]
    pub trial_ids: Vec<u64>,
    /// Trials whose records finished.
    pub finished: u32,
    /// Finished trials judged (not `not judged`, not aborted without a verdict).
    pub judged: u32,
    /// Judged trials that succeeded.
    pub successes: u32,
    /// Successes / finished trials (0 when none finished).
    pub success_rate: f64,
    /// Wilson 95% interval of the success rate over the finished trials.
    pub success_ci95: [f64; 2],
    /// |timing error| of the judged trials, median, milliseconds (null: none).
    pub timing_error_ms_p50: Option<f64>,
    /// |timing error| of the judged trials, 95th percentile (linear
    /// interpolation, numpy's default), milliseconds (null: none).
    pub timing_error_ms_p95: Option<f64>,
    /// Unix time the run started, seconds.
    pub started_unix_s: f64,
    /// Unix time it ended, seconds (null while running).
    pub finished_unix_s: Option<f64>,
    /// Why it failed or stopped (null otherwise).
    pub message: Option<String>,
    #[serde(skip)]
    #[ts(skip)]
    timing: Vec<f64>,
    #[serde(skip)]
    #[ts(skip)]
    stop: bool,
}

/// `POST /api/runs` answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct RunStarted {
    /// The run's id (`GET /api/runs/{id}`).
    pub id: u64,
}

/// The runs of this service.
#[derive(Debug, Default)]
pub struct Runs {
    runs: Mutex<BTreeMap<u64, RunStatus>>,
}

impl RunStatus {
    fn fold(&mut self, record: &crate::records::TrialRecord) {
        self.finished += 1;
        if record.status == "done"
            && let Some(ok) = record.success
        {
            self.judged += 1;
            self.successes += u32::from(ok);
            if let Some(t) = record.timing_error_ms {
                self.timing.push(t.abs());
            }
        }
        self.success_rate = if self.finished > 0 {
            f64::from(self.successes) / f64::from(self.finished)
        } else {
            0.0
        };
        self.success_ci95 = wilson_ci95(self.successes as usize, self.finished as usize);
        let mut sorted = self.timing.clone();
        sorted.sort_by(f64::total_cmp);
        let q = |p| (!sorted.is_empty()).then(|| quantile_sorted(&sorted, p));
        self.timing_error_ms_p50 = q(0.5);
        self.timing_error_ms_p95 = q(0.95);
    }
}

fn bad(field: &str, message: String) -> AppError {
    AppError::BadRequest {
        message,
        field: Some(field.to_owned()),
    }
}

/// The trials' setups, checked (each distinct setup against the parameters
/// in force, as `POST /api/trials` checks one), or a 400 naming the field.
///
/// # Errors
///
/// [`AppError::BadRequest`] naming the field: `n` out of range, both or bad
/// distance fields, or a trial setup [`POST /api/trials`](crate::api::start_trial)
/// would refuse.
pub fn setups(
    req: &RunRequest,
    params: &rt_core::params::Scenario,
    fixed_distance_m: Option<f64>,
) -> Result<Vec<TrialSetup>, AppError> {
    if !(1..=MAX_TRIALS).contains(&req.n) {
        return Err(bad(
            "n",
            format!(
                "n = {} is out of range: must be in [1, {MAX_TRIALS}]",
                req.n
            ),
        ));
    }
    let n = req.n as usize;
    let distances: Vec<Option<f64>> = match (&req.distance_m, req.distance_range_m) {
        (Some(_), Some(_)) => {
            return Err(bad(
                "distance_range_m",
                "give distance_m or distance_range_m, not both".into(),
            ));
        }
        (Some(Distances::One(d)), None) => vec![Some(*d); n],
        (Some(Distances::List(l)), None) if l.is_empty() || l.len() > 1000 => {
            return Err(bad(
                "distance_m",
                "distance_m must list 1 to 1000 distances".into(),
            ));
        }
        (Some(Distances::List(l)), None) => (0..n).map(|i| Some(l[i % l.len()])).collect(),
        (None, Some([lo, hi])) => {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return Err(bad(
                    "distance_range_m",
                    format!("distance_range_m = [{lo}, {hi}] must be finite with lo <= hi"),
                ));
            }
            (0..n)
                .map(|i| Some(lo + (hi - lo) * i as f64 / (n.max(2) - 1) as f64))
                .collect()
        }
        (None, None) => vec![None; n],
    };
    let mut checked: Vec<(u64, TrialSetup)> = Vec::new();
    distances
        .into_iter()
        .map(|d| {
            let key = d.map_or(u64::MAX, f64::to_bits);
            if let Some((_, s)) = checked.iter().find(|(k, _)| *k == key) {
                return Ok(*s);
            }
            let one = crate::api::TrialRequest {
                distance_m: d,
                movement_time_s: req.movement_time_s,
                release_deg: req.release_deg,
                mode: req.mode,
                strike_speed_mps: req.strike_speed_mps,
                strike_direction_deg: req.strike_direction_deg,
            };
            let s =
                crate::api::trial_setup(&one, params, fixed_distance_m).map_err(|e| match e {
                    // A listed or spread distance is the run's `distance_m` /
                    // `distance_range_m`.
                    AppError::BadRequest { message, field }
                        if field.as_deref() == Some("distance_m")
                            && req.distance_range_m.is_some() =>
                    {
                        bad("distance_range_m", message)
                    }
                    e => e,
                })?;
            checked.push((key, s));
            Ok(s)
        })
        .collect()
}

impl Runs {
    /// A run's status.
    pub fn get(&self, id: u64) -> Option<RunStatus> {
        self.runs.lock().ok()?.get(&id).cloned()
    }

    /// Every run kept, newest first.
    pub fn list(&self) -> Vec<RunStatus> {
        self.runs
            .lock()
            .map(|r| r.values().rev().cloned().collect())
            .unwrap_or_default()
    }

    /// Asks a run to stop after its current trial; false when there is no such run.
    pub fn stop(&self, id: u64) -> bool {
        let Ok(mut runs) = self.runs.lock() else {
            return false;
        };
        match runs.get_mut(&id) {
            Some(r) => {
                r.stop = true;
                true
            }
            None => false,
        }
    }

    fn update(&self, id: u64, f: impl FnOnce(&mut RunStatus)) -> Option<RunStatus> {
        let mut runs = self.runs.lock().ok()?;
        let r = runs.get_mut(&id)?;
        f(r);
        Some(r.clone())
    }

    /// Registers a run; refused (409) while another runs.
    fn begin(&self, n: u32) -> Result<u64, AppError> {
        let mut runs = self
            .runs
            .lock()
            .map_err(|_| AppError::Internal(anyhow::anyhow!("run table lock poisoned")))?;
        if let Some(r) = runs.values().find(|r| r.status == "running") {
            return Err(AppError::Conflict {
                message: format!(
                    "refused: run {} is running (DELETE /api/runs/{} stops it)",
                    r.id, r.id
                ),
                field: None,
                reason: Some("busy"),
            });
        }
        let id = runs.keys().next_back().map_or(1, |k| k + 1);
        while runs.len() >= KEEP {
            let Some(oldest) = runs.keys().next().copied() else {
                break;
            };
            runs.remove(&oldest);
        }
        runs.insert(
            id,
            RunStatus {
                id,
                status: "running",
                n,
                trial_ids: Vec::new(),
                finished: 0,
                judged: 0,
                successes: 0,
                success_rate: 0.0,
                success_ci95: wilson_ci95(0, 0),
                timing_error_ms_p50: None,
                timing_error_ms_p95: None,
                started_unix_s: crate::records::unix_now_s(),
                finished_unix_s: None,
                message: None,
                timing: Vec::new(),
                stop: false,
            },
        );
        Ok(id)
    }
}

/// Starts a run: checks it, registers it and spawns its task.
///
/// # Errors
///
/// [`AppError::Unavailable`] without a running lab or trial records;
/// [`AppError::BadRequest`] as [`setups`]; [`AppError::Conflict`] while another run
/// is going.
pub fn start(state: Arc<AppState>, req: &RunRequest) -> Result<u64, AppError> {
    let lab = state
        .lab
        .as_ref()
        .ok_or_else(|| AppError::Unavailable("the lab is not running".into()))?;
    if state.records.is_none() {
        return Err(AppError::Unavailable("no trial records are kept".into()));
    }
    let setups = setups(req, &lab.params(), lab.options().fixed_distance_m)?;
    let id = state.runs.begin(req.n)?;
    tokio::spawn(run(state, id, setups));
    Ok(id)
}

fn publish(state: &AppState, r: &RunStatus) {
    #[derive(Serialize)]
    struct Msg<'a> {
        #[serde(rename = "type")]
        kind: &'static str,
        run: &'a RunStatus,
    }
    if let (Some(lab), Ok(text)) = (
        state.lab.as_ref(),
        serde_json::to_string(&Msg {
            kind: "run",
            run: r,
        }),
    ) {
        lab.publish_event_text(text);
    }
}

async fn run(state: Arc<AppState>, id: u64, setups: Vec<TrialSetup>) {
    let end = |status: &'static str, message: Option<String>| {
        let r = state.runs.update(id, |r| {
            r.status = status;
            r.message = message;
            r.finished_unix_s = Some(crate::records::unix_now_s());
        });
        if let Some(r) = r {
            publish(&state, &r);
        }
    };
    // Trials the loop refused after answering late (they never ran) are
    // started again, a few times at most.
    let mut late_refusals = 0u32;
    let mut next = 0usize;
    while let Some(&setup) = setups.get(next) {
        if state.runs.get(id).is_none_or(|r| r.stop) {
            return end("stopped", Some("stopped by DELETE /api/runs/{id}".into()));
        }
        // Wait until the lab would take a trial, then start it.
        let deadline = Instant::now() + Duration::from_secs_f64(READY_TIMEOUT_S);
        // `late`: the control loop answered the start only after the
        // service stopped waiting; the record settles when it does.
        let (trial, late) = loop {
            if crate::not_ready(&state).is_none() {
                match crate::api::start_one(&state, setup).await {
                    Ok(t) => break (t, false),
                    Err(AppError::Unanswered { trial: Some(t) }) => break (t, true),
                    // Taken in between (another operator's trial): wait again.
                    Err(AppError::Conflict { .. }) => {}
                    Err(e) => return end("failed", Some(e.to_string())),
                }
            }
            if Instant::now() > deadline {
                let why = crate::not_ready(&state).map_or_else(String::new, |n| n.message);
                return end(
                    "failed",
                    Some(format!(
                        "the lab took no trial for {READY_TIMEOUT_S} s: {why}"
                    )),
                );
            }
            if state.runs.get(id).is_none_or(|r| r.stop) {
                return end("stopped", Some("stopped by DELETE /api/runs/{id}".into()));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        state.runs.update(id, |r| r.trial_ids.push(trial));
        // Wait for its record to finish.
        let Some(records) = state.records.clone() else {
            return end("failed", Some("no trial records are kept".into()));
        };
        let deadline = Instant::now() + Duration::from_secs_f64(TRIAL_TIMEOUT_S);
        let record = loop {
            let r = Arc::clone(&records);
            let rec = tokio::task::spawn_blocking(move || r.get(trial))
                .await
                .ok()
                .and_then(Result::ok)
                .flatten();
            match rec {
                Some(rec) if rec.status != "running" => break Some(rec),
                // A late answer that refused the trial: it never ran.
                None if late => break None,
                None => {
                    return end(
                        "failed",
                        Some(format!("trial {trial}'s record disappeared")),
                    );
                }
                _ => {}
            }
            if Instant::now() > deadline {
                return end(
                    "failed",
                    Some(format!(
                        "trial {trial} did not finish within {TRIAL_TIMEOUT_S} s"
                    )),
                );
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        let Some(record) = record else {
            let r = state
                .runs
                .update(id, |r| r.trial_ids.retain(|&t| t != trial));
            if let Some(r) = r {
                publish(&state, &r);
            }
            late_refusals += 1;
            if late_refusals > MAX_LATE_REFUSALS {
                return end(
                    "failed",
                    Some(format!(
                        "the control loop refused {late_refusals} trials after answering late"
                    )),
                );
            }
            continue;
        };
        next += 1;
        if let Some(r) = state.runs.update(id, |r| r.fold(&record)) {
            publish(&state, &r);
        }
    }
    end("done", None);
}
