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
//! | [`params`] | typed, validated parameters and scenario files |
//! | [`pendulum`] | the damped pendulum (eq. 8), its geometry, the ground-truth simulator |
//! | [`ekf`] | the extended Kalman filter (eqs. 1-16) and the predictor (pass times, motion start) |
//! | [`kinematics`] | the KUKA LBR iiwa 7 R800 model, limits, FK/Jacobian/IK |
//! | [`trajectory`] | timed Cartesian motions, profiles, feasibility |
//! | [`fri`] | KUKA FRI 1.15: wire codec, client session, simulated controller |
//! | [`control`] | the closed loop: control step, trial states, latency estimate, judging |
//! | [`sim`] | the simulated lab: virtual-time runtime wiring truth, camera, FRI robot and control |
//! | [`magnet`] | the electromagnet: firmware protocol, serial driver thread, fake device |
//! | [`timing`] | Hopf speed dynamics, competing neurons, timed straight-line motion (eqs. 20-21) |
//! | [`tuning`] | EKF noise estimated from recordings (maximum likelihood), the paper's Fig. 4 |
//! | [`vision`] | ball detection (OpenCV), camera sources, calibration, the vision thread |

pub mod bridge;
pub mod calibration;
pub mod control;
pub mod ekf;
pub mod fri;
pub mod kinematics;
pub mod lab;
pub mod magnet;
pub mod params;
pub mod pendulum;
pub mod sim;
pub mod timing;
pub mod trajectory;
pub mod tuning;
pub mod vision;
