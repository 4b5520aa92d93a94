//! Demo mode (`isochron serve --demo`): trials run unattended, one every
//! `interval_s` seconds (start to start; right after the previous one when it
//! took longer), each with its own distance and movement time taken in turn
//! from [`DISTANCES_M`] and [`MOVEMENT_TIMES_S`] (a lab that cannot move its
//! pendulum, `crate::LabOptions::fixed_distance_m`: every trial where it
//! hangs, the movement times in turn; each trial checked as
//! `POST /api/trials` checks one: a combination the parameters in force make
//! infeasible is skipped). A trial starts only when the lab would take it
//! (`GET /api/health`'s readiness); otherwise the demo is `paused` and says
//! why; a pause is shown for at least [`PAUSE_SHOWN`] (a calibration step
//! on the simulated lab takes about two seconds, too short for a visitor to
//! read, or for a page polling once a second to see). In a real lab (`lab.mode = "real"`) it runs only while an operator
//! holds it enabled (the operator heartbeat, `POST /api/heartbeat`, within
//! the dead-man time): without one it starts nothing, and when the heartbeats
//! lapse during a demo trial it stops the arm (`POST /api/stop`'s stop).
//!
//! The counts are kept in `DATA_DIR/demo.json`, so a restarted service goes
//! on counting; `GET /api/demo` shows the status, the page `/demo` shows it
//! to visitors.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rt_core::control::stats::wilson_ci95;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::AppState;
use crate::error::AppError;

/// The distances the demo's trials take in turn, metres (seven: with two
/// movement times every pair comes up within 14 trials).
pub const DISTANCES_M: [f64; 7] = [0.40, 0.70, 0.50, 0.75, 0.45, 0.65, 0.55];
/// The movement times the demo's trials take in turn, seconds.
pub const MOVEMENT_TIMES_S: [f64; 2] = [1.5, 2.0];
/// Default seconds from one demo trial's start to the next.
pub const DEFAULT_INTERVAL_S: f64 = 10.0;
/// Allowed `--demo-interval-s`, seconds.
pub const INTERVAL_RANGE_S: (f64, f64) = (1.0, 3600.0);
/// Longest a demo trial may take to finish its record before the demo gives
/// up on it (and stops the arm), seconds.
const TRIAL_TIMEOUT_S: f64 = 120.0;
/// How often the runner looks at the lab.
const TICK: Duration = Duration::from_millis(100);
/// The shortest a pause is shown (and no trial started): a visitor reads why.
pub const PAUSE_SHOWN: Duration = Duration::from_secs(5);
/// The counts' file in the data directory.
pub const STATE_FILE: &str = "demo.json";

/// How `isochron serve --demo` runs its demo.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Seconds from one trial's start to the next.
    pub interval_s: f64,
    /// A real lab: trials only while an operator's heartbeats arrive.
    pub operator_required: bool,
    /// The operator's heartbeats must be at most this far apart, seconds.
    pub operator_timeout_s: f64,
    /// Where the counts are kept (none: in memory only).
    pub state_file: Option<PathBuf>,
}

impl DemoOptions {
    /// Checks the interval (a clear error naming the flag).
    ///
    /// # Errors
    ///
    /// When the interval is not finite or outside [`INTERVAL_RANGE_S`], naming
    /// `--demo-interval-s`.
    pub fn check(&self) -> anyhow::Result<()> {
        let (lo, hi) = INTERVAL_RANGE_S;
        if !(self.interval_s.is_finite() && (lo..=hi).contains(&self.interval_s)) {
            anyhow::bail!(
                "--demo-interval-s {} is out of range: must be in [{lo}, {hi}] seconds",
                self.interval_s
            );
        }
        Ok(())
    }
}

