//! The reality lab's part of `isochron eval` (issue #20): the same `isochron
//! trials` runs on a scenario with `[world]` (a world the controller does not
//! know), per distance band and movement time, the paper's own condition, and
//! an ablation table (each world effect alone, all together; the controller's
//! online estimation on and off, and each of its switches off). Every figure
//! here is a **reality-lab** figure but the ablation's truthful row (issue
//! #40: the truthful simulator and judge); the rest of the report is
//! truthful-world. Each ablation row is timed by its judge's arrival rule
//! ([`check_judge_fits`]) and names that judge.

use std::{fmt::Write as _, path::Path};

use anyhow::bail;
use rt_core::{
    control::stats::wilson_ci95,
    params::{RangeParam, Scenario},
    sim::world::{judge::SETTLE_M, params::WorldParams},
};
use serde_json::Value;

use super::eval::run_cell;
use crate::plot;

/// One row of the reality lab's tables.
#[derive(Debug, Clone)]
pub struct RealityRow {
    /// Which table: `"band"`, `"time"`, `"paper"`, `"ablation"`.
    pub group: &'static str,
    /// What the row is.
    pub label: String,
    /// The `--per-trial` lines.
    pub trials: Vec<Value>,
    /// The command line that produced it.
    pub command: String,
    /// What the row's figures owe to the controller rather than to the
    /// row's world (shown beside the ablation's rows).
    pub note: Option<String>,
}

/// What the truthful row of the ablation changes in the controller's
/// beliefs, said beside it.
pub const TRUTHFUL_NOTE: &str = "beliefs as the truthful simulator: its magnet drops the ball \
     at the switch (`control.release_delay_prior_ms = 0`), its arrival is the fitted \
     profile's end (`control.arrival_settle_m = 0`)";

/// The judge a scenario's trials get: the physical judge in a lab with
/// `[world]` (contact with the tool's disc, arrival = the true tool settled
/// within 2 mm), the truthful judge otherwise (arrival = the end of the
/// best-fitting ideal profile).
pub fn judge_of(s: &Scenario) -> &'static str {
    if s.world.is_some() {
        "physical"
    } else {
        "truthful"
    }
}

/// Checks that the controller times its arrival by the rule its judge uses
/// (`control.arrival_settle_m`: 2 mm for the physical judge, 0 for the
/// truthful one); a mismatch makes every trial of the row late or early by
/// the difference of the two rules (issue #40: 147-179 ms).
pub fn check_judge_fits(s: &Scenario) -> anyhow::Result<()> {
    let want = if s.world.is_some() { SETTLE_M } else { 0.0 };
    if (s.control.arrival_settle_m - want).abs() > 1e-12 {
        bail!(
            "{}: control.arrival_settle_m = {} but its trials are judged by the {} judge, \
             whose arrival needs {want}",
            s.name,
            s.control.arrival_settle_m,
            judge_of(s)
        );
    }
    Ok(())
}

/// The controller's online estimation and coping (issues #20 and #36) and
/// the filter's damping estimate, all off (the robot latency estimator
/// always runs).
pub fn estimation_off(s: &Scenario) -> Scenario {
    let mut s = s.clone();
    s.ekf.estimate_frequency = false;
    s.ekf.estimate_offset = false;
    s.ekf.estimate_damping = false;
    s.control.learn_frequency = false;
    s.control.camera_offset_from_release = false;
    s.control.camera_offset_from_contact = false;
    s.control.arrival_trim_from_contact = false;
    s.control.skip_held_detections = false;
    s.ekf.plane_noise_per_m = 0.0;
    s.control.retime = false;
    s
}

