//! isochron's real-time core: one module per part of the paper.
//!
//! Every algorithm here is a step function that takes explicit timestamps and owns
//! no thread, socket or clock (DESIGN.md, principle 1). Nothing here depends on an
//! async runtime or a web framework; the `server` crate depends on this one, never
//! the reverse.
//!
//! | Module | Part of the paper |
//! |---|---|
//! | [`calibration`] | calibration fits: free swing, camera latency by LED, robot latency and servo; the calibration file |
//! | [`bridge`] | hand-offs between the control thread and the server; the shared data model |
//! | [`check`] | `ParamError` and the validation helpers (a leaf: imports nothing of the crate) |
//! | [`params`] | typed, validated parameters and scenario files |
//! | [`pendulum`] | the damped pendulum (eq. 8), its geometry, the ground-truth simulator |
//! | [`ekf`] | the extended Kalman filter (eqs. 1-16) and the predictor (pass times, motion start) |
//! | [`kinematics`] | the KUKA LBR iiwa 7 R800 model, limits, FK/Jacobian/IK |
//! | [`trajectory`] | timed Cartesian motions, profiles, feasibility |
//! | [`fri`] | KUKA FRI 1.15, the client side: wire codec, client session, guard, socket session |
//! | [`control`] | the closed loop: control step, trial states, latency estimate, judging |
//! | [`lab`] | the lab runtime and the one trial driver, on the wall clock or a virtual clock |
//! | [`sim`] | the simulated world only: simulated KUKA controller, cameras, magnet board, the reality lab's world |
//! | [`magnet`] | the electromagnet: firmware protocol, serial driver thread, fake device |
//! | [`timing`] | Hopf speed dynamics, competing neurons, timed straight-line motion (eqs. 20-21) |
//! | [`tuning`] | EKF noise estimated from recordings (maximum likelihood), the paper's Fig. 4 |
//! | [`vision`] | ball detection (OpenCV), camera sources, calibration, the vision thread |

// Outside tests the service returns errors and never panics on them: no
// `unwrap()`/`expect()` (tests may: clippy.toml's allow-*-in-tests).
#![cfg_attr(not(test), warn(clippy::unwrap_used, clippy::expect_used))]

pub mod bridge;
pub mod calibration;
pub mod check;
pub mod control;
pub mod ekf;
pub mod fri;
pub mod kinematics;
pub mod lab;
pub mod magnet;
pub mod params;
pub mod pendulum;
pub mod quantile;
pub mod sim;
pub mod timing;
pub mod trajectory;
pub mod tuning;
pub mod vision;

#[cfg(test)]
mod layering;