/// The demo as `GET /api/demo` shows it.
#[derive(Debug, Clone, Serialize, ToSchema, ts_rs::TS)]
pub struct DemoStatus {
    /// The service was started with `--demo`.
    pub enabled: bool,
    /// `off` (no `--demo`), `running` (a demo trial runs), `waiting` (for the
    /// next trial's time, or for another trial to finish), `paused` (the lab
    /// cannot run a trial now: `reason` and `message` say why) or
    /// `operator_needed` (a real lab: no operator holds the demo enabled).
    #[ts(type = "\"off\" | \"running\" | \"waiting\" | \"paused\" | \"operator_needed\"")]
    pub state: &'static str,
    /// Why it is paused or waiting: `/api/health`'s `not_ready.reason`
    /// (`uncalibrated`, `calibrating`, `robot_not_commanding`,
    /// `device_unavailable`, `busy`, ...), `operator` (no heartbeat) or
    /// `infeasible` (the parameters in force make its motions infeasible).
    pub reason: Option<String>,
    /// The state as a sentence a visitor reads.
    pub message: String,
    /// The lab's own sentence for why it is paused (an operator's detail;
    /// null when not paused).
    pub detail: Option<String>,
    /// Seconds from one trial's start to the next.
    pub interval_s: f64,
    /// Trials run only while an operator holds the demo enabled (a real lab).
    pub operator_required: bool,
    /// The demo trial running now, or the last one.
    #[ts(type = "number | null")]
    pub trial_id: Option<u64>,
    /// Seconds until the next trial may start (null: not waiting for time).
    pub next_in_s: Option<f64>,
    /// The next trial's distance, metres.
    pub next_distance_m: Option<f64>,
    /// The next trial's planned movement time, seconds.
    pub next_movement_time_s: Option<f64>,
    /// Demo trials whose records finished (across restarts: `demo.json`).
    pub trials: u32,
    /// Of them, judged (not aborted, not `not judged`).
    pub judged: u32,
    /// Of the judged, precisely timed (the judge's success).
    pub successes: u32,
    /// Wilson 95% interval of successes / judged (`[0, 1]` before any).
    pub success_ci95: [f64; 2],
    /// Demo trials aborted (the lab stopped them: a device, the operator, ...).
    pub aborted: u32,
}

/// The counts kept in `demo.json`.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
struct Counts {
    trials: u32,
    judged: u32,
    successes: u32,
    aborted: u32,
    /// Trials started so far (which distance and movement time come next).
    started: u64,
}

/// The demo's status holder (one per service).
#[derive(Debug)]
pub struct Demo {
    status: Mutex<DemoStatus>,
}

impl Default for Demo {
    fn default() -> Self {
        Self {
            status: Mutex::new(DemoStatus {
                enabled: false,
                state: "off",
                reason: None,
                message: "demo mode is off (start the service with `isochron serve --demo`)".into(),
                detail: None,
                interval_s: DEFAULT_INTERVAL_S,
                operator_required: false,
                trial_id: None,
                next_in_s: None,
                next_distance_m: None,
                next_movement_time_s: None,
                trials: 0,
                judged: 0,
                successes: 0,
                success_ci95: wilson_ci95(0, 0),
                aborted: 0,
            }),
        }
    }
}

impl Demo {
    /// The status now.
    pub fn status(&self) -> DemoStatus {
        self.status
            .lock()
            .map_or_else(|p| p.into_inner().clone(), |s| s.clone())
    }

    fn set(&self, f: impl FnOnce(&mut DemoStatus)) {
        let mut s = self
            .status
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        f(&mut s);
    }
}

/// The `k`-th demo trial's distance and movement time.
pub fn plan(k: u64) -> (f64, f64) {
    let d = DISTANCES_M[(k % DISTANCES_M.len() as u64) as usize];
    let t = MOVEMENT_TIMES_S[(k % MOVEMENT_TIMES_S.len() as u64) as usize];
    (d, t)
}