/// `world` with only the part `keep` (`"pendulum"`, `"camera"`, `"robot"`,
/// `"geometry"`) left; the others as believed. The magnet's release delay is
/// the pendulum's part: without it the world's magnet is the believed one
/// (an unset `world.pendulum.release_delay_ms` is `control.release_delay_prior_ms`),
/// so the controller's release-delay handling meets what it was built for and
/// a row's bias is its effect's.
pub fn world_only(world: &WorldParams, keep: &str) -> WorldParams {
    let mut w = WorldParams {
        sessions: world.sessions.clone(),
        ..WorldParams::default()
    };
    match keep {
        "pendulum" => w.pendulum = world.pendulum.clone(),
        "camera" => w.camera = world.camera.clone(),
        "robot" => w.robot = world.robot.clone(),
        _ => w.geometry = world.geometry.clone(),
    }
    w
}

/// The scenarios of the reality section: (group, label, scenario).
pub fn reality_scenarios(
    reality: &Scenario,
    movement_times_s: &[f64],
    edges_m: &[f64],
) -> anyhow::Result<Vec<(&'static str, String, Scenario)>> {
    let Some(world) = reality.world.clone() else {
        bail!(
            "--reality: scenario {} has no [world]: it is a truthful world",
            reality.name
        );
    };
    let mut out = Vec::new();
    let paper_t = 1.5;
    let full = RangeParam::new(
        edges_m.first().copied().unwrap_or(0.35),
        edges_m.last().copied().unwrap_or(0.80),
    );
    for band in edges_m.windows(2) {
        let mut s = reality.clone();
        s.task.movement_time_s = paper_t;
        s.task.distance_m = RangeParam::new(band[0], band[1]);
        out.push((
            "band",
            format!("{paper_t} s, {:.2}..{:.2} m", band[0], band[1]),
            s,
        ));
    }
    for &t in movement_times_s {
        let mut s = reality.clone();
        s.task.movement_time_s = t;
        s.task.distance_m = full;
        out.push((
            "time",
            format!("{t} s, {:.2}..{:.2} m", full.lo, full.hi),
            s,
        ));
    }
    let mut paper = reality.clone();
    paper.task.movement_time_s = paper_t;
    paper.task.distance_m = RangeParam::new(0.70, 0.70);
    out.push((
        "paper",
        "0.70 m, 1.5 s (the paper's condition)".into(),
        paper,
    ));
    let mut base = reality.clone();
    base.task.movement_time_s = paper_t;
    base.task.distance_m = full;
    let mut truthful = base.clone();
    truthful.world = None;
    truthful.control.arrival_settle_m = 0.0;
    truthful.control.release_delay_prior_ms = 0.0;
    out.push((
        "ablation",
        "no world effect (truthful world)".into(),
        truthful,
    ));
    // The control of the rows below: the same controller and judge, a world
    // with every part as believed.
    let mut believed = base.clone();
    believed.world = Some(WorldParams {
        sessions: world.sessions.clone(),
        ..WorldParams::default()
    });
    out.push((
        "ablation",
        "no world effect (world as believed)".into(),
        believed,
    ));
    for part in ["pendulum", "camera", "robot", "geometry"] {
        let mut s = base.clone();
        s.world = Some(world_only(&world, part));
        out.push(("ablation", format!("{part} effects alone"), s));
    }
    out.push(("ablation", "all effects".into(), base.clone()));
    out.push((
        "ablation",
        "all effects, online estimation off".into(),
        estimation_off(&base),
    ));
    type Switch = (&'static str, fn(&mut Scenario));
    let switches: [Switch; 9] = [
        ("ekf.estimate_frequency", |s| {
            s.ekf.estimate_frequency = false;
        }),
        ("ekf.estimate_offset", |s| s.ekf.estimate_offset = false),
        ("control.learn_frequency", |s| {
            s.control.learn_frequency = false;
        }),
        ("control.camera_offset_from_release", |s| {
            s.control.camera_offset_from_release = false;
        }),
        ("control.camera_offset_from_contact", |s| {
            s.control.camera_offset_from_contact = false;
        }),
        ("control.arrival_trim_from_contact", |s| {
            s.control.arrival_trim_from_contact = false;
        }),
        ("control.skip_held_detections", |s| {
            s.control.skip_held_detections = false;
        }),
        ("ekf.plane_noise_per_m", |s| s.ekf.plane_noise_per_m = 0.0),
        ("control.retime", |s| s.control.retime = false),
    ];
    for (name, off) in switches {
        let mut s = base.clone();
        off(&mut s);
        if s != base {
            out.push(("ablation", format!("all effects, {name} off"), s));
        }
    }
    for (i, (_, _, s)) in out.iter_mut().enumerate() {
        s.name = format!("{}-r{i:02}", reality.name);
        s.validate()?;
        check_judge_fits(s)?;
    }
    Ok(out)
}

/// Runs every reality scenario through `isochron trials` (`exe`).
pub fn run_reality(
    exe: &Path,
    dir: &Path,
    reality: &Scenario,
    n: usize,
    seed: u64,
    movement_times_s: &[f64],
    edges_m: &[f64],
) -> anyhow::Result<Vec<RealityRow>> {
    let scenarios = reality_scenarios(reality, movement_times_s, edges_m)?;
    let total = scenarios.len();
    let mut rows = Vec::with_capacity(total);
    for (i, (group, label, s)) in scenarios.into_iter().enumerate() {
        eprintln!("eval: reality lab {}/{total}: {label}, {n} trials", i + 1);
        let note = (s.world.is_none()).then(|| TRUTHFUL_NOTE.to_owned());
        let (_, trials, command) = run_cell(exe, dir, &s, n, seed)?;
        rows.push(RealityRow {
            group,
            label,
            trials,
            command,
            note,
        });
    }
    Ok(rows)
}

/// The trial's judge: `"physical"` when it carries the physical judge's
/// verdict, `"truthful"` when only the truthful judge's (a fitted arrival).
pub fn trial_judge(v: &Value) -> Option<&'static str> {
    if v.get("physical").is_some_and(|p| !p.is_null()) {
        Some("physical")
    } else if v.get("arrival_s").and_then(Value::as_f64).is_some() {
        Some("truthful")
    } else {
        None
    }
}

