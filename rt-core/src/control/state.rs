//! The trial state machine of DESIGN.md ("The trial").
//!
//! `Idle -> Arming -> Armed -> Released -> Tracking -> Intercepting -> Holding -> Done`,
//! then back to `Idle` (home). `Aborted` is reachable from every state and
//! ends in a safe stop; from `Aborted` and `Done` only `Idle` (reset) follows.
//! The reason of an abort is the controller's
//! ([`crate::control::Controller::abort_reason`]), not the state's.
//!
//! [`TrialState`] is also the API's (`bridge::TrialState`): its JSON names
//! are the snake_case variant names (`"tracking"`, `"aborted"`).

use serde::Serialize;
use ts_rs::TS;
use utoipa::ToSchema;

/// Where a trial is (DESIGN.md, "The trial").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, TS, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TrialState {
    /// Nothing running; the arm may be anywhere safe.
    #[default]
    Idle,
    /// Moving home in the coming motion's posture, checking before holding the ball.
    Arming,
    /// Robot at home in the coming motion's posture, magnet holding, checks passed.
    Armed,
    /// Magnet off: the ball swings, the filter has not initialised yet.
    Released,
    /// The filter tracks the ball; predictions are shown; waiting for the
    /// interception condition.
    Tracking,
    /// The interception condition was met: the Hopf system runs, the arm moves.
    Intercepting,
    /// At the intercept point after the motion.
    Holding,
    /// The trial is over (judged by whoever owns the truth).
    Done,
    /// The trial was aborted; the arm stopped safely (the reason is the
    /// controller's `abort_reason`).
    Aborted,
}

impl TrialState {
    /// Every state, in trial order.
    pub const ALL: [Self; 9] = [
        Self::Idle,
        Self::Arming,
        Self::Armed,
        Self::Released,
        Self::Tracking,
        Self::Intercepting,
        Self::Holding,
        Self::Done,
        Self::Aborted,
    ];

    /// The snake_case name, as in JSON (`"tracking"`, `"aborted"`).
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Idle => "idle",
            Self::Arming => "arming",
            Self::Armed => "armed",
            Self::Released => "released",
            Self::Tracking => "tracking",
            Self::Intercepting => "intercepting",
            Self::Holding => "holding",
            Self::Done => "done",
            Self::Aborted => "aborted",
        }
    }

    /// Short name in trial records and transition errors (`"tracking"`,
    /// `"abort"`): [`Self::as_str`] but for an abort, kept as the trial
    /// records have always named it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Aborted => "abort",
            s => s.as_str(),
        }
    }

    /// Whether the arm may be moving under the interception motion.
    pub const fn is_moving(self) -> bool {
        matches!(self, Self::Arming | Self::Intercepting)
    }

    /// True while the arm moves on its own (arming, intercepting): risky
    /// parameter changes are refused then.
    pub const fn arm_in_motion(self) -> bool {
        self.is_moving()
    }

    /// True from arming until the trial ends (a trial or its preparation runs).
    pub const fn busy(self) -> bool {
        !matches!(self, Self::Idle | Self::Done | Self::Aborted)
    }
}

/// Why a trial was aborted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AbortReason {
    /// The operator asked for a stop.
    StopRequested,
    /// The planned motion violates a limit (joint position, speed, acceleration,
    /// workspace) even at its shortest feasible duration.
    Infeasible,
    /// Inverse kinematics found no solution for a commanded point.
    IkFailed,
    /// The command guard refused a command (limit or step size).
    GuardTripped,
    /// No camera measurement for too long.
    CameraLost,
    /// The FRI link was lost or left commanding.
    FriLost,
    /// The filter never became confident enough to commit to a pass.
    PredictionTimeout,
    /// The committed pass cannot be met any more (too late to start).
    MissedWindow,
    /// The ball did not drop (the magnet did not release).
    MagnetFault,
    /// The filter refused its input (non-finite numbers).
    FilterFault,
    /// No operator heartbeat within the dead-man time while a trial ran.
    OperatorLost,
    /// The operator disarmed the lab before the release.
    Disarmed,
}

impl AbortReason {
    /// Short snake_case name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::StopRequested => "stop_requested",
            Self::Infeasible => "infeasible",
            Self::IkFailed => "ik_failed",
            Self::GuardTripped => "guard_tripped",
            Self::CameraLost => "camera_lost",
            Self::FriLost => "fri_lost",
            Self::PredictionTimeout => "prediction_timeout",
            Self::MissedWindow => "missed_window",
            Self::MagnetFault => "magnet_fault",
            Self::FilterFault => "filter_fault",
            Self::OperatorLost => "operator_lost",
            Self::Disarmed => "disarmed",
        }
    }
}