/// What the demo does when it is not running a trial of its own: the lab's
/// readiness and the operator's hold decide. `None`: start the next trial.
/// `Some(Hold)` otherwise.
pub fn hold(
    not_ready: Option<&crate::NotReady>,
    operator_required: bool,
    operator_present: bool,
) -> Option<Hold> {
    hold_inner(not_ready, operator_required, operator_present).map(|(state, reason, message)| {
        Hold {
            state,
            reason,
            message,
            detail: not_ready.map(|n| n.message.clone()),
        }
    })
}

/// Why the demo does not start a trial now.
#[derive(Debug, Clone, PartialEq)]
pub struct Hold {
    /// `waiting`, `paused` or `operator_needed`.
    pub state: &'static str,
    /// The readiness' reason, or `operator`.
    pub reason: Option<String>,
    /// A sentence a visitor reads.
    pub message: String,
    /// The lab's own sentence (`/api/health`'s `not_ready.message`).
    pub detail: Option<String>,
}

fn hold_inner(
    not_ready: Option<&crate::NotReady>,
    operator_required: bool,
    operator_present: bool,
) -> Option<(&'static str, Option<String>, String)> {
    if let Some(n) = not_ready {
        if n.reason == "busy" {
            return Some((
                "waiting",
                Some("busy".into()),
                "waiting for the trial that is running to finish".into(),
            ));
        }
        return Some((
            "paused",
            Some(n.reason.to_owned()),
            format!("paused: {}", visitor_sentence(n.reason)),
        ));
    }
    if operator_required && !operator_present {
        return Some((
            "operator_needed",
            Some("operator".into()),
            "paused: on the real robot the demo runs only while an operator holds it enabled \
             (the operator's page open with the token, sending its heartbeat)"
                .into(),
        ));
    }
    None
}

/// The lab's reason in words a visitor reads.
fn visitor_sentence(reason: &str) -> &'static str {
    match reason {
        "uncalibrated" => "the lab needs its calibration before it can run",
        "calibrating" => "the lab is being calibrated",
        "robot_not_commanding" => "the robot is not taking commands",
        "device_unavailable" => "a device (camera or magnet) is not available",
        "starting" => "the lab is starting",
        "no_lab" => "no lab runs in this service",
        _ => "the lab cannot run a trial now",
    }
}

fn load(path: Option<&PathBuf>) -> Counts {
    path.and_then(|p| std::fs::read_to_string(p).ok())
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or_default()
}

fn save(path: Option<&PathBuf>, c: &Counts) {
    let Some(p) = path else { return };
    let tmp = p.with_extension("json.tmp");
    let ok = serde_json::to_vec(c)
        .ok()
        .is_some_and(|b| std::fs::write(&tmp, b).is_ok() && std::fs::rename(&tmp, p).is_ok());
    if !ok {
        tracing::warn!(file = %p.display(), "cannot write the demo's counts");
    }
}

/// Starts the demo runner on the current tokio runtime.
pub fn spawn(state: Arc<AppState>, opts: DemoOptions) {
    let counts = load(opts.state_file.as_ref());
    state.demo.set(|s| {
        s.enabled = true;
        s.state = "waiting";
        s.message = "starting".into();
        s.interval_s = opts.interval_s;
        s.operator_required = opts.operator_required;
        apply(s, &counts);
    });
    tracing::info!(
        interval_s = opts.interval_s,
        operator_required = opts.operator_required,
        trials = counts.trials,
        "demo mode: trials run unattended"
    );
    tokio::spawn(run(state, opts, counts));
}

fn apply(s: &mut DemoStatus, c: &Counts) {
    s.trials = c.trials;
    s.judged = c.judged;
    s.successes = c.successes;
    s.aborted = c.aborted;
    s.success_ci95 = wilson_ci95(c.successes as usize, c.judged as usize);
}

/// Keeps a pause shown for at least [`PAUSE_SHOWN`] after it began.
#[derive(Debug, Default)]
struct PauseShown {
    since: Option<Instant>,
    last: Option<Hold>,
}

