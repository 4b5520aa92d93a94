//! The lab's lifecycle fuzzed on the virtual clock: random sequences of the
//! operator's commands (trial, trial posted the moment the last one shows
//! `done`, stop, arm, disarm, magnet on/off, new parameters, heartbeat) at
//! random delays, against [`VirtualLab`] (the one trial driver, the
//! simulated controller over the real FRI codec and client), with the
//! server's bookkeeping of trial records modelled as `isochron serve` does
//! it (a record is created before the trial command is sent, removed when
//! the control loop refuses it, finished by the trial's end event).
//!
//! After each sequence (a final stop, then the lab left to settle) the
//! invariants are checked: the lab is idle and every command answered; no
//! record is left running; every accepted trial has exactly one end event
//! (`trial_finished` or `aborted`), a refused one none, and no event names
//! an unknown trial; no command left for the robot outside the joint limits;
//! the snapshot agrees with the events (no trial shown, as many trials
//! counted as ended); and the lab still takes a trial, which finishes.
//! Deterministic for a seed. `make test` runs a short run; `make fuzz` runs
//! thousands of sequences (`ISOCHRON_LIFECYCLE_SEQUENCES`).

use std::collections::{BTreeMap, HashMap};
use std::fmt;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::VirtualLab;
use crate::bridge::{Command, Event, TrialState};
use crate::params::Scenario;

/// What one fuzzing run did, and what it checked.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LifecycleReport {
    /// Sequences run.
    pub sequences: u64,
    /// Operator commands sent (stops and heartbeats included).
    pub commands: u64,
    /// Invariant checks made.
    pub checks: u64,
    /// Trials the control loop accepted.
    pub trials_accepted: u64,
    /// Trials it refused (their records removed).
    pub trials_refused: u64,
    /// Trials posted the moment the last one showed `done`.
    pub posted_on_done: u64,
    /// Accepted trials that ended `done`.
    pub done: u64,
    /// Accepted trials that ended aborted.
    pub aborted: u64,
}

impl fmt::Display for LifecycleReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} sequences, {} commands, {} invariant checks; trials: {} accepted \
             ({} posted on `done`; {} done, {} aborted), {} refused",
            self.sequences,
            self.commands,
            self.checks,
            self.trials_accepted,
            self.posted_on_done,
            self.done,
            self.aborted,
            self.trials_refused
        )
    }
}

/// An invariant that did not hold, with the sequence that broke it.
#[derive(Debug, Clone, PartialEq)]
pub struct LifecycleViolation {
    /// The sequence's seed (rerun it alone with [`run_sequence`]).
    pub seed: u64,
    /// What did not hold.
    pub what: String,
    /// The operator's actions, in order, with their virtual times.
    pub actions: Vec<String>,
}

impl fmt::Display for LifecycleViolation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "seed {}: {}\n  actions: {}",
            self.seed,
            self.what,
            self.actions.join("; ")
        )
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Status {
    Running,
    Done,
    Aborted,
}

#[derive(Debug)]
struct Record {
    status: Status,
    ends: u32,
}

#[derive(Debug, Clone, Copy)]
enum Action {
    Trial,
    TrialOnDone,
    Stop,
    Arm,
    Disarm,
    Magnet(bool),
    Params,
    Heartbeat,
}

/// The server's side of one sequence: the records and the unanswered commands.
struct Operator {
    records: BTreeMap<u64, Record>,
    /// Ack id -> the trial record it would start (0: not a trial).
    waiting: HashMap<u64, u64>,
    next_record: u64,
    /// End events seen (any trial id, 0 included).
    ends: u64,
    log: Vec<String>,
    problems: Vec<String>,
}

impl Operator {
    fn new() -> Self {
        Self {
            records: BTreeMap::new(),
            waiting: HashMap::new(),
            next_record: 1,
            ends: 0,
            log: Vec::new(),
            problems: Vec::new(),
        }
    }

