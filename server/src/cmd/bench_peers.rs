//! `isochron bench --peers PYTHON`: the filter step and the per-cycle IK beside
//! their usual Python peers in the same run, on the same inputs:
//! filterpy's `ExtendedKalmanFilter` (the same five-state pendulum model, RK4
//! with its exact Jacobian, the same noise) and the Robotics Toolbox's C++
//! Levenberg-Marquardt solver (`ETS.ik_LM`, warm-started from the previous
//! cycle) on the iiwa 7 from this repository's URDF, reaching the flange poses
//! isochron's IK reached along its path.
//!
//! The peers run in `PYTHON` (a Python with `filterpy` and
//! `roboticstoolbox-python`; `make bench` makes one in `.venv-peers`) as a
//! script embedded here (`bench_peers.py`), reading one JSON input file.
//! The ratios are the peers' median time per call over isochron's. They are
//! reported only when the peers did the same job: the filter's final angle
//! within 1 mrad of isochron's on every run, every IK target reached within
//! 10 um, and the toolbox's forward kinematics of isochron's joints on the
//! targets (the same arm).

use std::path::Path;
use std::process::Command;

use anyhow::Context;
use rt_core::ekf::Ekf;
use rt_core::kinematics::{Joints, fk};
use rt_core::params::Scenario;
use serde::{Deserialize, Serialize};

const SCRIPT: &str = include_str!("bench_peers.py");

/// `ik_LM`'s tolerance (on `E = e^T W e / 2`): its default 1e-6 accepts a seed
/// 1.3 mm from the target without iterating; 1e-10 reaches it to 0.3 um.
const IK_LM_TOL: f64 = 1e-10;

/// The largest position error of a solved IK target for the same job, m.
const IK_SAME_JOB_M: f64 = 1e-5;

/// One filter run: capture times and lateral measurements, and isochron's
/// final angle estimate.
#[derive(Debug, Clone, Serialize)]
pub struct EkfRun {
    pub t: Vec<f64>,
    pub z: Vec<f64>,
    pub phi_final: f64,
}

#[derive(Debug, Serialize)]
struct EkfSpec<'a> {
    length_m: f64,
    gravity_mps2: f64,
    damping_per_s: f64,
    measurement_noise_m: f64,
    accel_psd_rad2ps3: f64,
    damping_psd_per_s3: f64,
    damping_std_per_s: f64,
    max_step_s: f64,
    runs: &'a [EkfRun],
}

/// The IK path: isochron's solutions and the flange poses they reach.
#[derive(Debug, Clone, Default)]
pub struct IkPath {
    /// Targets per path (the path restarts from home after this many).
    pub path_len: usize,
    pub q_home: Joints,
    pub q: Vec<Joints>,
}

#[derive(Debug, Serialize)]
struct IkSpec {
    urdf: String,
    /// `ik_LM`'s tolerance on half the squared pose error.
    tol: f64,
    path_len: usize,
    q_home: [f64; 7],
    q: Vec<[f64; 7]>,
    /// Row-major 4x4 `base_from_flange` of each `q`.
    flange_poses: Vec<[f64; 16]>,
}

#[derive(Debug, Serialize)]
struct Spec<'a> {
    ekf: EkfSpec<'a>,
    ik: IkSpec,
}

/// p50 / p99 / max of a peer's calls.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct PeerTimes {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
    pub count: u64,
}

#[derive(Debug, Deserialize)]
struct PeerEkf {
    step_ns: PeerTimes,
    final_angle_max_diff_rad: f64,
}

#[derive(Debug, Deserialize)]
struct PeerIk {
    solve_us: PeerTimes,
    solved: u64,
    targets: u64,
    max_position_error_m: f64,
    fk_max_error_m: f64,
}

#[derive(Debug, Deserialize)]
struct PeerOut {
    python: String,
    numpy: String,
    filterpy: String,
    roboticstoolbox: String,
    ekf: PeerEkf,
    ik: PeerIk,
}

