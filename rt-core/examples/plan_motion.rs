//! Plan a timed motion: the paper's interception motion (home to the
//! intercept point, Hopf speed profile) planned on the KUKA LBR iiwa 7 R800 at
//! several distances (posture, peak joint speeds against the limits, the
//! binding joint), then each motion run through the Hopf dynamics at the
//! control period to show isochrony: every distance arrives at the same time.
//!
//! Run: `cargo run -p rt-core --example plan_motion`. It exits non-zero when a
//! motion is refused, misses its target by more than 1 mm or arrives more than
//! 1 ms from the planned moment (the arrival as CONTRACT.md defines it: the
//! end of the best-fitting ideal profile).

use nalgebra::{UnitQuaternion, Vector3};
use rt_core::timing::{MotionPhase, MotionSample, TimedMotion, TimingParams, fit_arrival};
use rt_core::trajectory::profile::ProfileKind;
use rt_core::trajectory::{MotionRequest, TaskParams, TrajectoryParams, plan};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let task = TaskParams::default();
    let period_s = 0.005;
    println!(
        "movement time {:.2} s, control period {:.0} ms",
        task.movement_time_s,
        period_s * 1e3
    );
    for distance_m in [0.35, 0.55, 0.70, 0.80] {
        // The joint-space plan: posture, feasibility, the binding limit.
        let request = MotionRequest::interception(&task, distance_m);
        let planned = plan(&request, &TrajectoryParams::default())?;
        let summary = planned.summary();
        if !planned.feasible {
            return Err(format!("{distance_m} m refused: {:?}", planned.reason).into());
        }
        let peak = planned.speed_ratio.iter().copied().fold(0.0, f64::max);

        // The Cartesian motion through the Hopf dynamics.
        let mut motion = TimedMotion::new(TimingParams::default())?;
        let start = request.start_m;
        let target: Vector3<f64> = request.end_m;
        let orientation = UnitQuaternion::from_rotation_matrix(&planned.tool_rotation);
        motion.begin(&start, &target, &orientation, request.movement_time_s)?;
        let mut sample = MotionSample::default();
        let mut peak_speed: f64 = 0.0;
        let (mut times, mut progress) = (Vec::new(), Vec::new());
        while sample.phase != MotionPhase::Arrived && sample.t_s < 2.0 * request.movement_time_s {
            motion.step(period_s, None, &mut sample)?;
            peak_speed = peak_speed.max(sample.path_speed_mps);
            times.push(sample.t_s);
            progress.push((sample.position_m - start).norm());
        }
        let miss_mm = (sample.position_m - target).norm() * 1e3;
        // The arrival as CONTRACT.md defines it: the end of the ideal profile
        // that best fits the progress (least squares over the whole motion).
        let fit = fit_arrival(
            ProfileKind::Hopf,
            request.length_m(),
            request.movement_time_s,
            &times,
            &progress,
        )?;
        let late_ms = (fit.arrival_s - request.movement_time_s) * 1e3;
        println!(
            "{distance_m:.2} m: path {:.3} m, tilt {:+.1} deg, peak joint speed {:.0}% (binding {} {}), \
             peak path speed {peak_speed:.2} m/s, arrival {:.4} s ({late_ms:+.2} ms), {miss_mm:.2} mm from the target",
            request.length_m(),
            summary.tilt_deg.unwrap_or(f64::NAN),
            peak * 100.0,
            summary.binding_joint.unwrap_or("-"),
            summary.binding_limit.unwrap_or("-"),
            fit.arrival_s,
        );
        if miss_mm > 1.0 || late_ms.abs() > 1.0 {
            return Err(format!("{distance_m} m: {miss_mm:.2} mm off, {late_ms:+.1} ms").into());
        }
    }
    Ok(())
}
