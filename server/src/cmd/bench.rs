//! `isochron bench [--json]`: the hot paths and the real-time loop (CONTRACT.md).

use std::time::{Duration, Instant};

use nalgebra::UnitQuaternion;
use rt_core::control::Controller;
use rt_core::control::posture::flange_pose;
use rt_core::control::stats::quantile_sorted;
use rt_core::ekf::Ekf;
use rt_core::kinematics::analytic::ArmGeometry;
use rt_core::kinematics::{Joints, Tool};
use rt_core::params::{Scenario, VisionMode};
use rt_core::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};
use rt_core::sim::VirtualLab;
use rt_core::sim::realtime::{LoopReport, run_loop};
use rt_core::timing::{MotionSample, TimedMotion};
use serde::Serialize;

/// Arguments of `isochron bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Seconds the real-time loop runs.
    #[arg(long, default_value_t = 10.0)]
    pub loop_s: f64,
}

#[derive(Debug, Serialize)]
struct P2 {
    p50: f64,
    p99: f64,
}

#[derive(Debug, Serialize)]
struct P3 {
    p50: f64,
    p99: f64,
    max: f64,
}

#[derive(Debug, Serialize)]
struct P4 {
    p50: f64,
    p99: f64,
    p999: f64,
    max: f64,
}

#[derive(Debug, Serialize)]
struct Bench {
    ekf_step_ns: P2,
    hopf_step_ns: P2,
    ik_solve_us: P3,
    control_step_us: P4,
    /// Not measured here until the vision module is in the build.
    vision_frame_ms: Option<P2>,
    #[serde(rename = "loop")]
    loop_: LoopReport,
}

fn sorted(mut v: Vec<f64>) -> Vec<f64> {
    v.sort_by(f64::total_cmp);
    v
}

fn ns_since(t: Instant) -> f64 {
    t.elapsed().as_nanos() as f64
}

fn ekf_ns(s: &Scenario) -> anyhow::Result<Vec<f64>> {
    let model = PendulumModel::from_params(&s.pendulum)?;
    let geo = PendulumGeometry::new(s.pendulum.length_m, 0.6, s.task.intercept_height_m)?;
    let mut out = Vec::with_capacity(4000);
    for run in 0..10 {
        let mut ekf = Ekf::new(s.ekf.clone(), model, geo)?;
        let mut sim = PendulumSim::held_at(model, geo, (20.0 + f64::from(run)).to_radians(), 0.0)?;
        sim.release(0.0)?;
        for k in 1..400 {
            let t = f64::from(k) / 30.0;
            sim.advance_to(t)?;
            let z = sim.lateral_m();
            let started = Instant::now();
            let _ = ekf.measure(t, z);
            out.push(ns_since(started));
        }
    }
    Ok(sorted(out))
}

fn hopf_ns(s: &Scenario) -> anyhow::Result<Vec<f64>> {
    let mut out = Vec::with_capacity(20_000);
    let a = nalgebra::Vector3::from(s.task.home_m);
    let b = nalgebra::Vector3::new(0.7, 0.0, s.task.intercept_height_m);
    let mut sample = MotionSample::default();
    for _ in 0..10 {
        let mut m = TimedMotion::new(s.timing.clone())?;
        m.begin(&a, &b, &UnitQuaternion::identity(), s.task.movement_time_s)?;
        for _ in 0..1600 {
            let started = Instant::now();
            let _ = m.step(0.001, None, &mut sample);
            out.push(ns_since(started));
        }
    }
    Ok(sorted(out))
}

fn ik_us(s: &Scenario) -> anyhow::Result<Vec<f64>> {
    let plan = Controller::plan(s, 0.7)?;
    let tool = Tool::along_z(s.task.tool_length_m);
    let a = nalgebra::Vector3::from(s.task.home_m);
    let mut out = Vec::with_capacity(10_000);
    let mut q = Joints::zeros();
    for k in 0..10_000 {
        let u = f64::from(k % 1000) / 1000.0;
        let p = a + (plan.intercept_m - a) * u;
        let started = Instant::now();
        let pose = flange_pose(&tool, &p, &plan.posture.orientation);
        if let Ok(g) = ArmGeometry::new(&pose) {
            g.solve(plan.posture.arm_angle_rad, plan.posture.flags, &mut q);
        }
        out.push(ns_since(started) * 1e-3);
    }
    Ok(sorted(out))
}

fn control_us(s: &Scenario) -> anyhow::Result<Vec<f64>> {
    let mut s = s.clone();
    s.camera.vision = VisionMode::Model;
    s.robot.fri_period_ms = 1;
    let mut lab = VirtualLab::new(&s, 1)?;
    lab.loop_step().step_ns = Some(Vec::with_capacity(100_000));
    for i in 0..3 {
        let _ = lab.run_trial(i);
    }
    let v = lab.loop_step().step_ns.take().unwrap_or_default();
    Ok(sorted(v.into_iter().map(|ns| ns as f64 * 1e-3).collect()))
}

/// Runs the benches; returns the text for stdout.
pub fn run(args: &BenchArgs) -> anyhow::Result<String> {
    if !(args.loop_s.is_finite() && args.loop_s > 0.0 && args.loop_s <= 600.0) {
        anyhow::bail!(
            "--loop-s = {} is out of range: must be in (0, 600]",
            args.loop_s
        );
    }
    let s = Scenario::default();
    let e = ekf_ns(&s)?;
    let h = hopf_ns(&s)?;
    let ik = ik_us(&s)?;
    let c = control_us(&s)?;
    let mut rt = s.clone();
    rt.robot.fri_period_ms = 1;
    let lp = run_loop(&rt, Duration::from_secs_f64(args.loop_s))?;
    let q = quantile_sorted;
    let b = Bench {
        ekf_step_ns: P2 {
            p50: q(&e, 0.5),
            p99: q(&e, 0.99),
        },
        hopf_step_ns: P2 {
            p50: q(&h, 0.5),
            p99: q(&h, 0.99),
        },
        ik_solve_us: P3 {
            p50: q(&ik, 0.5),
            p99: q(&ik, 0.99),
            max: q(&ik, 1.0),
        },
        control_step_us: P4 {
            p50: q(&c, 0.5),
            p99: q(&c, 0.99),
            p999: q(&c, 0.999),
            max: q(&c, 1.0),
        },
        vision_frame_ms: None,
        loop_: lp,
    };
    if args.json {
        return Ok(serde_json::to_string(&b)?);
    }
    Ok(format!(
        "ekf step        p50 {:.0} ns, p99 {:.0} ns\n\
         hopf step       p50 {:.0} ns, p99 {:.0} ns\n\
         ik solve        p50 {:.2} us, p99 {:.2} us, max {:.2} us\n\
         control step    p50 {:.1} us, p99 {:.1} us, p99.9 {:.1} us, max {:.1} us\n\
         loop ({} ms)     {} cycles, {} late, {} missed; reply p50 {:.0} us, p99.9 {:.0} us, max {:.0} us",
        b.ekf_step_ns.p50,
        b.ekf_step_ns.p99,
        b.hopf_step_ns.p50,
        b.hopf_step_ns.p99,
        b.ik_solve_us.p50,
        b.ik_solve_us.p99,
        b.ik_solve_us.max,
        b.control_step_us.p50,
        b.control_step_us.p99,
        b.control_step_us.p999,
        b.control_step_us.max,
        lp.period_ms,
        lp.cycles,
        lp.late_replies,
        lp.missed_cycles,
        lp.reply_latency_us.p50,
        lp.reply_latency_us.p999,
        lp.reply_latency_us.max,
    ))
}