/// The signed timing error (negative: early), ms: the physical judge's, or
/// the truthful judge's `arrival - t*` in a truthful world.
pub fn signed_ms(v: &Value) -> f64 {
    let num = |k: &str| v.get(k).and_then(Value::as_f64);
    match trial_judge(v) {
        Some("physical") => v["physical"]["timing_error_ms"]
            .as_f64()
            .unwrap_or(f64::NAN),
        Some(_) => match (num("arrival_s"), num("t_star_s")) {
            (Some(a), Some(t)) => 1e3 * (a - t),
            _ => f64::NAN,
        },
        None => f64::NAN,
    }
}

/// The judge of a row's trials, named with its arrival rule.
fn judge_cell(r: &RealityRow) -> &'static str {
    let mut judges = r.trials.iter().filter_map(trial_judge);
    match judges.next() {
        None => "-",
        Some(first) if judges.any(|j| j != first) => "mixed",
        Some("physical") => "physical (contact; settled within 2 mm)",
        Some(_) => "truthful (fitted profile's end)",
    }
}

/// The report's quantile ([`rt_core::quantile`], numpy's default rule) of a
/// sorted sample, NaN ("–") when it is empty.
fn quantile(sorted: &[f64], p: f64) -> f64 {
    rt_core::quantile::quantile(sorted, p).unwrap_or(f64::NAN)
}

