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
use rt_core::trajectory::strike::{
    CONTACT_PHASES, StrikeLimit, StrikePlan, StrikeRefusal, StrikeSearch, Stroke,
    largest_strike_speed, plan_strike, strike_direction,
};
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
    /// With `--strike`: the strike mode's stroke instead (its largest feasible speed).
    Plan(PlanArgs),
    /// The largest feasible strike speed over distance and movement time (the
    /// strike mode's feasibility map): a markdown table and JSON in `--out`.
    StrikeMap(StrikeMapArgs),
}

/// Arguments of `isochron kin strike-map`.
#[derive(Debug, clap::Args)]
pub struct StrikeMapArgs {
    /// The lab (intercept height, tool); default: the paper's lab.
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Distances, metres (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.35,0.45,0.55,0.60,0.70,0.80"
    )]
    pub distances_m: Vec<f64>,
    /// Movement times (contact after the stroke's start), seconds (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "0.5,0.75,1.0,1.5,2.0")]
    pub movement_times_s: Vec<f64>,
    /// The strike direction's elevation above the horizontal in the swing plane, degrees.
    #[arg(long, default_value_t = 20.0)]
    pub strike_direction_deg: f64,
    /// The tool's mass, kg (at the flange).
    #[arg(long, default_value_t = DEFAULT_TOOL_MASS_KG)]
    pub tool_mass_kg: f64,
    /// Where to write `strike_map.md` and `strike_map.json`.
    #[arg(long, default_value = "reports/strike")]
    pub out: PathBuf,
}

/// The tool's mass the strike commands assume by default, kg: a 10 cm
/// aluminium rod with a 6 cm disc and its mount.
pub const DEFAULT_TOOL_MASS_KG: f64 = 0.2;
/// The fastest stroke the strike search tries, m/s.
const STRIKE_MAX_MPS: f64 = 3.0;
/// The strike search's resolution, m/s.
const STRIKE_RESOLUTION_MPS: f64 = 0.02;

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
    /// Plan the strike mode's stroke (through the intercept point along the
    /// strike direction, contact at the movement time) and print the largest
    /// feasible strike speed.
    #[arg(long)]
    pub strike: bool,
    /// With `--strike`: also plan this tool speed at contact, m/s (exit 0 only
    /// when it is feasible).
    #[arg(long, requires = "strike")]
    pub strike_speed_mps: Option<f64>,
    /// With `--strike`: the strike direction's elevation above the horizontal
    /// in the swing plane, degrees.
    #[arg(long, default_value_t = 20.0, requires = "strike")]
    pub strike_direction_deg: f64,
    /// With `--strike`: the tool's mass, kg (at the flange).
    #[arg(long, default_value_t = DEFAULT_TOOL_MASS_KG, requires = "strike")]
    pub tool_mass_kg: f64,
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
        KinCommand::Plan(p) if p.strike => run_strike(&p),
        KinCommand::Plan(p) => run_plan(&p),
        KinCommand::StrikeMap(m) => run_strike_map(&m),
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

/// The strike commands' direction (in the swing plane, degrees above the
/// horizontal) and tool mass, refused with the option's name when out of range.
fn check_strike(direction_deg: f64, tool_mass_kg: f64) -> anyhow::Result<()> {
    check::within("--strike-direction-deg", direction_deg, -60.0, 60.0)?;
    check::within("--tool-mass-kg", tool_mass_kg, 0.0, 5.0)?;
    Ok(())
}

/// One strike plan, as `kin plan --strike --json` prints it.
#[derive(Debug, Serialize)]
struct StrikeAnswer {
    feasible: bool,
    speed_mps: f64,
    contact_fraction: f64,
    contact_s: f64,
    approach_m: f64,
    brake_m: f64,
    cycle_s: f64,
    start_m: [f64; 3],
    end_m: [f64; 3],
    speed_ratio: Option<[f64; JOINTS]>,
    acceleration_ratio: Option<[f64; JOINTS]>,
    torque_nm: Option<[f64; JOINTS]>,
    torque_ratio: Option<[f64; JOINTS]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    reason: Option<String>,
}

