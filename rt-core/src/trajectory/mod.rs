#![doc = include_str!("README.md")]

pub mod path;
pub mod plan;
pub mod profile;
pub mod strike;
pub mod task;

#[cfg(test)]
mod tests;

pub use path::{MotionRequest, tool_rotation};
pub use plan::{
    Binding, ElbowPolicy, Infeasibility, LimitKind, MotionPlan, PlanError, PlanSummary, Posture,
    TrajectoryParams, evaluate, plan,
};
pub use task::{TaskMode, TaskParams};
