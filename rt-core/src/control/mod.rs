#![doc = include_str!("README.md")]

pub mod beliefs;
pub mod cost;
pub mod judge;
pub mod latency;
pub mod measured;
pub mod rebound;
pub mod report;
pub mod state;
pub mod stats;
pub mod step;
pub mod success;

pub use beliefs::Beliefs;
pub use cost::{Lateness, StepClock, StepCost, StepRecord, StepTimings};
pub use judge::{
    JudgeScratch, Judgement, PlannedMotion, TrialTrace, judge, judge_into, judge_strike_crossing,
};
pub use latency::{LatencyEstimator, LatencyReport};
pub use rebound::PredictedRebound;
pub use report::{Summary, TrialRecord};
pub use state::{AbortReason, TrialMachine, TrialState};
pub use step::{
    ArmPlan, Commit, ControlCounters, ControlError, ControlParams, Controller, Excitation,
    KNOCK_LIMIT_SHARE, KNOCK_MIN_S, MOVE_TO_LIMIT_SHARE, MOVE_TO_MARGIN_RAD, Sighting, StepInput,
    StepOutput, StrikeArm,
};
pub use success::SuccessParams;