impl StrikeAnswer {
    fn of(p: &StrikePlan) -> Self {
        let s = &p.stroke;
        Self {
            feasible: p.feasible,
            speed_mps: s.speed_mps,
            contact_fraction: s.contact_fraction,
            contact_s: s.contact_s,
            approach_m: s.approach_m,
            brake_m: s.brake_m,
            cycle_s: s.request.movement_time_s,
            start_m: s.request.start_m.into(),
            end_m: s.request.end_m.into(),
            speed_ratio: p.plan.as_ref().map(|m| m.speed_ratio),
            acceleration_ratio: p.plan.as_ref().map(|m| m.acceleration_ratio),
            torque_nm: p.torque.map(|t| t.peak_nm),
            torque_ratio: p.torque.map(|t| t.ratio),
            reason: p.reason.as_ref().map(ToString::to_string),
        }
    }
}

/// `kin plan --strike --json`.
#[derive(Debug, Serialize)]
struct StrikeReport {
    mode: &'static str,
    distance_m: f64,
    movement_time_s: f64,
    strike_direction_deg: f64,
    tool_mass_kg: f64,
    largest_speed_mps: f64,
    largest: Option<StrikeAnswer>,
    binding: Option<String>,
    requested: Option<StrikeAnswer>,
}

fn strike_search(scenario: &Scenario, movement_time_s: f64, tool_mass_kg: f64) -> StrikeSearch {
    StrikeSearch {
        movement_time_s,
        tool: rt_core::kinematics::Tool::along_z(scenario.task.tool_length_m),
        tool_mass_kg,
        max_speed_mps: STRIKE_MAX_MPS,
        resolution_mps: STRIKE_RESOLUTION_MPS,
        // The controller's check: where the arm waits must be out of the
        // believed swing.
        swing: Some(rt_core::trajectory::strike::SwingClearance::new(
            scenario.pendulum.length_m,
            scenario.pendulum.ball_radius_m,
            scenario.task.tool_contact_radius_m,
        )),
    }
}

/// The best plan at `speed` over the contact phases: the first feasible one,
/// else the last refusal.
fn strike_at(
    contact: nalgebra::Vector3<f64>,
    direction: nalgebra::Vector3<f64>,
    speed: f64,
    search: &StrikeSearch,
    params: &TrajectoryParams,
) -> anyhow::Result<Result<StrikePlan, Option<StrikeRefusal>>> {
    let mut why = None;
    for f in CONTACT_PHASES {
        let stroke = Stroke::new(
            contact,
            direction,
            speed,
            search.movement_time_s,
            f,
            search.tool,
        )?;
        let p = plan_strike(stroke, params, search.tool_mass_kg)?;
        if p.feasible {
            return Ok(Ok(p));
        }
        why = p.reason;
    }
    Ok(Err(why))
}