    /// Takes the control loop's answers and events, as the bridge thread does.
    fn pump(&mut self, lab: &mut VirtualLab, report: &mut LifecycleReport) {
        while let Some(ack) = lab.server().acks.pop() {
            let Some(trial) = self.waiting.remove(&ack.id) else {
                self.problems.push(format!(
                    "an answer to a command never sent (ack {})",
                    ack.id
                ));
                continue;
            };
            if trial == 0 {
                continue;
            }
            match ack.outcome {
                Ok(()) => report.trials_accepted += 1,
                Err(r) => {
                    report.trials_refused += 1;
                    self.log
                        .push(format!("trial {trial} refused: {}", r.as_str()));
                    // The server removes the record of a refused trial.
                    if let Some(r) = self.records.remove(&trial)
                        && r.ends > 0
                    {
                        self.problems
                            .push(format!("trial {trial} was refused but had an end event"));
                    }
                }
            }
        }
        while let Some(e) = lab.server().events.pop() {
            let end = match e.event {
                Event::TrialFinished { .. } => Status::Done,
                Event::Aborted { .. } => Status::Aborted,
                Event::StateChanged { .. } => continue,
            };
            self.ends += 1;
            if e.trial_id == 0 {
                continue;
            }
            match self.records.get_mut(&e.trial_id) {
                Some(r) => {
                    r.ends += 1;
                    if r.status == Status::Running {
                        r.status = end;
                        match end {
                            Status::Done => report.done += 1,
                            _ => report.aborted += 1,
                        }
                    }
                }
                None => self.problems.push(format!(
                    "an end event for trial {} that has no record (refused or never posted)",
                    e.trial_id
                )),
            }
        }
    }

    fn send(&mut self, lab: &mut VirtualLab, command: Command, report: &mut LifecycleReport) {
        report.commands += 1;
        let trial = match command {
            Command::RunTrial { trial_id, .. } => trial_id,
            _ => 0,
        };
        match lab.server().commands.send(command) {
            Ok(ack) => {
                self.waiting.insert(ack, trial);
            }
            Err(_) => {
                // The ring was full: the server answers 503 and removes the record.
                self.records.remove(&trial);
            }
        }
    }

    fn post_trial(&mut self, lab: &mut VirtualLab, report: &mut LifecycleReport) {
        let id = self.next_record;
        self.next_record += 1;
        self.records.insert(
            id,
            Record {
                status: Status::Running,
                ends: 0,
            },
        );
        self.send(
            lab,
            Command::RunTrial {
                trial_id: id,
                setup: crate::bridge::TrialSetup::default(),
            },
            report,
        );
    }
}

fn pick(rng: &mut ChaCha8Rng) -> Action {
    match rng.random_range(0..100) {
        0..25 => Action::Trial,
        25..45 => Action::TrialOnDone,
        45..53 => Action::Stop,
        53..63 => Action::Arm,
        63..73 => Action::Disarm,
        73..77 => Action::Magnet(true),
        77..87 => Action::Magnet(false),
        87..94 => Action::Params,
        _ => Action::Heartbeat,
    }
}

/// A delay before the next action, in periods: often none or a few (inside
/// the previous command's effect), sometimes long enough for a trial to end.
fn delay_periods(rng: &mut ChaCha8Rng, period_s: f64) -> u64 {
    let s = match rng.random_range(0..10) {
        0..4 => rng.random_range(0.0..0.05),
        4..7 => rng.random_range(0.05..1.0),
        _ => rng.random_range(1.0..5.0),
    };
    (s / period_s).round() as u64
}

/// Advances until `until` holds (checked every period), at most `max_s`.
fn run_until(
    lab: &mut VirtualLab,
    op: &mut Operator,
    report: &mut LifecycleReport,
    max_s: f64,
    mut until: impl FnMut(&mut VirtualLab, &Operator) -> bool,
) -> bool {
    let periods = (max_s / lab.period_s()).ceil() as u64;
    for _ in 0..periods {
        if until(lab, op) {
            return true;
        }
        lab.advance(1);
        op.pump(lab, report);
    }
    until(lab, op)
}