/// `peers` in `isochron bench --json`.
#[derive(Debug, Serialize)]
pub struct Peers {
    /// Versions: Python, numpy, filterpy, roboticstoolbox-python.
    pub versions: [String; 4],
    /// filterpy's predict + update per measurement, ns.
    pub filterpy_ekf_step_ns: PeerTimes,
    /// filterpy's final angle against isochron's, worst run, rad.
    pub filterpy_final_angle_max_diff_rad: f64,
    /// `filterpy_ekf_step_ns.p50` over isochron's `ekf_step_ns.p50`.
    pub ekf_ratio: Option<f64>,
    /// The toolbox's `ik_LM` per target, us (tolerance `toolbox_ik_tol`).
    pub toolbox_ik_lm_us: PeerTimes,
    pub toolbox_ik_tol: f64,
    /// Targets it solved, of `ik_targets`.
    pub toolbox_ik_solved: u64,
    pub ik_targets: u64,
    /// Its worst position error on a solved target, m.
    pub toolbox_ik_max_position_error_m: f64,
    /// The toolbox's forward kinematics of isochron's joints against the
    /// targets, worst, m (the same arm).
    pub toolbox_fk_max_error_m: f64,
    /// `toolbox_ik_lm_us.p50` over isochron's `ik_solve_us.p50`.
    pub ik_ratio: Option<f64>,
    /// Why a ratio is missing (the peers did not do the same job).
    pub refused: Vec<String>,
}

/// isochron's filter on `runs` measurement sequences; returns each call's time
/// (ns, unsorted) and fills each run's final angle.
pub fn time_ekf(s: &Scenario, runs: &mut [EkfRun]) -> anyhow::Result<Vec<f64>> {
    let model = rt_core::pendulum::PendulumModel::from_params(&s.pendulum)?;
    let geo = rt_core::pendulum::PendulumGeometry::new(
        s.pendulum.length_m,
        0.6,
        s.task.intercept_height_m,
    )?;
    let mut out = Vec::with_capacity(runs.iter().map(|r| r.t.len()).sum());
    for run in runs.iter_mut() {
        let mut ekf = Ekf::new(s.ekf.clone(), model, geo)?;
        for (&t, &z) in run.t.iter().zip(&run.z) {
            let started = std::time::Instant::now();
            let _ = ekf.measure(t, z);
            out.push(started.elapsed().as_nanos() as f64);
        }
        run.phi_final = ekf.posterior().map_or(f64::NAN, |(_, x, _)| x[0]);
    }
    Ok(out)
}

/// Runs the peers in `python` on the same inputs; `ours` = isochron's
/// `ekf_step_ns.p50` and `ik_solve_us.p50` from the same run.
pub fn run(
    python: &Path,
    s: &Scenario,
    runs: &[EkfRun],
    ik: &IkPath,
    ours: (f64, f64),
) -> anyhow::Result<Peers> {
    let dir = tempfile::tempdir().context("a temporary directory for the peers")?;
    let urdf = dir.path().join("iiwa7.urdf");
    std::fs::write(
        &urdf,
        rt_core::kinematics::iiwa7::urdf_with_tool(s.task.tool_length_m),
    )?;
    let model = rt_core::pendulum::PendulumModel::from_params(&s.pendulum)?;
    let spec = Spec {
        ekf: EkfSpec {
            length_m: model.length_m,
            gravity_mps2: model.gravity_mps2,
            damping_per_s: model.damping_per_s,
            measurement_noise_m: s.ekf.measurement_noise_m,
            accel_psd_rad2ps3: s.ekf.accel_psd_rad2ps3,
            damping_psd_per_s3: s.ekf.damping_psd_per_s3,
            damping_std_per_s: s.ekf.damping_std_per_s,
            max_step_s: s.ekf.max_step_s,
            runs,
        },
        ik: IkSpec {
            urdf: urdf.display().to_string(),
            tol: IK_LM_TOL,
            path_len: ik.path_len,
            q_home: ik.q_home.into(),
            q: ik.q.iter().map(|q| (*q).into()).collect(),
            flange_poses: ik
                .q
                .iter()
                .map(|q| {
                    let m = fk::flange_pose(q).to_homogeneous();
                    std::array::from_fn(|i| m[(i / 4, i % 4)])
                })
                .collect(),
        },
    };
    let input = dir.path().join("input.json");
    std::fs::write(&input, serde_json::to_vec(&spec)?)?;
    let script = dir.path().join("bench_peers.py");
    std::fs::write(&script, SCRIPT)?;
    let out = Command::new(python)
        .arg(&script)
        .arg(&input)
        .output()
        .with_context(|| format!("--peers {}: cannot run it", python.display()))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let last = err.lines().last().unwrap_or("no message");
        anyhow::bail!(
            "--peers {}: the peers failed ({}): {last}",
            python.display(),
            out.status
        );
    }
    let p: PeerOut = serde_json::from_slice(&out.stdout).with_context(|| {
        format!(
            "--peers {}: its output is not the peers' JSON",
            python.display()
        )
    })?;
    Ok(judge(p, ours))
}

