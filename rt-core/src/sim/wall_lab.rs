//! The simulated lab on the wall clock: the links [`crate::lab::LabRuntime`]
//! plugs in (`isochron serve` without a configuration, `isochron bench`'s
//! `loop`, the runtime tests). The runtime imports nothing from `sim`; it
//! calls these factories once it knows what a link needs:
//!
//! - robot: [`SimServer`], the simulated KUKA controller over loopback UDP
//!   ([`super::robot_params`]: the scenario's latency, jitter and servo lag),
//!   sending to the FRI client's address;
//! - camera: [`SimCameraSource`], frames rendered from the ground truth the
//!   trial driver hands over ([`SimTruth`], a truthful world: in real time
//!   the reality lab, `[world]`, is served behind a real lab's interfaces
//!   instead, `world/README.md`) on the lab's clock;
//! - magnet: the fake board ([`FakeDevice`]) behind a pty in a private
//!   directory, removed with the lab.

use std::any::Any;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use super::camera::{SimCamera, SimCameraParams, SimCameraSource};
use super::kuka::{SimRunOptions, SimServer};
use super::magnet::FakeDevice;
use super::truth::{SimTruth, TruthUpdate, TruthView};
use crate::fri::SessionState;
use crate::fri::stats::LatencyHistogram;
use crate::lab::runtime::{
    CameraLink, CameraSetup, FriLink, LabRuntime, LabSetup, LoopReport, MagnetLink,
    RobotLoopCounts, RuntimeError, SimulatedCamera, SimulatedRobot,
};
use crate::lab::step::{CameraModel, Truth};
use crate::magnet::MagnetParams;
use crate::params::Scenario;
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};
use crate::vision::SwingPlaneCalibration;

/// The simulated lab for `scenario` (seeded with `seed`): the simulated
/// KUKA controller, camera and magnet board behind the runtime's links.
pub fn simulated(scenario: Scenario, seed: u64) -> LabSetup {
    LabSetup::new(
        scenario,
        seed,
        FriLink::Simulated(Box::new(start_robot)),
        CameraLink::Simulated(Box::new(start_camera)),
        MagnetLink::Simulated(Box::new(start_magnet)),
    )
}

impl SimulatedRobot for SimServer {
    fn state(&self) -> SessionState {
        self.stats().state()
    }

    fn request_commanding(&self) {
        SimServer::request_commanding(self);
    }

    fn loop_counts(&self) -> RobotLoopCounts {
        use std::sync::atomic::Ordering::Relaxed;
        let s = self.stats();
        RobotLoopCounts {
            messages_sent: s.messages_sent.load(Relaxed),
            late_replies: s.late_replies.load(Relaxed),
            missing_replies: s.missing_replies.load(Relaxed),
        }
    }