/// Runs one sequence on a fresh lab of `scenario`, deterministic for `seed`.
///
/// # Errors
///
/// A [`LifecycleViolation`] (what did not hold, the seed, the actions) when the lab
/// cannot be built or an invariant of the sequence breaks.
pub fn run_sequence(
    scenario: &Scenario,
    seed: u64,
    report: &mut LifecycleReport,
) -> Result<(), LifecycleViolation> {
    let mut lab = VirtualLab::new(scenario, seed).map_err(|e| LifecycleViolation {
        seed,
        what: format!("the lab did not start: {e}"),
        actions: Vec::new(),
    })?;
    lab.keep_events = true;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x11fe_c1c1e);
    let mut op = Operator::new();
    let period_s = lab.period_s();
    let n = rng.random_range(3..=10);
    for _ in 0..n {
        let action = pick(&mut rng);
        op.log.push(format!("{:.3} s {action:?}", lab.t_s()));
        match action {
            Action::Trial => op.post_trial(&mut lab, report),
            Action::TrialOnDone => {
                // The natural script: post the next trial the moment the
                // state stream shows the last one `done`.
                let seen = run_until(&mut lab, &mut op, report, 20.0, |lab, _| {
                    lab.server().latest.read().trial_state == TrialState::Done
                });
                if seen {
                    report.posted_on_done += 1;
                    op.log.push(format!("{:.3} s (done shown)", lab.t_s()));
                }
                op.post_trial(&mut lab, report);
            }
            Action::Stop => {
                // As `POST /api/stop`: the stop flag, then the command.
                lab.server().stop.request_stop();
                op.send(&mut lab, Command::Stop, report);
            }
            Action::Arm => op.send(&mut lab, Command::Arm, report),
            Action::Disarm => op.send(&mut lab, Command::Disarm, report),
            Action::Magnet(on) => op.send(&mut lab, Command::Magnet { on }, report),
            Action::Params => {
                let mut s = scenario.clone();
                s.task.movement_time_s = rng.random_range(1.4..2.0);
                op.send(&mut lab, Command::SetParams(Box::new(s)), report);
            }
            Action::Heartbeat => {
                report.commands += 1;
                let _ = lab.server().heartbeat.beat();
            }
        }
        let wait = delay_periods(&mut rng, period_s);
        lab.advance(1);
        op.pump(&mut lab, report);
        for _ in 1..wait {
            lab.advance(1);
            op.pump(&mut lab, report);
        }
    }
    // The end of the script: a stop, then the lab settles.
    op.log.push(format!("{:.3} s final stop", lab.t_s()));
    report.commands += 1;
    lab.server().stop.request_stop();
    let settled = run_until(&mut lab, &mut op, report, 60.0, |lab, op| {
        lab.lab_step().is_idle() && op.waiting.is_empty()
    });
    let fail = |what: String, op: &Operator| LifecycleViolation {
        seed,
        what,
        actions: op.log.clone(),
    };
    if let Some(p) = op.problems.first() {
        return Err(fail(p.clone(), &op));
    }
    report.checks += 1;
    if !settled {
        return Err(fail(
            format!(
                "the lab was not idle 60 s after the final stop (state {}, {} commands unanswered)",
                lab.controller().state().name(),
                op.waiting.len()
            ),
            &op,
        ));
    }
    report.checks += 1;
    for (id, r) in &op.records {
        report.checks += 1;
        if r.status == Status::Running {
            return Err(fail(
                format!("trial {id}'s record is still running once the lab is idle"),
                &op,
            ));
        }
        report.checks += 1;
        if r.ends != 1 {
            return Err(fail(
                format!("trial {id} had {} end events (one expected)", r.ends),
                &op,
            ));
        }
    }
    report.checks += 1;
    let violations = lab.limit_violations();
    if violations > 0 {
        return Err(fail(
            format!("{violations} commands outside the limits"),
            &op,
        ));
    }
    let snap = *lab.server().latest.read();
    report.checks += 1;
    if snap.trial_id != 0 {
        return Err(fail(
            format!(
                "the idle lab's snapshot still shows trial {}",
                snap.trial_id
            ),
            &op,
        ));
    }
    report.checks += 1;
    if snap.counters.trials != op.ends {
        return Err(fail(
            format!(
                "the snapshot counts {} ended trials, the event stream {}",
                snap.counters.trials, op.ends
            ),
            &op,
        ));
    }
    // The lab still takes a trial, and it finishes.
    report.checks += 1;
    let ready = run_until(&mut lab, &mut op, report, 10.0, |lab, _| {
        lab.server().latest.read().ready.trial
    });
    if !ready {
        let r = lab.server().latest.read().ready;
        return Err(fail(
            format!(
                "the lab does not take a trial 10 s after settling: {:?} {}",
                r.reason, r.message
            ),
            &op,
        ));
    }
    op.log.push(format!("{:.3} s final trial", lab.t_s()));
    let id = op.next_record;
    op.post_trial(&mut lab, report);
    let ended = run_until(&mut lab, &mut op, report, 60.0, |lab, op| {
        lab.lab_step().is_idle()
            && op.waiting.is_empty()
            && op
                .records
                .get(&id)
                .is_none_or(|r| r.status != Status::Running)
    });
    report.checks += 1;
    match op.records.get(&id) {
        Some(r) if ended && r.ends == 1 && r.status != Status::Running => {}
        Some(r) => {
            return Err(fail(
                format!("the final trial did not finish: {r:?} (ended {ended})"),
                &op,
            ));
        }
        None => {
            return Err(fail(
                "the final trial was refused by a ready lab".to_owned(),
                &op,
            ));
        }
    }
    if let Some(p) = op.problems.first() {
        return Err(fail(p.clone(), &op));
    }
    report.sequences += 1;
    Ok(())
}

