#![doc = include_str!("README.md")]

pub mod camera;
pub mod kuka;
pub mod lifecycle;
pub mod magnet;
pub mod truth;
pub mod virtual_lab;
#[cfg(all(feature = "opencv", feature = "serial"))]
pub mod wall_lab;

pub use virtual_lab::{INITIAL_JOINTS_DEG, LOOPBACK_NS, VirtualLab, robot_params};
pub mod world;