/// The ratios, when the peers did the same job.
fn judge(p: PeerOut, (ekf_ours_ns, ik_ours_us): (f64, f64)) -> Peers {
    let mut refused = Vec::new();
    let ekf_same = p.ekf.final_angle_max_diff_rad <= 1e-3;
    if !ekf_same {
        refused.push(format!(
            "filterpy's final angle is {:.2e} rad from isochron's (more than 1 mrad)",
            p.ekf.final_angle_max_diff_rad
        ));
    }
    let ik_same = p.ik.fk_max_error_m <= 1e-6
        && p.ik.solved == p.ik.targets
        && p.ik.max_position_error_m <= IK_SAME_JOB_M;
    if !ik_same {
        refused.push(format!(
            "the toolbox solved {} of {} targets (worst {:.2e} m; its FK of isochron's joints {:.2e} m off)",
            p.ik.solved, p.ik.targets, p.ik.max_position_error_m, p.ik.fk_max_error_m
        ));
    }
    let ratio = |peer: f64, ours: f64| (ours > 0.0).then_some(peer / ours);
    Peers {
        versions: [p.python, p.numpy, p.filterpy, p.roboticstoolbox],
        filterpy_ekf_step_ns: p.ekf.step_ns,
        filterpy_final_angle_max_diff_rad: p.ekf.final_angle_max_diff_rad,
        ekf_ratio: ekf_same
            .then(|| ratio(p.ekf.step_ns.p50, ekf_ours_ns))
            .flatten(),
        toolbox_ik_lm_us: p.ik.solve_us,
        toolbox_ik_tol: IK_LM_TOL,
        toolbox_ik_solved: p.ik.solved,
        ik_targets: p.ik.targets,
        toolbox_ik_max_position_error_m: p.ik.max_position_error_m,
        toolbox_fk_max_error_m: p.ik.fk_max_error_m,
        ik_ratio: ik_same
            .then(|| ratio(p.ik.solve_us.p50, ik_ours_us))
            .flatten(),
        refused,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn out(angle_diff: f64, solved: u64, worst_m: f64) -> PeerOut {
        let t = |p50| PeerTimes {
            p50,
            p99: 2.0 * p50,
            max: 3.0 * p50,
            count: 1000,
        };
        PeerOut {
            python: "3.11.7".into(),
            numpy: "2".into(),
            filterpy: "2.0.0".into(),
            roboticstoolbox: "1.5.0".into(),
            ekf: PeerEkf {
                step_ns: t(190_000.0),
                final_angle_max_diff_rad: angle_diff,
            },
            ik: PeerIk {
                solve_us: t(30.0),
                solved,
                targets: 1000,
                max_position_error_m: worst_m,
                fk_max_error_m: 1e-15,
            },
        }
    }

    #[test]
    fn ratios_are_given_only_when_the_peers_did_the_same_job() {
        let p = judge(out(3e-8, 1000, 3e-7), (500.0, 0.75));
        assert_eq!(p.ekf_ratio, Some(380.0));
        assert_eq!(p.ik_ratio, Some(40.0));
        assert!(p.refused.is_empty(), "{:?}", p.refused);
        // The toolbox's default tolerance: a seed 1.3 mm off counts as solved.
        let p = judge(out(3e-8, 1000, 1.34e-3), (500.0, 0.75));
        assert_eq!((p.ekf_ratio, p.ik_ratio), (Some(380.0), None));
        assert!(p.refused[0].contains("1.34e-3 m"), "{:?}", p.refused);
        // A filter that ends elsewhere, an IK that fails a target.
        let p = judge(out(0.02, 999, 3e-7), (500.0, 0.75));
        assert_eq!((p.ekf_ratio, p.ik_ratio), (None, None));
        assert_eq!(p.refused.len(), 2);
    }
}
