//! The lab behind `isochron serve`: the lab runtime of `rt_core`
//! ([`rt_core::lab::LabRuntime`]: the FRI client session on `isochron-fri`
//! calling the closed loop, the simulated KUKA controller on
//! `isochron-fri-sim` over loopback UDP, the camera on `isochron-vision`
//! through the OpenCV detector, the magnet driver on its fake board) joined to
//! the server by the bridge and the camera's frame channel.
//!
//! The real lab is the same runtime with real drivers ([`start_lab`] with a
//! [`LabSetup`] naming a controller address, a frame source and a serial port).

use std::sync::Arc;

pub use rt_core::lab::LabRuntime;
use rt_core::{bridge, lab::LabSetup, params::Scenario};

/// Frames buffered between the vision thread and the server (the newest wins).
const FRAME_RING: usize = 4;

/// Starts the lab of `setup` and the server side of its bridge. Keep the
/// [`LabRuntime`] alive as long as the [`crate::Lab`]; drop it after
/// [`crate::Lab::shutdown`] (dropping it stops its threads).
///
/// # Errors
///
/// When [`LabRuntime::start`] fails (any [`RuntimeError`](rt_core::lab::RuntimeError))
/// or the bridge thread cannot start.
pub fn start_lab(
    setup: LabSetup,
    records: Option<Arc<crate::Records>>,
    options: crate::LabOptions,
) -> anyhow::Result<(Arc<crate::Lab>, LabRuntime)> {
    let scenario = setup.scenario.clone();
    let (control, end) = bridge::bridge(bridge::BridgeCapacity::default());
    let (frame_tx, frame_rx) = bridge::frame_channel(FRAME_RING, Arc::clone(&end.stats));
    let runtime = LabRuntime::start(setup, control, Some(frame_tx))?;
    let lab = crate::Lab::start(end, Some(frame_rx), scenario, records, options)?;
    lab.set_devices(crate::lab::Devices {
        vision: runtime.vision_stats().cloned(),
        magnet: Some(runtime.magnet().clone()),
        led: runtime.led_feed().cloned(),
        stills: runtime.stills().cloned(),
        epoch: Some(runtime.epoch()),
    });
    Ok((lab, runtime))
}

/// Starts the simulated lab whose truth the trial driver follows
/// (`sim::wall_lab`: its recordings carry the ground truth; `isochron serve`
/// without a config serves a world behind a real lab's interfaces instead).
///
/// # Errors
///
/// As [`start_lab`].
pub fn start_simulated(
    scenario: Scenario,
    records: Option<Arc<crate::Records>>,
    options: crate::LabOptions,
    seed: u64,
) -> anyhow::Result<(Arc<crate::Lab>, LabRuntime)> {
    start_lab(
        rt_core::sim::wall_lab::simulated(scenario, seed),
        records,
        options,
    )
}