    fn rtt(&self) -> &LatencyHistogram {
        &self.stats().rtt
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// The simulated KUKA controller (`isochron-fri-sim`) sending to `client`.
fn start_robot(
    scenario: &Scenario,
    seed: u64,
    client: SocketAddr,
) -> Result<Arc<dyn SimulatedRobot>, RuntimeError> {
    let server = SimServer::spawn(
        super::robot_params(scenario, seed),
        SocketAddr::from(([127, 0, 0, 1], 0)),
        client,
        SimRunOptions {
            auto_command: true,
            duration: None,
            normal_priority: false,
            keep_commanding: false,
        },
    )
    .map_err(|e| RuntimeError::Sim(Box::new(e)))?;
    Ok(Arc::new(server))
}

/// The simulated camera rendering the ground truth, and the truth.
fn start_camera(c: &CameraSetup<'_>) -> Result<SimulatedCamera, RuntimeError> {
    let scenario = c.scenario;
    let cam = SimCamera::new(
        &scenario.camera,
        &SimCameraParams::default(),
        scenario.pendulum.ball_radius_m,
        c.seed,
    )?;
    // The detector's calibration uses the believed intrinsics (the
    // renderer draws through the nominal pinhole).
    let model = CameraModel {
        intrinsics: scenario.camera.believed_intrinsics(cam.params().hfov_deg),
        pose: cam.params().pose,
        ball_radius_m: scenario.pendulum.ball_radius_m,
    };
    // Until the first trial: the ball hangs at rest mid-range.
    let d = c
        .fixed_distance_m
        .unwrap_or(scenario.task.distance_m.lerp(0.5));
    let rest = nalgebra::Vector3::new(d, 0.0, scenario.task.intercept_height_m);
    let calibration =
        SwingPlaneCalibration::from_pose(model.intrinsics, &model.pose, &rest, model.ball_radius_m);
    let (mut truth_tx, truth_rx) = rtrb::RingBuffer::<TruthUpdate>::new(16);
    let (cal_tx, cal_rx) = rtrb::RingBuffer::<SwingPlaneCalibration>::new(16);
    let pm = PendulumModel::from_params(&scenario.pendulum)?;
    let geo = PendulumGeometry::new(
        scenario.pendulum.length_m,
        d,
        scenario.task.intercept_height_m,
    )?;
    if let Ok(b) = PendulumSim::held_at(pm, geo, 0.0, 0.0) {
        let _ = truth_tx.push(TruthUpdate::Ball(b));
    }
    let mut view = TruthView::new(truth_rx);
    let source = SimCameraSource::new(cam, move |t| view.at(t), c.clock);
    // In real time the simulated lab is a truthful world (the reality lab,
    // `[world]`, runs on the virtual clock or behind a real lab's interfaces).
    Ok(SimulatedCamera {
        source: Box::new(source),
        calibration,
        calibrations: cal_rx,
        truth: Truth {
            observer: Box::new(SimTruth::new(truth_tx, false, None, None, c.period_s)),
            calibrations: cal_tx,
            camera: model,
        },
    })
}

/// The fake magnet board behind a pty and the private directory of its
/// link (dropped in this order: the board stops, then the link goes).
struct FakeBoard {
    device: FakeDevice,
    _dir: tempfile::TempDir,
}

/// The fake magnet board, and the driver's parameters for its port.
fn start_magnet() -> Result<(MagnetParams, Box<dyn Any + Send>), RuntimeError> {
    let dir = tempfile::Builder::new()
        .prefix("isochron-magnet-")
        .tempdir()?;
    let device = FakeDevice::start(dir.path().join("tty"))?;
    // The fake board is a thread of this process: on a loaded machine it
    // answers late, which is not a lost board (a real Uno's 300 ms would
    // abort trials as magnet faults beside `stress-ng`).
    let params = MagnetParams {
        command_timeout_ms: 2000.0,
        ..MagnetParams::for_port(device.path().display().to_string())
    };
    Ok((params, Box::new(FakeBoard { device, _dir: dir })))
}

/// The fake magnet board of a lab built by [`simulated`] (tests).
pub fn fake_magnet(lab: &LabRuntime) -> Option<&FakeDevice> {
    lab.simulated_magnet()?
        .downcast_ref::<FakeBoard>()
        .map(|b| &b.device)
}

/// The simulated controller of a lab built by [`simulated`].
pub fn sim_server(lab: &LabRuntime) -> Option<&SimServer> {
    lab.simulated_robot()?.as_any().downcast_ref::<SimServer>()
}

/// Runs the simulated lab at the scenario's FRI period and measures the loop
/// for `duration` once the session commands (no server attached: the bridge's
/// server end is dropped, so every hand-off is counted, never waited on).
///
/// # Errors
///
/// The [`RuntimeError`] of [`LabRuntime::start`], [`LabRuntime::wait_commanding`]
/// (not commanding within 5 s) or [`LabRuntime::stop`].
pub fn run_loop(scenario: &Scenario, duration: Duration) -> Result<LoopReport, RuntimeError> {
    let (control, _server) = crate::bridge::bridge(crate::bridge::BridgeCapacity::default());
    let lab = LabRuntime::start(simulated(scenario.clone(), 1), control, None)?;
    lab.wait_commanding(Duration::from_secs(5))?;
    let mut report = lab.measure(duration);
    let step = lab.stop()?;
    report.deadline_misses = step.deadline_misses();
    Ok(report)
}

#[cfg(test)]
mod tests;
