//! The controller cannot read the world: a run's exchanges with the control
//! side, and their replay.
//!
//! A recorded virtual lab (`VirtualLab::recorded`, tests) logs, in its
//! driver and never in the control step, every [`Exchange`] of the control
//! side (the FRI client, the trial driver and the controller) from the lab's
//! start, in order and with their times: the inputs the driver hands it and
//! the outputs it gives back. The replay (tests) builds a fresh control side
//! from the same beliefs (the scenario without `[world]`, the same seed) with
//! no world, no ground truth and no robot simulator, feeds it the logged
//! inputs at their logged times and logs its own outputs at the same places:
//! the two logs must be identical, entry by entry (their `Debug` text, so
//! every float bit for bit). A difference means the control side read
//! something that is not in its inputs (the world leaked), or the log misses
//! a channel.

use super::step::{IoReply, IoRequest, MagnetNote, TrialOutcome};
use super::trial::TrialDraw;
use crate::bridge::{Command, Event, EventRecord};
use crate::control::measured::MeasuredJudgement;
use crate::control::{AbortReason, Commit, TrialState};
use crate::fri::client::FriClient;
use crate::vision::Measurement;

/// One exchange of the control side with the rest of the lab (see the
/// module documentation).
#[expect(
    dead_code,
    reason = "the fields are read through the `Debug` text (the replay's comparison)"
)]
#[derive(Debug, Clone)]
pub(crate) enum Exchange {
    // What the driver hands the control side.
    /// The index (draw) of the next trial (`LabStep::set_next_trial`).
    NextTrial(usize),
    /// The operator's command, through the bridge's command ring.
    Command(Command),
    /// A camera measurement, into the measurement ring.
    Measurement(Measurement),
    /// A magnet switch report, into the magnet ring. It carries what the
    /// magnet driver reports: the coil's new state and the time its pin
    /// switched (the command's write time plus the line's wire time, as the
    /// real driver computes it; the world's residual magnetism after it is
    /// not in it).
    MagnetNote(MagnetNote),
    /// The FRI client's silence check at this time (ns).
    Poll(u64),
    /// A monitoring datagram handed to the FRI client
    /// (`FriClient::on_datagram`, then `ControlStep::after_reply`).
    Datagram { now_ns: u64, bytes: Vec<u8> },
    /// The driver between messages (`ControlStep::idle`) at this time (ns).
    Idle(u64),
    /// `isochron-lab-io`'s turn at this time (s): the requests of the
    /// control side are taken and answered (plans and parameters from the
    /// beliefs; magnet switches come back as notes).
    Serve(f64),
    /// The robot was rebooted (a new session): `Controller::new_session`.
    NewSession,
    /// The driver gave up on a trial at this time (s; a refusal, a magnet
    /// error, its own timeout): `Controller::abort(StopRequested)`.
    Abort(f64),
    // What the control side gives back (the replay makes its own).
    /// The command datagram answering the datagram before (`None`: no reply).
    Reply(Option<Vec<u8>>),
    /// The controller's commit, after a message that changed it (the
    /// planned pass time t*, the motion's start and duration, the latency
    /// and camera offset compensated).
    Commit(Option<Commit>),
    /// A request to `isochron-lab-io`, as it takes it.
    Request(String),
    /// `isochron-lab-io`'s answer to the request (a plan, parameters).
    Answer(String),
    /// An event to the operator (a finished trial's result without the
    /// judges' truth: [`describe_event`]).
    Event(String),
    /// The answer to an operator's command, as the driver reads it.
    Ack(String),
    /// A trial's outcome as the driver takes it ([`Verdict`]; boxed: the
    /// largest variant by far).
    Outcome(Option<Box<Verdict>>),
    /// The replay only: an input its ring refused (full: the control side
    /// did not take what the recorded one took).
    Refused(&'static str),
}

impl Exchange {
    /// Whether the replay feeds this exchange in (else it makes its own).
    #[cfg(test)]
    pub(crate) fn is_input(&self) -> bool {
        matches!(
            self,
            Self::NextTrial(_)
                | Self::Command(_)
                | Self::Measurement(_)
                | Self::MagnetNote(_)
                | Self::Poll(_)
                | Self::Datagram { .. }
                | Self::Idle(_)
                | Self::Serve(_)
                | Self::NewSession
                | Self::Abort(_)
        )
    }
}

/// What the control side decided about a trial: its [`TrialOutcome`]
/// without the judges' truth (the ground-truth and physical verdicts, the
/// prediction's errors against the true ball) and without the step's
/// measured CPU times (deadline misses, preempted steps: this machine's,
/// not the inputs'), with the FRI client's guard interventions so far.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Verdict {
    pub id: u64,
    pub index: usize,
    pub draw: TrialDraw,
    pub planned_movement_time_s: f64,
    pub final_state: TrialState,
    pub abort_reason: Option<AbortReason>,
    /// The measured judge (the real lab's judgement).
    pub measured: Option<MeasuredJudgement>,
    pub latency_estimate_ms: f64,
    pub camera_offset_estimate_ms: Option<f64>,
    pub length_estimate_m: Option<f64>,
    pub limit_violations: u64,
    pub t_end_s: f64,
    /// The FRI client's guard: position, step and non-finite interventions.
    pub guard: [u64; 3],
}

