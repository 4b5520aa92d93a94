//! `isochron kin fk|ik|plan`: the iiwa 7's kinematics and motion planning from the
//! command line (CONTRACT.md, "Commands").

use std::io::{BufRead, Write};
use std::path::PathBuf;

use anyhow::{Context, bail};
use rt_core::kinematics::analytic::{self, IkError};
use rt_core::kinematics::iiwa7::JOINTS;
use rt_core::kinematics::numeric::rotation_error;
use rt_core::kinematics::{Joints, flange_pose, pose_from_rows, pose_to_rows, within_limits};
use rt_core::params::{Scenario, check};
use rt_core::trajectory::{ElbowPolicy, MotionRequest, PlanSummary, TrajectoryParams, plan};
use serde::{Deserialize, Serialize};

/// Arguments of `isochron kin`.
#[derive(Debug, clap::Args)]
pub struct KinArgs {
    /// What to compute.
    #[command(subcommand)]
    pub command: KinCommand,
}

/// The `kin` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum KinCommand {
    /// Forward kinematics: lines of 7 joint angles (rad, spaces or commas) on stdin ->
    /// one JSON flange pose per line.
    Fk,
    /// Inverse kinematics: JSON lines {"p_m":[..],"R":[[..],[..],[..]],"seed_rad":[..]?}
    /// (flange pose) on stdin -> one JSON answer per line, always within the joint limits.
    Ik {
        /// Keep every joint at least this far inside its limit, degrees.
        #[arg(long, default_value_t = 0.0)]
        margin_deg: f64,
    },
    /// Plan the scenario's interception motion to a distance: tilt, arm angle, speed
    /// ratios, binding joint, margin and shortest feasible duration. Exit 0 when feasible.
    Plan(PlanArgs),
}

/// How the elbow may move (`kin plan --elbow`).
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Elbow {
    /// Any arm angle (the planner's choice).
    Free,
    /// The elbow held in the vertical plane through the base axis.
    Planar,
}

/// Arguments of `isochron kin plan`.
#[derive(Debug, clap::Args)]
pub struct PlanArgs {
    /// Horizontal distance from the robot's base axis to the intercept point, metres.
    #[arg(long)]
    pub distance_m: f64,
    /// Duration of the motion, seconds (default: the scenario's).
    #[arg(long)]
    pub movement_time_s: Option<f64>,
    /// The lab (home, intercept height, tool); default: the paper's lab.
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// How the elbow may move.
    #[arg(long, value_enum, default_value_t = Elbow::Free)]
    pub elbow: Elbow,
    /// Print one JSON object instead of a summary.
    #[arg(long)]
    pub json: bool,
}

/// Runs `isochron kin`.
pub fn run(args: KinArgs) -> anyhow::Result<()> {
    match args.command {
        KinCommand::Fk => stream(fk_line),
        KinCommand::Ik { margin_deg } => {
            check::within("--margin-deg", margin_deg, 0.0, 30.0)?;
            let margin = margin_deg.to_radians();
            stream(|line| ik_line(line, margin))
        }
        KinCommand::Plan(p) => run_plan(&p),
    }
}

/// Reads stdin line by line, writes one JSON line per non-empty input line. A
/// malformed line gives `{"ok":false,"error":"line N: ..."}` and, at the end, a
/// non-zero exit.
fn stream(mut each: impl FnMut(&str) -> Result<String, String>) -> anyhow::Result<()> {
    let stdin = std::io::stdin().lock();
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    let mut bad = 0usize;
    let mut first_bad = String::new();
    for (i, line) in stdin.lines().enumerate() {
        let line = line.context("cannot read stdin")?;
        let text = line.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let answer = match each(text) {
            Ok(json) => json,
            Err(msg) => {
                let msg = format!("line {}: {msg}", i + 1);
                if bad == 0 {
                    first_bad.clone_from(&msg);
                }
                bad += 1;
                serde_json::to_string(&ErrorLine {
                    ok: false,
                    error: &msg,
                })?
            }
        };
        if let Err(e) = writeln!(out, "{answer}").and_then(|()| out.flush()) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                return Ok(());
            }
            return Err(e.into());
        }
    }
    if bad > 0 {
        bail!("{bad} malformed input line(s), first: {first_bad}");
    }
    Ok(())
}

#[derive(Serialize)]
struct ErrorLine<'a> {
    ok: bool,
    error: &'a str,
}

#[derive(Serialize)]
struct FkAnswer {
    p_m: [f64; 3],
    #[serde(rename = "R")]
    r: [[f64; 3]; 3],
    within_limits: bool,
}

fn parse_joints(line: &str) -> Result<Joints, String> {
    let mut q = Joints::zeros();
    let mut n = 0;
    for tok in line.split(|c: char| c == ',' || c.is_whitespace()) {
        if tok.is_empty() {
            continue;
        }
        let v: f64 = tok
            .parse()
            .map_err(|_| format!("{tok:?} is not a number"))?;
        if !v.is_finite() {
            return Err(format!("{tok} is not a finite number"));
        }
        if n < JOINTS {
            q[n] = v;
        }
        n += 1;
    }
    if n != JOINTS {
        return Err(format!("expected {JOINTS} joint angles (radians), got {n}"));
    }
    Ok(q)
}