impl PauseShown {
    /// The hold to show at `now`, given the lab's hold now.
    fn shown(&mut self, hold: Option<Hold>, now: Instant) -> Option<Hold> {
        if let Some(h) = hold.as_ref().filter(|h| h.state == "paused") {
            self.since.get_or_insert(now);
            self.last = Some(h.clone());
            return hold;
        }
        if self.last.is_some() && hold.is_none() {
            // A noted pause starts its time when it can first be shown.
            let since = *self.since.get_or_insert(now);
            if now.duration_since(since) < PAUSE_SHOWN {
                return self.last.clone();
            }
        }
        self.since = None;
        self.last = None;
        hold
    }

    /// A pause seen while it cannot be shown (a demo trial's record is
    /// awaited): shown for [`PAUSE_SHOWN`] from when it can be.
    fn note(&mut self, hold: Hold) {
        self.last = Some(hold);
        self.since = None;
    }
}

struct Current {
    id: u64,
    started: Instant,
    stopped: bool,
}

async fn run(state: Arc<AppState>, opts: DemoOptions, mut counts: Counts) {
    let interval = Duration::from_secs_f64(opts.interval_s);
    let operator_timeout = Duration::from_secs_f64(opts.operator_timeout_s.max(0.05));
    let mut next_at = Instant::now();
    let mut current: Option<Current> = None;
    let mut beats = state
        .lab
        .as_ref()
        .map_or(0, |l| l.bridge_counters().heartbeats);
    let mut last_beat: Option<Instant> = None;
    let mut pause = PauseShown::default();
    let mut ticker = tokio::time::interval(TICK);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        ticker.tick().await;
        if let Some(lab) = state.lab.as_ref() {
            let n = lab.bridge_counters().heartbeats;
            if n != beats {
                beats = n;
                last_beat = Some(Instant::now());
            }
        }
        let operator_present = last_beat.is_some_and(|t| t.elapsed() <= operator_timeout);
        if let Some(cur) = current.as_mut() {
            // A calibration step can start between the trial's end and its
            // record's (the step takes ~2 s): the pause is noted now, so it
            // is shown once the record is in.
            let lab_hold = hold(
                crate::not_ready(&state).as_ref(),
                opts.operator_required,
                operator_present,
            );
            if let Some(h) = lab_hold.filter(|h| h.reason.as_deref() == Some("calibrating")) {
                pause.note(h);
            }
            // A demo trial runs: the operator's hold, then its record.
            if opts.operator_required && !operator_present && !cur.stopped {
                cur.stopped = true;
                if let Some(lab) = state.lab.as_ref() {
                    lab.stop().await;
                }
                tracing::warn!(
                    trial = cur.id,
                    "demo: the operator's hold lapsed, the arm was stopped"
                );
                state.demo.set(|s| {
                    s.message =
                        "stopped: the operator's hold lapsed, so the arm was stopped".into();
                });
            }
            let record = match state.records.clone() {
                Some(r) => {
                    let id = cur.id;
                    tokio::task::spawn_blocking(move || r.get(id))
                        .await
                        .ok()
                        .and_then(Result::ok)
                        .flatten()
                }
                None => None,
            };
            let finished = record.as_ref().is_none_or(|r| r.status != "running");
            let timed_out = cur.started.elapsed() > Duration::from_secs_f64(TRIAL_TIMEOUT_S);
            if timed_out && !finished {
                tracing::warn!(trial = cur.id, "demo: the trial did not finish; stopping");
                if let Some(lab) = state.lab.as_ref() {
                    lab.stop().await;
                }
            }
            if finished || timed_out {
                if let Some(r) = record.filter(|r| r.status != "running") {
                    counts.trials += 1;
                    if r.status == "aborted" {
                        counts.aborted += 1;
                    } else if let Some(ok) = r.success {
                        counts.judged += 1;
                        counts.successes += u32::from(ok);
                    }
                }
                save(opts.state_file.as_ref(), &counts);
                state.demo.set(|s| apply(s, &counts));
                current = None;
            }
            continue;
        }
        let not_ready = crate::not_ready(&state);
        let (d, t) = plan(counts.started);
        // A lab that cannot move its pendulum: every trial where it hangs,
        // the movement times in turn.
        let d = state
            .lab
            .as_ref()
            .and_then(|lab| lab.options().fixed_distance_m)
            .unwrap_or(d);
        let lab_hold = hold(not_ready.as_ref(), opts.operator_required, operator_present);
        if let Some(h) = pause.shown(lab_hold, Instant::now()) {
            state.demo.set(|s| {
                s.state = h.state;
                s.reason = h.reason;
                s.message = h.message;
                s.detail = h.detail;
                s.next_in_s = None;
                s.next_distance_m = Some(d);
                s.next_movement_time_s = Some(t);
            });
            continue;
        }
        let now = Instant::now();
        if now < next_at {
            let left = (next_at - now).as_secs_f64();
            state.demo.set(|s| {
                s.state = "waiting";
                s.reason = None;
                s.detail = None;
                s.message = format!("next trial in {left:.0} s: {d:.2} m in {t:.1} s");
                s.next_in_s = Some(left);
                s.next_distance_m = Some(d);
                s.next_movement_time_s = Some(t);
            });
            continue;
        }
        let req = crate::api::TrialRequest {
            distance_m: Some(d),
            movement_time_s: Some(t),
            ..crate::api::TrialRequest::default()
        };
        let setup = match state.lab.as_ref() {
            Some(lab) => {
                crate::api::trial_setup(&req, &lab.params(), lab.options().fixed_distance_m)
            }
            None => continue,
        };
        let setup = match setup {
            Ok(s) => s,
            Err(e) => {
                // Not feasible with the parameters in force: the next one
                // (said, in case the parameters make every one infeasible).
                tracing::debug!(distance_m = d, movement_time_s = t, error = %e, "demo: skipping an infeasible trial");
                state.demo.set(|s| {
                    s.state = "paused";
                    s.reason = Some("infeasible".into());
                    s.message = "paused: the parameters in force do not let the arm make \
                                 the demo's motions"
                        .into();
                    s.detail = Some(e.to_string());
                });
                counts.started += 1;
                continue;
            }
        };
        // Strike mode (issue #38): the visitors' page says the stroke.
        let stroke = state
            .lab
            .as_ref()
            .map(|lab| lab.params().task)
            .filter(|k| k.mode == rt_core::params::TaskMode::Strike)
            .map(|k| format!(", striking at {:.2} m/s", k.strike_speed_mps))
            .unwrap_or_default();
        match crate::api::start_one(&state, setup).await {
            // Answered late: it runs as any other, or its record goes (then
            // the demo goes on to the next).
            Ok(id) | Err(AppError::Unanswered { trial: Some(id) }) => {
                counts.started += 1;
                save(opts.state_file.as_ref(), &counts);
                next_at = Instant::now() + interval;
                current = Some(Current {
                    id,
                    started: Instant::now(),
                    stopped: false,
                });
                state.demo.set(|s| {
                    s.state = "running";
                    s.reason = None;
                    s.detail = None;
                    s.message = format!("trial {id}: {d:.2} m in {t:.1} s{stroke}");
                    s.trial_id = Some(id);
                    s.next_in_s = None;
                });
            }
            // Taken in between, or refused for a reason the readiness shows
            // next tick: try again then.
            Err(AppError::Conflict { .. } | AppError::Unavailable(_)) => {}
            Err(e) => {
                tracing::warn!(error = %e, "demo: a trial was refused");
                counts.started += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::NotReady;

    #[test]
    fn the_plan_varies_distance_and_movement_time_and_covers_every_pair() {
        let pairs: std::collections::BTreeSet<(u64, u64)> = (0..14)
            .map(plan)
            .map(|(d, t)| ((d * 100.0).round() as u64, (t * 10.0).round() as u64))
            .collect();
        assert_eq!(pairs.len(), DISTANCES_M.len() * MOVEMENT_TIMES_S.len());
        assert_ne!(plan(0).0, plan(1).0);
        assert_ne!(plan(0).1, plan(1).1);
    }

    #[test]
    fn the_demo_holds_for_the_lab_and_for_the_operator() {
        let nr = |reason| NotReady {
            reason,
            message: "why".into(),
        };
        assert!(hold(None, false, false).is_none());
        assert!(hold(None, true, true).is_none());
        let h = hold(None, true, false).unwrap();
        assert_eq!(
            (h.state, h.reason.as_deref()),
            ("operator_needed", Some("operator"))
        );
        assert!(h.message.contains("operator"), "{h:?}");
        for reason in ["uncalibrated", "robot_not_commanding", "device_unavailable"] {
            let h = hold(Some(&nr(reason)), false, true).unwrap();
            assert_eq!((h.state, h.reason.as_deref()), ("paused", Some(reason)));
            assert!(h.message.starts_with("paused: "), "{h:?}");
            assert_eq!(h.detail.as_deref(), Some("why"));
        }
        // The lab's refusal comes first, even with an operator holding it.
        assert_eq!(
            hold(Some(&nr("calibrating")), true, true).unwrap().state,
            "paused"
        );
        assert_eq!(
            hold(Some(&nr("busy")), false, true).unwrap().state,
            "waiting"
        );
    }

    #[test]
    fn a_pause_is_shown_for_at_least_its_minimum_then_the_demo_goes_on() {
        let paused = hold(
            Some(&NotReady {
                reason: "calibrating",
                message: "why".into(),
            }),
            false,
            true,
        );
        assert_eq!(PAUSE_SHOWN, Duration::from_secs(5));
        let mut p = PauseShown::default();
        let t0 = Instant::now();
        assert!(p.shown(None, t0).is_none(), "nothing to hold");
        assert_eq!(p.shown(paused.clone(), t0), paused);
        // The lab is ready again after 1 s: still shown paused until 5 s.
        let kept = p.shown(None, t0 + Duration::from_secs(1));
        assert_eq!(kept.as_ref().map(|h| h.state), Some("paused"));
        assert_eq!(kept.and_then(|h| h.reason).as_deref(), Some("calibrating"));
        assert!(p.shown(None, t0 + Duration::from_millis(4999)).is_some());
        assert!(
            p.shown(None, t0 + PAUSE_SHOWN).is_none(),
            "resumes by itself"
        );
        // A pause noted while a trial's record was awaited (the step may be
        // over by then) is shown for the whole minimum from when it can be.
        let mut q = PauseShown::default();
        q.note(paused.clone().unwrap());
        q.note(paused.clone().unwrap());
        let later = t0 + Duration::from_secs(20);
        assert_eq!(q.shown(None, later), paused);
        assert_eq!(q.shown(None, later + Duration::from_millis(4999)), paused);
        assert!(q.shown(None, later + PAUSE_SHOWN).is_none());
        // A wait for another trial is not a pause and ends the one shown.
        let busy = hold(
            Some(&NotReady {
                reason: "busy",
                message: "why".into(),
            }),
            false,
            true,
        );
        assert_eq!(p.shown(paused.clone(), t0), paused);
        assert_eq!(p.shown(busy.clone(), t0 + Duration::from_secs(1)), busy);
        assert!(p.shown(None, t0 + Duration::from_secs(2)).is_none());
    }

    #[test]
    fn the_interval_is_checked() {
        let o = |interval_s| DemoOptions {
            interval_s,
            operator_required: false,
            operator_timeout_s: 1.0,
            state_file: None,
        };
        assert!(o(10.0).check().is_ok());
        for bad in [0.0, -1.0, f64::NAN, 1e9] {
            let e = o(bad).check().unwrap_err().to_string();
            assert!(e.contains("--demo-interval-s"), "{e}");
        }
    }
}