/// One table line: trials, successes, rate, CI, |error| p50/p95, signed mean,
/// limit violations (and, in the ablation, the judge and the note).
fn line(r: &RealityRow) -> String {
    let n = r.trials.len();
    let ok = r
        .trials
        .iter()
        .filter(|v| v["success"].as_bool() == Some(true))
        .count();
    let ci = wilson_ci95(ok, n);
    let signed: Vec<f64> = r
        .trials
        .iter()
        .map(signed_ms)
        .filter(|x| x.is_finite())
        .collect();
    let mut abs: Vec<f64> = signed.iter().map(|x| x.abs()).collect();
    abs.sort_by(f64::total_cmp);
    let mean = signed.iter().sum::<f64>() / signed.len().max(1) as f64;
    let violations: f64 = r
        .trials
        .iter()
        .filter_map(|v| v["limit_violations"].as_f64())
        .sum();
    let mut out = format!(
        "| {} | {n} | {ok} | {:.1}% | {:.1}..{:.1}% | {:.1} / {:.1} | {:+.1} | {violations} |",
        r.label,
        100.0 * ok as f64 / n.max(1) as f64,
        100.0 * ci[0],
        100.0 * ci[1],
        quantile(&abs, 0.5),
        quantile(&abs, 0.95),
        mean,
    );
    if r.group == "ablation" {
        let _ = write!(
            out,
            " {} | {} |",
            judge_cell(r),
            r.note.as_deref().unwrap_or("")
        );
    }
    out
}