fn fk_line(line: &str) -> Result<String, String> {
    let q = parse_joints(line)?;
    let (p_m, r) = pose_to_rows(&flange_pose(&q));
    serde_json::to_string(&FkAnswer {
        p_m,
        r,
        within_limits: within_limits(&q, 0.0),
    })
    .map_err(|e| e.to_string())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct IkRequest {
    p_m: [f64; 3],
    #[serde(rename = "R")]
    r: [[f64; 3]; 3],
    #[serde(default)]
    seed_rad: Option<[f64; JOINTS]>,
}

#[derive(Serialize)]
struct IkAnswer {
    ok: bool,
    q_rad: Option<[f64; JOINTS]>,
    pos_err_m: Option<f64>,
    rot_err_rad: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    arm_angle_rad: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    flags: Option<[i8; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    reason: Option<String>,
}

fn ik_line(line: &str, margin_rad: f64) -> Result<String, String> {
    let req: IkRequest = serde_json::from_str(line).map_err(|e| format!("bad JSON: {e}"))?;
    let target = pose_from_rows(req.p_m, req.r).map_err(|e| e.to_string())?;
    let seed = match req.seed_rad {
        Some(s) if s.iter().all(|v| v.is_finite()) => Some(Joints::from(s)),
        Some(_) => return Err("seed_rad must be finite numbers".into()),
        None => None,
    };
    let answer = match analytic::solve(&target, seed.as_ref(), margin_rad) {
        Ok(sol) => {
            let back = flange_pose(&sol.q);
            IkAnswer {
                ok: true,
                q_rad: Some(sol.q.into()),
                pos_err_m: Some((back.translation.vector - target.translation.vector).norm()),
                rot_err_rad: Some(rotation_error(&target.rotation, &back.rotation).norm()),
                arm_angle_rad: Some(sol.arm_angle_rad),
                flags: Some(sol.flags.signs()),
                reason: None,
            }
        }
        Err(e) => refusal(&e),
    };
    serde_json::to_string(&answer).map_err(|e| e.to_string())
}

fn refusal(e: &IkError) -> IkAnswer {
    IkAnswer {
        ok: false,
        q_rad: None,
        pos_err_m: None,
        rot_err_rad: None,
        arm_angle_rad: None,
        flags: None,
        reason: Some(e.to_string()),
    }
}

fn run_plan(args: &PlanArgs) -> anyhow::Result<()> {
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    check::within("--distance-m", args.distance_m, 0.1, 1.2)?;
    let mut request = MotionRequest::interception(&scenario.task, args.distance_m);
    if let Some(t) = args.movement_time_s {
        check::within("--movement-time-s", t, 0.3, 10.0)?;
        request.movement_time_s = t;
    }
    let params = TrajectoryParams {
        elbow: match args.elbow {
            Elbow::Free => ElbowPolicy::Free,
            Elbow::Planar => ElbowPolicy::Planar,
        },
        ..TrajectoryParams::default()
    };
    let summary = match plan(&request, &params) {
        Ok(p) => p.summary(),
        Err(e) => PlanSummary::refused(&request, &e),
    };
    let text = if args.json {
        serde_json::to_string(&summary)?
    } else {
        human(&summary)
    };
    let mut out = std::io::stdout().lock();
    match writeln!(out, "{text}").and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => return Err(e.into()),
        _ => {}
    }
    if !summary.feasible {
        bail!(
            "infeasible: {}",
            summary.reason.as_deref().unwrap_or("no reason given")
        );
    }
    Ok(())
}

fn human(s: &PlanSummary) -> String {
    let mut t = format!(
        "d = {:.3} m in {:.3} s: {}\n",
        s.distance_m,
        s.movement_time_s,
        if s.feasible { "feasible" } else { "REFUSED" }
    );
    if let (Some(tilt), Some(psi), Some(ratio)) = (s.tilt_deg, s.arm_angle_deg, s.speed_ratio) {
        t += &format!("tilt {tilt:.1} deg, arm angle {psi:.1} deg\n");
        t += "peak speed / limit:";
        for (i, r) in ratio.iter().enumerate() {
            t += &format!(" A{}={:.0}%", i + 1, r * 100.0);
        }
        t += "\n";
    }
    if let (Some(j), Some(l)) = (s.binding_joint, s.binding_limit) {
        t += &format!("binding: {j} {l}\n");
    }
    if let Some(m) = s.min_margin_deg {
        t += &format!("smallest position margin {m:.2} deg\n");
    }
    if let Some(ts) = s.shortest_feasible_s {
        t += &format!("shortest feasible duration {ts:.3} s\n");
    }
    if let Some(r) = &s.reason {
        t += &format!("reason: {r}\n");
    }
    t.trim_end().to_owned()
}