impl Verdict {
    pub(crate) fn of(o: &TrialOutcome, client: &FriClient) -> Self {
        use std::sync::atomic::Ordering::Relaxed;
        let c = client.stats();
        Self {
            id: o.id,
            index: o.index,
            draw: o.draw,
            planned_movement_time_s: o.planned_movement_time_s,
            final_state: o.final_state,
            abort_reason: o.abort_reason,
            measured: o.measured,
            latency_estimate_ms: o.latency_estimate_ms,
            camera_offset_estimate_ms: o.camera_offset_estimate_ms,
            length_estimate_m: o.length_estimate_m,
            limit_violations: o.limit_violations,
            t_end_s: o.t_end_s,
            guard: [
                c.guard_position.load(Relaxed),
                c.guard_step.load(Relaxed),
                c.guard_non_finite.load(Relaxed),
            ],
        }
    }
}

/// A request of the control side to `isochron-lab-io`, as text.
pub(crate) fn describe_request(req: &IoRequest) -> String {
    match req {
        IoRequest::Magnet(on) => format!("Magnet({on})"),
        IoRequest::Plan {
            ack,
            trial_id,
            auto_release,
            index,
            draw,
            setup,
        } => format!(
            "Plan {{ ack: {ack}, trial_id: {trial_id}, auto_release: {auto_release}, \
             index: {index}, draw: {draw:?}, movement_time_s: {:?}, mode: {:?}, \
             strike_speed_mps: {:?}, strike_direction_deg: {:?} }}",
            setup.movement_time_s, setup.mode, setup.strike_speed_mps, setup.strike_direction_deg
        ),
        IoRequest::Params { ack, scenario } => {
            format!("Params {{ ack: {ack}, scenario: {scenario:?} }}")
        }
        IoRequest::Free(_) => "Free".to_owned(),
    }
}

/// `isochron-lab-io`'s answer, as text.
pub(crate) fn describe_reply(reply: &IoReply) -> String {
    match reply {
        IoReply::Plan {
            ack,
            trial_id,
            auto_release,
            index,
            draw,
            plan,
        } => format!(
            "Plan {{ ack: {ack}, trial_id: {trial_id}, auto_release: {auto_release}, \
             index: {index}, draw: {draw:?}, plan: {plan:?} }}"
        ),
        IoReply::Params { ack, result } => match result {
            Ok((_, s)) => format!("Params {{ ack: {ack}, accepted: {s:?} }}"),
            Err(s) => format!("Params {{ ack: {ack}, refused: {s:?} }}"),
        },
    }
}