fn run_strike(args: &PlanArgs) -> anyhow::Result<()> {
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    check::within("--distance-m", args.distance_m, 0.1, 1.2)?;
    let t = args
        .movement_time_s
        .unwrap_or(scenario.task.movement_time_s);
    check::within("--movement-time-s", t, 0.3, 10.0)?;
    check_strike(args.strike_direction_deg, args.tool_mass_kg)?;
    if let Some(v) = args.strike_speed_mps {
        check::within("--strike-speed-mps", v, 0.01, STRIKE_MAX_MPS)?;
    }
    let params = TrajectoryParams {
        elbow: match args.elbow {
            Elbow::Free => ElbowPolicy::Free,
            Elbow::Planar => ElbowPolicy::Planar,
        },
        ..TrajectoryParams::default()
    };
    let contact = scenario.task.intercept_m(args.distance_m);
    // The ball passing towards +y returns towards -y (the arm is symmetric).
    let direction = strike_direction(-1.0, args.strike_direction_deg);
    let search = strike_search(&scenario, t, args.tool_mass_kg);
    let limit: StrikeLimit = largest_strike_speed(contact, direction, &search, &params)?;
    let requested = match args.strike_speed_mps {
        Some(v) => Some(strike_at(contact, direction, v, &search, &params)?),
        None => None,
    };
    let report = StrikeReport {
        mode: "strike",
        distance_m: args.distance_m,
        movement_time_s: t,
        strike_direction_deg: args.strike_direction_deg,
        tool_mass_kg: args.tool_mass_kg,
        largest_speed_mps: limit.speed_mps,
        largest: limit.best.as_ref().map(StrikeAnswer::of),
        binding: limit.binding.as_ref().map(ToString::to_string),
        requested: requested
            .as_ref()
            .and_then(|r| r.as_ref().ok())
            .map(StrikeAnswer::of),
    };
    let text = if args.json {
        serde_json::to_string(&report)?
    } else {
        strike_human(&report, args.strike_speed_mps, requested.as_ref())
    };
    let mut out = std::io::stdout().lock();
    match writeln!(out, "{text}").and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => return Err(e.into()),
        _ => {}
    }
    match requested {
        Some(Err(why)) => bail!(
            "infeasible strike: {}",
            why.map_or_else(|| "no reason given".to_owned(), |w| w.to_string())
        ),
        None if limit.speed_mps <= 0.0 => bail!(
            "no feasible strike: {}",
            limit
                .binding
                .as_ref()
                .map_or_else(|| "no reason given".to_owned(), ToString::to_string)
        ),
        _ => Ok(()),
    }
}

fn strike_line(a: &StrikeAnswer) -> String {
    let mut t = format!(
        "{:.2} m/s at contact, contact at {:.0}% of a {:.3} s cycle: approach {:.3} m, brake {:.3} m\n",
        a.speed_mps,
        a.contact_fraction * 100.0,
        a.cycle_s,
        a.approach_m,
        a.brake_m
    );
    if let Some(sr) = a.speed_ratio {
        t += "peak speed / limit:";
        for (i, r) in sr.iter().enumerate() {
            t += &format!(" A{}={:.0}%", i + 1, r * 100.0);
        }
    }
    if let Some(tr) = a.torque_ratio {
        t += "\npeak torque / limit:";
        for (i, r) in tr.iter().enumerate() {
            t += &format!(" A{}={:.0}%", i + 1, r * 100.0);
        }
    }
    t
}

fn strike_human(
    r: &StrikeReport,
    asked: Option<f64>,
    requested: Option<&Result<StrikePlan, Option<StrikeRefusal>>>,
) -> String {
    let mut t = format!(
        "strike at d = {:.3} m, contact {:.3} s after the start, direction {:+.0} deg, tool {:.2} kg\n",
        r.distance_m, r.movement_time_s, r.strike_direction_deg, r.tool_mass_kg
    );
    t += &format!(
        "largest feasible strike speed: {:.2} m/s\n",
        r.largest_speed_mps
    );
    if let Some(a) = &r.largest {
        t += &strike_line(a);
        t += "\n";
    }
    if let Some(b) = &r.binding {
        t += &format!("faster is refused: {b}\n");
    }
    if let (Some(v), Some(req)) = (asked, requested) {
        match req {
            Ok(p) => {
                t += &format!("at {v:.2} m/s: feasible\n");
                t += &strike_line(&StrikeAnswer::of(p));
            }
            Err(why) => {
                t += &format!(
                    "at {v:.2} m/s: REFUSED ({})",
                    why.as_ref()
                        .map_or_else(|| "no reason given".to_owned(), ToString::to_string)
                );
            }
        }
    }
    t.trim_end().to_owned()
}