/// Runs `sequences` sequences, seeds `seed`, `seed + 1`, ...; stops at the
/// first violation.
///
/// # Errors
///
/// The first sequence's [`LifecycleViolation`], with the report of the sequences
/// run until then.
pub fn run(
    scenario: &Scenario,
    seed: u64,
    sequences: u64,
) -> Result<LifecycleReport, (LifecycleReport, LifecycleViolation)> {
    let mut report = LifecycleReport::default();
    for i in 0..sequences {
        if let Err(v) = run_sequence(scenario, seed.wrapping_add(i), &mut report) {
            return Err((report, v));
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::VisionMode;

    fn lab() -> Scenario {
        let mut s = Scenario::default();
        s.camera.vision = VisionMode::Model;
        s
    }

    /// The natural script (post the next trial the moment the state shows the
    /// last one `done`): every trial's record finishes, each with one end.
    /// Before the fix the earlier trial was replaced unconcluded.
    #[test]
    fn trials_posted_on_done_each_finish() {
        let s = lab();
        let mut lab = VirtualLab::new(&s, 5).unwrap();
        lab.keep_events = true;
        let mut op = Operator::new();
        let mut report = LifecycleReport::default();
        for _ in 0..5 {
            let done = run_until(&mut lab, &mut op, &mut report, 20.0, |lab, _| {
                lab.server().latest.read().trial_state == TrialState::Done
            });
            assert!(done || op.records.is_empty(), "{:?}", op.records);
            // Inside the after-done window: the answer (as `POST /api/trials`
            // waits for it) comes once the last trial is concluded.
            op.post_trial(&mut lab, &mut report);
            assert!(run_until(&mut lab, &mut op, &mut report, 5.0, |_, op| op
                .waiting
                .is_empty()));
        }
        assert!(run_until(
            &mut lab,
            &mut op,
            &mut report,
            30.0,
            |lab, op| {
                lab.lab_step().is_idle()
                    && op.waiting.is_empty()
                    && op.records.values().all(|r| r.status != Status::Running)
            }
        ));
        assert!(op.problems.is_empty(), "{:?}", op.problems);
        assert_eq!(report.trials_accepted, 5, "{report:?} {:?}", op.log);
        assert_eq!(op.records.len(), 5);
        for (id, r) in &op.records {
            assert_eq!((r.status, r.ends), (Status::Done, 1), "trial {id}");
        }
    }

    /// Disarming an armed trial ends its record (aborted, `disarmed`).
    #[test]
    fn a_disarmed_trial_is_recorded_as_aborted() {
        let s = lab();
        let mut lab = VirtualLab::new(&s, 6).unwrap();
        lab.keep_events = true;
        let mut op = Operator::new();
        let mut report = LifecycleReport::default();
        op.post_trial(&mut lab, &mut report);
        assert!(run_until(&mut lab, &mut op, &mut report, 10.0, |lab, _| {
            lab.server().latest.read().trial_state == TrialState::Armed
        }));
        op.send(&mut lab, Command::Disarm, &mut report);
        let mut aborted = None;
        for _ in 0..20 {
            lab.advance(1);
            while let Some(e) = lab.server().events.pop() {
                if let Event::Aborted { reason, .. } = e.event {
                    aborted = Some((e.trial_id, reason));
                }
            }
        }
        assert_eq!(
            aborted,
            Some((1, crate::bridge::AbortKind::Disarmed)),
            "the disarmed trial's end"
        );
        assert!(lab.lab_step().is_idle());
    }

    /// A short run of the fuzzer (`make fuzz` runs thousands:
    /// `ISOCHRON_LIFECYCLE_SEQUENCES`, `ISOCHRON_LIFECYCLE_SEED`).
    #[test]
    fn no_command_sequence_loses_a_trial_record() {
        let n = std::env::var("ISOCHRON_LIFECYCLE_SEQUENCES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(40);
        let seed = std::env::var("ISOCHRON_LIFECYCLE_SEED")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(1);
        match run(&lab(), seed, n) {
            Ok(r) => {
                eprintln!("lifecycle fuzz: {r}");
                assert_eq!(r.sequences, n);
                assert!(r.trials_accepted > 0 && r.posted_on_done > 0, "{r}");
            }
            Err((r, v)) => panic!("lifecycle fuzz after {r}:\n{v}"),
        }
    }
}