/// An event of the control side, as text: a finished trial's result only
/// with what the control side decides (the distance, the limit violations,
/// the measured judge), not the judges' truth that decides it in a
/// simulated lab.
pub(crate) fn describe_event(e: &EventRecord) -> String {
    match &e.event {
        Event::TrialFinished { result } => format!(
            "{{ t_s: {:?}, trial_id: {}, TrialFinished {{ distance_m: {:?}, \
             limit_violations: {}, measured: {:?} }} }}",
            e.t_s, e.trial_id, result.distance_m, result.limit_violations, result.measured
        ),
        _ => format!("{e:?}"),
    }
}

#[cfg(test)]
pub(crate) use replayer::{Replay, first_difference};

#[cfg(test)]
mod replayer {
    use super::*;
    use crate::control::AbortReason;
    use crate::fri::client::ControlStep;
    use crate::lab::control_side::{ControlSide, LabError};
    use crate::params::Scenario;
    use crate::vision::SwingPlaneCalibration;

    /// A control side built from the beliefs alone, fed a recorded run's
    /// inputs (see the module documentation).
    pub(crate) struct Replay {
        side: ControlSide,
        /// The beliefs, as `isochron-lab-io` holds them (plans, parameters).
        scenario: Scenario,
        /// `isochron-lab-io`'s answer to the request taken, not yet given.
        answer: Option<IoReply>,
        /// In `isochron-lab-io`'s turn (its requests and answers follow).
        serving: bool,
        last_commit: Option<Commit>,
        out: Vec<Exchange>,
    }

    impl Replay {
        /// The control side the virtual lab (`VirtualLab::new`, `sim/virtual_lab.rs`) builds
        /// for a scenario with these beliefs (no `[world]`), `seed`, its
        /// controller's period `period_s` and the camera's `calibration`,
        /// but with no truth, world or simulated robot behind it.
        pub(crate) fn new(
            beliefs: &Scenario,
            seed: u64,
            period_s: f64,
            calibration: SwingPlaneCalibration,
        ) -> Result<Self, LabError> {
            assert!(beliefs.world.is_none(), "the replay runs on the beliefs");
            Ok(Self {
                side: ControlSide::new(beliefs, seed, period_s, calibration, None)?,
                scenario: beliefs.clone(),
                answer: None,
                serving: false,
                last_commit: None,
                out: Vec::new(),
            })
        }

        /// Feeds `log`'s inputs in order; returns the replay's log: the same
        /// inputs, and the outputs this control side gave at the same places.
        pub(crate) fn run(mut self, log: &[Exchange]) -> Vec<Exchange> {
            self.out.reserve(log.len());
            for e in log {
                self.feed(e);
            }
            self.leftovers();
            self.out
        }