/// Appends the reality lab's section to `md` and writes its histogram into `dir`.
pub fn write_reality(
    md: &mut String,
    dir: &Path,
    reality: &Scenario,
    rows: &[RealityRow],
) -> anyhow::Result<()> {
    let _ = writeln!(
        md,
        "\n## Reality lab (`{}`): every figure in this section is a reality-lab figure \
         but the ablation's truthful row (a truthful-world figure)\n\n\
         The scenario's `[world]` (scenarios/README.md) is a lab that is not what the \
         controller believes: the true pendulum (length, drag, pivot friction, swing out of \
         the plane, the magnet's release delay), the true camera (latency per session with \
         jitter, rolling shutter, exposure, lens distortion, pose), the true robot (latency \
         per session drifting within it, second-order servos, noise, torque limits) and the \
         true geometry. Trials are judged by the physical judge on the true world (contact of \
         the ball with the tool's disc in the committed pass, arrival = the true tool settling \
         within 2 mm, signed timing error: negative = early), except the ablation's truthful \
         row (its judge is named in the row). The controller uses only its \
         beliefs, its measurements and (with `--calibration`) calibration files; these runs \
         use no calibration file. Timing error columns: |error| p50 / p95 and the signed mean (ms).\n",
        reality.name
    );
    let header = "| condition | trials | successes | rate | 95% CI | timing error p50 / p95 (ms) | signed mean (ms) | limit violations |\n|---|---|---|---|---|---|---|---|";
    let ablation_header = "| condition | trials | successes | rate | 95% CI | timing error p50 / p95 (ms) | signed mean (ms) | limit violations | judge (arrival) | note |\n|---|---|---|---|---|---|---|---|---|---|";
    for (group, title) in [
        ("band", "By distance band (1.5 s)"),
        ("time", "By movement time (whole range)"),
        ("paper", "The paper's condition"),
        (
            "ablation",
            "Ablation: which world effect costs what, and what the online estimation buys (1.5 s, whole range)",
        ),
    ] {
        let h = if group == "ablation" {
            ablation_header
        } else {
            header
        };
        let _ = writeln!(md, "\n### {title}\n\n{h}");
        for r in rows.iter().filter(|r| r.group == group) {
            let _ = writeln!(md, "{}", line(r));
        }
    }
    let _ = writeln!(
        md,
        "\nOnline estimation off: `ekf.estimate_frequency`, `ekf.estimate_offset`, \
         `ekf.estimate_damping`, `control.learn_frequency`, \
         `control.camera_offset_from_release` and `control.retime` all false (the robot \
         latency estimator always runs). The paper's condition fixes the distance at 0.70 m.\n\n\
         The ablation's rows are reality-lab figures except its truthful row, a \
         **truthful-world** figure: the truthful simulator judged by the truthful judge \
         (arrival = the end of the best-fitting ideal profile, as in the truthful-world \
         tables), the controller timing its arrival by that rule. Every other row is judged \
         by the physical judge, the controller timing its arrival by the settling rule; \
         their control is the world as believed (every part of `[world]` unset), with the \
         same controller and judge as the rows below it. \
         An effect \"alone\" keeps only its part of `[world]`; the other parts are as \
         believed. The magnet's release delay is the pendulum's part: in the camera, robot \
         and geometry rows the magnet is the believed one \
         (`control.release_delay_prior_ms`), so the controller's release-delay handling \
         (`control.camera_offset_from_release`) is the same in every row with a world and \
         meets the magnet it was built for, and a row's bias is its effect's. The truthful \
         simulator has no release delay: its row's beliefs say so (the note beside it)."
    );
    let signed: Vec<f64> = rows
        .iter()
        .filter(|r| r.group != "ablation")
        .flat_map(|r| r.trials.iter())
        .map(signed_ms)
        .filter(|x| x.is_finite())
        .collect();
    let name = "reality_signed_timing_error.svg";
    std::fs::write(
        dir.join(name),
        plot::histogram(
            "Reality lab: signed timing error arrival - t* (negative: early)",
            "signed timing error (ms)",
            &signed,
            30,
        )?,
    )?;
    let caption = format!(
        "Reality lab: signed timing error of every judged trial of the band, movement-time \
         and paper rows ({} trials).",
        signed.len()
    );
    let _ = writeln!(md, "\n![{caption}]({name})\n\n{caption}\n");
    let _ = writeln!(md, "Reproduce the reality lab's rows (in this folder):\n");
    for r in rows {
        let _ = writeln!(md, "    {}", r.command);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn reality() -> Scenario {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
        Scenario::from_file(&path).unwrap()
    }

    #[test]
    fn the_reality_section_has_its_rows_and_says_they_are_reality_lab_figures() {
        let r = reality();
        let sc = reality_scenarios(&r, &[1.2, 2.0], &[0.35, 0.55, 0.80]).unwrap();
        let labels: Vec<&str> = sc.iter().map(|(_, l, _)| l.as_str()).collect();
        assert!(labels.contains(&"0.70 m, 1.5 s (the paper's condition)"));
        assert!(labels.contains(&"camera effects alone"));
        assert!(labels.contains(&"all effects, online estimation off"));
        assert!(labels.contains(&"all effects, control.camera_offset_from_release off"));
        // Each effect alone keeps only its part of the world.
        let cam = &sc
            .iter()
            .find(|(_, l, _)| l == "camera effects alone")
            .unwrap()
            .2;
        let w = cam.world.as_ref().unwrap();
        assert_eq!(w.camera, r.world.as_ref().unwrap().camera);
        assert_eq!(
            w.pendulum,
            rt_core::params::world::WorldPendulumParams::default()
        );
        // The truthful row has no world; the paper row is 0.70 m.
        assert!(sc.iter().any(|(_, _, s)| s.world.is_none()));
        let paper = &sc.iter().find(|(g, _, _)| *g == "paper").unwrap().2;
        assert_eq!(
            (paper.task.distance_m.lo, paper.task.distance_m.hi),
            (0.70, 0.70)
        );
        // A truthful scenario is refused as a reality lab.
        assert!(reality_scenarios(&Scenario::default(), &[1.5], &[0.35, 0.8]).is_err());

        let dir =
            std::env::temp_dir().join(format!("isochron-eval-reality-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let trial = |ok: bool, e: f64| json!({"success": ok, "physical": {"timing_error_ms": e}, "limit_violations": 0, "arrival_s": 2.0, "t_star_s": 2.0});
        let rows = vec![
            RealityRow {
                group: "paper",
                label: "0.70 m, 1.5 s (the paper's condition)".into(),
                trials: vec![trial(true, -3.0), trial(true, 5.0), trial(false, -30.0)],
                command: "isochron trials --scenario cells/x.toml".into(),
                note: None,
            },
            RealityRow {
                group: "ablation",
                label: "all effects".into(),
                trials: vec![trial(true, 1.0)],
                command: "isochron trials --scenario cells/y.toml".into(),
                note: None,
            },
            RealityRow {
                group: "ablation",
                label: "no world effect (truthful world)".into(),
                // The truthful judge: arrival 0.4 ms after t*.
                trials: vec![
                    json!({"success": true, "limit_violations": 0, "arrival_s": 3.0004, "t_star_s": 3.0}),
                ],
                command: "isochron trials --scenario cells/z.toml".into(),
                note: Some(TRUTHFUL_NOTE.into()),
            },
        ];
        let mut md = String::new();
        write_reality(&mut md, &dir, &r, &rows).unwrap();
        assert!(md.contains("reality-lab figure"), "{md}");
        assert!(
            md.contains("| 0.70 m, 1.5 s (the paper's condition) | 3 | 2 | 66.7% |"),
            "{md}"
        );
        // Signed mean of -3, 5, -30: -9.3 ms (early).
        assert!(md.contains("| -9.3 |"), "{md}");
        // Each ablation row names its judge; the truthful row's signed error
        // is the truthful judge's, its note beside it.
        assert!(
            md.contains("| +1.0 | 0 | physical (contact; settled within 2 mm) |  |"),
            "{md}"
        );
        assert!(
            md.contains(&format!(
                "| +0.4 | 0 | truthful (fitted profile's end) | {TRUTHFUL_NOTE} |"
            )),
            "{md}"
        );
        let svg = std::fs::read_to_string(dir.join("reality_signed_timing_error.svg")).unwrap();
        assert!(svg.starts_with("<svg"));
    }

    #[test]
    fn every_ablation_row_is_timed_by_its_judges_rule_and_isolates_its_effect() {
        let r = reality();
        let world = r.world.clone().unwrap();
        let sc = reality_scenarios(&r, &[1.5], &[0.35, 0.8]).unwrap();
        let row = |label: &str| &sc.iter().find(|(_, l, _)| l == label).unwrap().2;
        for (_, label, s) in &sc {
            check_judge_fits(s).unwrap_or_else(|e| panic!("{label}: {e}"));
        }
        // The truthful row: the truthful judge's arrival and the truthful
        // simulator's magnet (it drops at the switch); the rest as reality's.
        let t = row("no world effect (truthful world)");
        assert_eq!(judge_of(t), "truthful");
        assert_eq!(t.control.arrival_settle_m, 0.0);
        assert_eq!(t.control.release_delay_prior_ms, 0.0);
        assert!(t.control.camera_offset_from_release);
        // Timed by the other judge's rule, a row is refused.
        let mut wrong = t.clone();
        wrong.control.arrival_settle_m = SETTLE_M;
        assert!(check_judge_fits(&wrong).is_err());
        let mut wrong = row("all effects").clone();
        wrong.control.arrival_settle_m = 0.0;
        assert!(check_judge_fits(&wrong).is_err());
        // Every world row: the same controller (release-delay handling included).
        for label in [
            "no world effect (world as believed)",
            "pendulum effects alone",
            "camera effects alone",
            "robot effects alone",
            "geometry effects alone",
            "all effects",
        ] {
            let s = row(label);
            assert_eq!(judge_of(s), "physical", "{label}");
            assert_eq!(s.control, r.control, "{label}");
        }
        // The magnet's release delay is the pendulum's: drawn there, the
        // believed one elsewhere.
        let p = row("pendulum effects alone").world.as_ref().unwrap();
        assert_eq!(p.pendulum.release_delay_ms, world.pendulum.release_delay_ms);
        assert!(p.pendulum.release_delay_ms.is_some());
        for label in [
            "no world effect (world as believed)",
            "camera effects alone",
            "robot effects alone",
            "geometry effects alone",
        ] {
            let w = row(label).world.as_ref().unwrap();
            assert_eq!(w.pendulum.release_delay_ms, None, "{label}");
        }
    }
}
