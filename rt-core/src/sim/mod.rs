#![doc = include_str!("README.md")]

pub mod camera;
pub mod kuka;
pub mod magnet;
pub mod truth;
pub mod world;