/// A transition that is not allowed from the current state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("cannot go from {from} to {to}")]
pub struct BadTransition {
    /// The current state's name.
    pub from: &'static str,
    /// The asked state's name.
    pub to: &'static str,
}

/// The state machine: holds the state and refuses transitions DESIGN.md does not allow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrialMachine {
    state: TrialState,
    transitions: u64,
}

impl Default for TrialMachine {
    fn default() -> Self {
        Self::new()
    }
}

impl TrialMachine {
    /// Starts in `Idle`.
    pub const fn new() -> Self {
        Self {
            state: TrialState::Idle,
            transitions: 0,
        }
    }

    /// The current state.
    pub const fn state(&self) -> TrialState {
        self.state
    }

    /// Transitions taken so far.
    pub const fn transitions(&self) -> u64 {
        self.transitions
    }

    /// Whether `from -> to` is allowed.
    pub const fn allowed(from: TrialState, to: TrialState) -> bool {
        use TrialState as S;
        match (from, to) {
            // A stop is accepted from everywhere (but not a second abort).
            (S::Aborted, S::Aborted) => false,
            (_, S::Aborted) => true,
            (S::Idle, S::Arming)
            | (S::Arming, S::Armed)
            | (S::Armed, S::Released | S::Idle)
            | (S::Released, S::Tracking)
            | (S::Tracking, S::Intercepting)
            | (S::Intercepting, S::Holding)
            | (S::Holding, S::Done)
            | (S::Done | S::Aborted, S::Idle) => true,
            _ => false,
        }
    }

    /// Goes to `to` if allowed; otherwise changes nothing.
    ///
    /// # Errors
    ///
    /// [`BadTransition`] when the state machine does not allow going from the current
    /// state to `to`.
    pub fn go(&mut self, to: TrialState) -> Result<(), BadTransition> {
        if Self::allowed(self.state, to) {
            self.state = to;
            self.transitions += 1;
            Ok(())
        } else {
            Err(BadTransition {
                from: self.state.name(),
                to: to.name(),
            })
        }
    }

    /// Aborts (a no-op when already aborted).
    pub fn abort(&mut self) {
        let _ = self.go(TrialState::Aborted);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use TrialState as S;

    #[test]
    fn the_happy_path_is_allowed_in_order_only() {
        let mut m = TrialMachine::new();
        for s in [
            S::Arming,
            S::Armed,
            S::Released,
            S::Tracking,
            S::Intercepting,
            S::Holding,
            S::Done,
            S::Idle,
        ] {
            m.go(s).unwrap();
        }
        assert_eq!(m.transitions(), 8);
        // Skipping a state is refused and changes nothing.
        let err = m.go(S::Tracking).unwrap_err();
        assert_eq!((err.from, err.to), ("idle", "tracking"));
        assert_eq!(m.state(), S::Idle);
    }

    #[test]
    fn abort_is_reachable_from_everywhere_once() {
        let all = [
            S::Idle,
            S::Arming,
            S::Armed,
            S::Released,
            S::Tracking,
            S::Intercepting,
            S::Holding,
            S::Done,
        ];
        for s in all {
            assert!(TrialMachine::allowed(s, S::Aborted));
        }
        assert!(!TrialMachine::allowed(S::Aborted, S::Aborted));
        let mut m = TrialMachine::new();
        m.abort();
        let n = m.transitions();
        m.abort();
        assert_eq!(m.state(), S::Aborted);
        assert_eq!(m.transitions(), n);
        // Only a reset leaves an abort.
        assert!(m.go(S::Armed).is_err());
        m.go(S::Idle).unwrap();
    }

    #[test]
    fn states_serialise_with_their_wire_names() {
        for s in S::ALL {
            assert_eq!(serde_json::to_value(s).unwrap(), s.as_str());
        }
        assert_eq!(serde_json::to_string(&S::Aborted).unwrap(), r#""aborted""#);
        assert_eq!(
            serde_json::to_string(&S::Tracking).unwrap(),
            r#""tracking""#
        );
        assert_eq!(S::Aborted.name(), "abort");
        assert_eq!(S::Tracking.name(), "tracking");
        assert_eq!(S::default(), S::Idle);
    }
}
