#![doc = include_str!("README.md")]

pub mod camera;
pub mod kuka;
pub mod lab;
pub mod magnet;
pub mod rig;
pub mod world;

pub use lab::{LabError, VirtualLab};