        fn feed(&mut self, e: &Exchange) {
            // `isochron-lab-io`'s turn takes every request there is: when it
            // ends, this control side must have asked nothing more.
            if self.serving
                && !matches!(
                    e,
                    Exchange::Request(_) | Exchange::Answer(_) | Exchange::NewSession
                )
            {
                self.serving = false;
                self.leftovers();
            }
            if e.is_input() {
                self.out.push(e.clone());
            }
            let s = &mut self.side;
            match e {
                Exchange::NextTrial(i) => s.step.set_next_trial(*i),
                Exchange::Command(c) => {
                    if s.server.commands.send(c.clone()).is_err() {
                        self.out.push(Exchange::Refused("command"));
                    }
                }
                Exchange::Measurement(m) => {
                    if s.measurements.push(*m).is_err() {
                        self.out.push(Exchange::Refused("measurement"));
                    }
                }
                Exchange::MagnetNote(n) => {
                    if s.notes.push(*n).is_err() {
                        self.out.push(Exchange::Refused("magnet note"));
                    }
                }
                Exchange::Poll(now) => {
                    s.client.poll(*now, &mut s.step);
                }
                Exchange::Idle(now) => ControlStep::idle(&mut s.step, *now),
                Exchange::Datagram { now_ns, bytes } => {
                    let reply = s
                        .client
                        .on_datagram(bytes, *now_ns, &mut s.step)
                        .map(<[u8]>::to_vec);
                    s.step.after_reply();
                    self.out.push(Exchange::Reply(reply));
                    let commit = s.step.inner().controller().commit().copied();
                    if commit != self.last_commit {
                        self.last_commit = commit;
                        self.out.push(Exchange::Commit(commit));
                    }
                }
                Exchange::Serve(_) => {
                    self.serving = true;
                    // The server's part of the period (telemetry is not an
                    // exchange: dropped, as the lab drops it).
                    while s.server.telemetry.pop().is_some() {}
                }
                Exchange::NewSession => s.step.inner_mut().controller_mut().new_session(),
                Exchange::Abort(t) => s
                    .step
                    .inner_mut()
                    .controller_mut()
                    .abort(*t, AbortReason::StopRequested),
                Exchange::Request(_) => match s.io_requests.pop() {
                    Ok(req) => {
                        self.out.push(Exchange::Request(describe_request(&req)));
                        // Magnet switches come back as the logged notes.
                        if !matches!(req, IoRequest::Magnet(_) | IoRequest::Free(_)) {
                            self.answer =
                                super::super::step::plan_or_params(&mut self.scenario, req)
                                    .map(|(reply, _)| reply);
                        }
                    }
                    Err(_) => self.out.push(Exchange::Request("(none)".into())),
                },
                Exchange::Answer(_) => match self.answer.take() {
                    Some(reply) => {
                        self.out.push(Exchange::Answer(describe_reply(&reply)));
                        if s.io_replies.push(reply).is_err() {
                            self.out.push(Exchange::Refused("answer"));
                        }
                    }
                    None => self.out.push(Exchange::Answer("(none)".into())),
                },
                Exchange::Event(_) => {
                    let e = s.server.events.pop();
                    self.out.push(Exchange::Event(
                        e.map_or_else(|| "(none)".into(), |e| describe_event(&e)),
                    ));
                }
                Exchange::Ack(_) => {
                    let a = s.server.acks.pop();
                    self.out.push(Exchange::Ack(
                        a.map_or_else(|| "(none)".into(), |a| format!("{a:?}")),
                    ));
                }
                Exchange::Outcome(_) => {
                    let v = s
                        .step
                        .take_outcome()
                        .map(|o| Box::new(Verdict::of(&o, &s.client)));
                    self.out.push(Exchange::Outcome(v));
                }
                Exchange::Reply(_) | Exchange::Commit(_) | Exchange::Refused(_) => {}
            }
        }

        /// What this control side asked that the recorded one had not when
        /// `isochron-lab-io`'s turn ended: requests not taken, an answer not
        /// given.
        fn leftovers(&mut self) {
            let s = &mut self.side;
            while let Ok(req) = s.io_requests.pop() {
                self.out.push(Exchange::Request(format!(
                    "(extra) {}",
                    describe_request(&req)
                )));
            }
            if let Some(reply) = self.answer.take() {
                self.out.push(Exchange::Answer(format!(
                    "(held) {}",
                    describe_reply(&reply)
                )));
            }
        }
    }

    /// The first entry where two logs differ (their `Debug` text), with the
    /// entries before it; `None` when they are identical.
    pub(crate) fn first_difference(a: &[Exchange], b: &[Exchange]) -> Option<String> {
        let text =
            |e: Option<&Exchange>| e.map_or_else(|| "(end)".to_owned(), |e| format!("{e:?}"));
        let short = |s: String| {
            if s.chars().count() > 600 {
                format!("{}...", s.chars().take(600).collect::<String>())
            } else {
                s
            }
        };
        let i = (0..a.len().max(b.len())).find(|&i| text(a.get(i)) != text(b.get(i)))?;
        let before: String = a[i.saturating_sub(6)..i.min(a.len())]
            .iter()
            .map(|e| format!("\n    {}", short(format!("{e:?}"))))
            .collect();
        Some(format!(
            "entry {i} of {} / {}; before it:{before}\n  recorded: {}\n  replayed: {}",
            a.len(),
            b.len(),
            short(text(a.get(i))),
            short(text(b.get(i)))
        ))
    }
}
