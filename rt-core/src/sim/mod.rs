#![doc = include_str!("README.md")]

pub mod camera;
pub mod fri_step;
pub mod lab;
pub mod magnet;
pub mod realtime;
pub mod world;

pub use fri_step::FriLoopStep;
pub use lab::{LabError, LoopStep, TrialDraw, VirtualLab, draw_trial};