/// One cell of the strike map.
#[derive(Debug, Serialize)]
struct StrikeCell {
    distance_m: f64,
    movement_time_s: f64,
    largest_speed_mps: f64,
    contact_fraction: Option<f64>,
    binding: Option<String>,
}

fn run_strike_map(args: &StrikeMapArgs) -> anyhow::Result<()> {
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    if args.distances_m.is_empty() || args.movement_times_s.is_empty() {
        bail!("--distances-m and --movement-times-s each need at least one value");
    }
    for d in &args.distances_m {
        check::within("--distances-m", *d, 0.1, 1.2)?;
    }
    for t in &args.movement_times_s {
        check::within("--movement-times-s", *t, 0.3, 10.0)?;
    }
    check_strike(args.strike_direction_deg, args.tool_mass_kg)?;
    let params = TrajectoryParams::default();
    let direction = strike_direction(-1.0, args.strike_direction_deg);
    let mut cells = Vec::new();
    for &t in &args.movement_times_s {
        let search = strike_search(&scenario, t, args.tool_mass_kg);
        for &d in &args.distances_m {
            let limit =
                largest_strike_speed(scenario.task.intercept_m(d), direction, &search, &params)?;
            eprintln!("strike map: {d:.2} m, {t:.2} s: {:.2} m/s", limit.speed_mps);
            cells.push(StrikeCell {
                distance_m: d,
                movement_time_s: t,
                largest_speed_mps: limit.speed_mps,
                contact_fraction: limit.best.as_ref().map(|b| b.stroke.contact_fraction),
                binding: limit.binding.as_ref().map(ToString::to_string),
            });
        }
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut md = String::from("# Strike mode: the largest feasible strike speed\n\n");
    md += &format!(
        "Tool speed at contact (m/s) of the fastest feasible stroke through the intercept \
         point (height {:.2} m) along the swing plane ({:+.0} deg above the horizontal), \
         contact after the movement time, over the contact phases {:?} of the Hopf cycle, \
         where the arm waits armed out of the ball's swing (the controller's check); \
         kinematic limits of `[trajectory]` (speed {:.0}%, acceleration {:.0}%, position \
         margin {:.0} deg) and joint torques within {:.0}% of the iiwa 7's limits (recursive \
         Newton-Euler, CAD inertials, a {:.2} kg tool at the flange). Resolution {:.2} m/s, \
         searched up to {:.1} m/s. Written by `isochron kin strike-map`.\n\n",
        scenario.task.intercept_height_m,
        args.strike_direction_deg,
        CONTACT_PHASES,
        params.velocity_fraction * 100.0,
        params.acceleration_fraction * 100.0,
        params.position_margin_deg,
        rt_core::trajectory::strike::TORQUE_FRACTION * 100.0,
        args.tool_mass_kg,
        STRIKE_RESOLUTION_MPS,
        STRIKE_MAX_MPS,
    );
    md += "| movement time \\ distance |";
    for d in &args.distances_m {
        md += &format!(" {d:.2} m |");
    }
    md += "\n|---|";
    for _ in &args.distances_m {
        md += "---|";
    }
    md += "\n";
    for &t in &args.movement_times_s {
        md += &format!("| {t:.2} s |");
        for c in cells.iter().filter(|c| c.movement_time_s == t) {
            md += &format!(" {:.2} |", c.largest_speed_mps);
        }
        md += "\n";
    }
    md += "\nWhat binds the next faster stroke:\n\n";
    for c in &cells {
        md += &format!(
            "- {:.2} m, {:.2} s: {}\n",
            c.distance_m,
            c.movement_time_s,
            c.binding
                .as_deref()
                .unwrap_or("nothing up to the search's maximum")
        );
    }
    std::fs::write(args.out.join("strike_map.md"), &md)?;
    std::fs::write(
        args.out.join("strike_map.json"),
        serde_json::to_string_pretty(&cells)?,
    )?;
    println!("{md}");
    Ok(())
}
