//! `isochron eval`: runs `isochron trials` across distances and movement times and
//! writes a report (Markdown + SVG) that sets the results beside the paper's.
//!
//! Every cell is run by this same binary's `trials` command with a scenario file
//! written for it, so the report's numbers are exactly what `isochron trials` prints
//! for the same scenario and seed (the command lines are in the report).
//! `--reality FILE` adds the reality lab's section (`eval_reality.rs`).

use std::{
    fmt::Write as _,
    path::{Path, PathBuf},
    process::Command,
};

use anyhow::{Context, bail};
use rt_core::{
    control::stats::wilson_ci95,
    params::{RangeParam, Scenario},
    trajectory::profile::ProfileKind,
};
use serde_json::Value;

use crate::plot::{self, Bar, Series, Style};

/// Arguments of `isochron eval`.
#[derive(Debug, clap::Args)]
pub struct EvalArgs {
    /// The lab to evaluate (default: the paper's).
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Folder for the report (report.md, SVG figures, the scenario files, raw results).
    #[arg(long, default_value = "eval")]
    pub out: PathBuf,
    /// Trials per cell (distance band x movement time).
    #[arg(long, default_value_t = 30)]
    pub n: usize,
    /// Seed of every cell's trials.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Movement times to evaluate, seconds.
    #[arg(long, value_delimiter = ',', default_value = "1.2,1.5,2.0")]
    pub movement_times_s: Vec<f64>,
    /// Edges of the distance bands, metres.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.35,0.45,0.55,0.65,0.75,0.80"
    )]
    pub distance_edges_m: Vec<f64>,
    /// A reality lab (a scenario with `[world]`, e.g. scenarios/reality.toml):
    /// adds its section (per band and movement time, the paper's condition,
    /// the ablation table, the signed timing-error histogram).
    #[arg(long)]
    pub reality: Option<PathBuf>,
    /// The robustness envelope (`--envelope`, `eval_envelope.rs`).
    #[command(flatten)]
    pub envelope: super::eval_envelope::EnvelopeArgs,
}

/// Runs `isochron trials` (`exe`) on `sc` (written to `dir/cells/NAME.toml`):
/// its `--json` summary, its `--per-trial` lines and the command line.
pub fn run_cell(
    exe: &Path,
    dir: &Path,
    sc: &Scenario,
    n: usize,
    seed: u64,
) -> anyhow::Result<(Value, Vec<Value>, String)> {
    let file = dir.join("cells").join(format!("{}.toml", sc.name));
    std::fs::write(&file, sc.to_toml_string())?;
    let per_trial = file.with_extension("jsonl");
    let out = Command::new(exe)
        .arg("trials")
        .arg("--scenario")
        .arg(&file)
        .args(["--n", &n.to_string(), "--seed", &seed.to_string()])
        .arg("--json")
        .arg("--per-trial")
        .arg(&per_trial)
        .stderr(std::process::Stdio::null())
        .output()
        .context("cannot run isochron trials")?;
    if !out.status.success() {
        bail!(
            "isochron trials failed for {}: {}",
            file.display(),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let summary: Value =
        serde_json::from_slice(&out.stdout).context("trials printed no JSON summary")?;
    let trials = std::fs::read_to_string(&per_trial)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let command = format!(
        "isochron trials --scenario cells/{}.toml --n {n} --seed {seed} --json",
        sc.name
    );
    Ok((summary, trials, command))
}

/// One cell's outcome.
#[derive(Debug, Clone)]
pub struct Cell {
    /// Movement time, seconds.
    pub movement_time_s: f64,
    /// Distance band, metres.
    pub band_m: (f64, f64),
    /// The `--json` summary of `isochron trials`.
    pub summary: Value,
    /// The `--per-trial` lines.
    pub trials: Vec<Value>,
    /// The command line that produced it.
    pub command: String,
}

fn num(v: &Value, path: &[&str]) -> f64 {
    let mut cur = v;
    for k in path {
        match cur.get(k) {
            Some(x) => cur = x,
            None => return f64::NAN,
        }
    }
    cur.as_f64().unwrap_or(f64::NAN)
}

/// A per-trial value, flat (as `isochron trials --per-trial` writes it) or under `judgement`.
fn field(v: &Value, key: &str) -> f64 {
    let flat = num(v, &[key]);
    if flat.is_finite() {
        flat
    } else {
        num(v, &["judgement", key])
    }
}

fn check_args(a: &EvalArgs) -> anyhow::Result<()> {
    if a.n == 0 || a.n > 10_000 {
        bail!("--n = {} is out of range: must be in [1, 10000]", a.n);
    }
    if a.movement_times_s.is_empty()
        || a.movement_times_s
            .iter()
            .any(|t| !t.is_finite() || !(0.3..=10.0).contains(t))
    {
        bail!("--movement-times-s: every value must be a finite number in [0.3, 10] s");
    }
    let e = &a.distance_edges_m;
    if e.len() < 2
        || e.iter().any(|d| !d.is_finite() || !(0.1..=1.2).contains(d))
        || e.windows(2).any(|w| w[0] >= w[1])
    {
        bail!("--distance-edges-m: at least two increasing values in [0.1, 1.2] m");
    }
    Ok(())
}

/// Runs `isochron eval`; returns the path of the report.
pub fn run(args: &EvalArgs) -> anyhow::Result<String> {
    if args.envelope.envelope {
        return super::eval_envelope::run(args);
    }
    check_args(args)?;
    let base = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    std::fs::create_dir_all(args.out.join("cells"))
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let exe = std::env::current_exe().context("cannot find the isochron binary")?;
    let mut cells = Vec::new();
    let total = args.movement_times_s.len() * (args.distance_edges_m.len() - 1);
    for &t in &args.movement_times_s {
        for band in args.distance_edges_m.windows(2) {
            let mut sc = base.clone();
            sc.name = format!("{}-T{t:.2}-d{:.2}-{:.2}", base.name, band[0], band[1]);
            sc.task.movement_time_s = t;
            sc.task.distance_m = RangeParam::new(band[0], band[1]);
            sc.validate()?;
            eprintln!(
                "eval: cell {}/{total}: T = {t} s, d = {:.2}..{:.2} m, {} trials",
                cells.len() + 1,
                band[0],
                band[1],
                args.n
            );
            let (summary, trials, command) = run_cell(&exe, &args.out, &sc, args.n, args.seed)?;
            cells.push(Cell {
                movement_time_s: t,
                band_m: (band[0], band[1]),
                summary,
                trials,
                command,
            });
        }
    }
    let reality = match &args.reality {
        Some(p) => {
            let r = Scenario::from_file(p)?;
            let rows = super::eval_reality::run_reality(
                &exe,
                &args.out,
                &r,
                args.n,
                args.seed,
                &args.movement_times_s,
                &args.distance_edges_m,
            )?;
            Some((r, rows))
        }
        None => None,
    };
    let report = write_report(
        &args.out,
        &base,
        &cells,
        args.seed,
        reality.as_ref().map(|(r, rows)| (r, rows.as_slice())),
    )?;
    Ok(format!("report: {}", report.display()))
}

fn pct(p: f64) -> String {
    if p.is_finite() {
        format!("{:.1}%", 100.0 * p)
    } else {
        "–".into()
    }
}

/// Writes report.md and its figures into `dir`; returns report.md's path.
pub fn write_report(
    dir: &Path,
    base: &Scenario,
    cells: &[Cell],
    seed: u64,
    reality: Option<(&Scenario, &[super::eval_reality::RealityRow])>,
) -> anyhow::Result<PathBuf> {
    let mut md = String::new();
    let times: Vec<f64> = {
        let mut v: Vec<f64> = cells.iter().map(|c| c.movement_time_s).collect();
        v.dedup();
        v
    };
    let _ = writeln!(
        md,
        "# isochron evaluation: {}\n\nEverything before the section *Reality lab* is a \
         **truthful-world** figure: the simulated lab and the controller share the pendulum \
         model, the timestamps, the geometry and the robot's model. \
         Simulated lab `{}` (pendulum {} m, camera {} fps with {} ms latency, \
         FRI period {} ms, robot latency {} ms unknown to the controller), seed {seed}. \
         Success: tool within {} m of the ball centre when it passes the intercept point, \
         and arrival within {} ms of that moment (CONTRACT.md).\n",
        base.name,
        base.name,
        base.pendulum.length_m,
        base.camera.fps,
        base.camera.latency_ms,
        base.robot.fri_period_ms,
        base.robot.latency_ms,
        base.success.position_tolerance_m,
        base.success.timing_tolerance_ms
    );
    // Headline: per movement time, over all distances.
    let _ = writeln!(
        md,
        "## Headline\n\n| | movement time | distances | trials | precisely timed | 95% CI | timing error p50 / p95 (ms) | movement time std (ms) |\n|---|---|---|---|---|---|---|---|"
    );
    let _ = writeln!(
        md,
        "| paper (real robot) | ~1.5 s (varied per reboot) | 0.70 m (range 0.35..0.80 m) | not stated | 93% | – | – | – |"
    );
    for &t in &times {
        let cs: Vec<&Cell> = cells.iter().filter(|c| c.movement_time_s == t).collect();
        let trials: Vec<&Value> = cs.iter().flat_map(|c| c.trials.iter()).collect();
        let n = trials.len();
        let ok = trials
            .iter()
            .filter(|v| v["success"].as_bool() == Some(true))
            .count();
        let ci = wilson_ci95(ok, n);
        let mut te: Vec<f64> = trials
            .iter()
            .map(|v| field(v, "timing_error_ms"))
            .filter(|x| x.is_finite())
            .collect();
        te.sort_by(f64::total_cmp);
        let q = |p: f64| rt_core::quantile::quantile(&te, p).unwrap_or(f64::NAN);
        let mt: Vec<f64> = trials
            .iter()
            .map(|v| field(v, "movement_time_s"))
            .filter(|x| x.is_finite())
            .collect();
        let mean = mt.iter().sum::<f64>() / mt.len().max(1) as f64;
        let std =
            (mt.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / mt.len().max(1) as f64).sqrt();
        let (dlo, dhi) = (
            cs.first().map_or(f64::NAN, |c| c.band_m.0),
            cs.last().map_or(f64::NAN, |c| c.band_m.1),
        );
        let _ = writeln!(
            md,
            "| isochron (simulated) | {t} s | {dlo:.2}..{dhi:.2} m | {n} | {} | {}..{} | {:.1} / {:.1} | {:.2} |",
            pct(ok as f64 / n.max(1) as f64),
            pct(ci[0]),
            pct(ci[1]),
            q(0.5),
            q(0.95),
            1e3 * std
        );
    }
    // Per cell.
    let _ = writeln!(
        md,
        "\n## By distance and movement time\n\n| movement time | distance band | trials | successes | rate | 95% CI | timing p95 (ms) | position p95 (mm) | planned duration max (s) | failures (first reason) |\n|---|---|---|---|---|---|---|---|---|---|"
    );
    for c in cells {
        let n = c.trials.len();
        let ok = c
            .trials
            .iter()
            .filter(|v| v["success"].as_bool() == Some(true))
            .count();
        let ci = wilson_ci95(ok, n);
        let reason = c
            .trials
            .iter()
            .find_map(|v| v["failure"].as_str())
            .unwrap_or("");
        let planned_max = c
            .trials
            .iter()
            .map(|v| field(v, "planned_movement_time_s"))
            .filter(|x| x.is_finite())
            .fold(f64::NAN, f64::max);
        let _ = writeln!(
            md,
            "| {} s | {:.2}..{:.2} m | {n} | {ok} | {} | {}..{} | {:.1} | {:.1} | {:.3} | {} |",
            c.movement_time_s,
            c.band_m.0,
            c.band_m.1,
            pct(ok as f64 / n.max(1) as f64),
            pct(ci[0]),
            pct(ci[1]),
            num(&c.summary, &["timing_error_ms", "p95"]),
            1e3 * num(&c.summary, &["position_error_m", "p95"]),
            planned_max,
            reason.replace('|', "/")
        );
    }
    let _ = writeln!(
        md,
        "\nWhere the asked movement time is not feasible within the joint limits (90% of the \
         velocity limits, 5 deg position margin) the controller takes the shortest feasible \
         duration and says so: the column *planned duration max* shows it. A trial the \
         system refuses counts as a failure with its reason."
    );
    // Figures.
    let mut figs: Vec<(&str, String, &str)> = Vec::new();
    let bars: Vec<Bar> = cells
        .iter()
        .map(|c| {
            let n = c.trials.len();
            let ok = c
                .trials
                .iter()
                .filter(|v| v["success"].as_bool() == Some(true))
                .count();
            let ci = wilson_ci95(ok, n);
            Bar {
                label: format!(
                    "{} s\n{:.2}-{:.2}",
                    c.movement_time_s, c.band_m.0, c.band_m.1
                ),
                value: 100.0 * ok as f64 / n.max(1) as f64,
                interval: Some((100.0 * ci[0], 100.0 * ci[1])),
                note: format!("{ok}/{n}"),
            }
        })
        .collect();
    figs.push((
        "success_by_distance.svg",
        plot::bar_chart(
            "Success rate with 95% CI by movement time and distance band",
            "movement time (s), distance band (m)",
            "precisely timed (% of trials)",
            &bars,
            (0.0, 100.0),
        )?,
        "Success rate (Wilson 95% interval) per cell; the paper reached 93% at 0.70 m in 1.5 s.",
    ));
    let all_te: Vec<f64> = cells
        .iter()
        .flat_map(|c| c.trials.iter())
        .map(|v| field(v, "timing_error_ms"))
        .collect();
    figs.push((
        "timing_error_histogram.svg",
        plot::histogram(
            "Timing error |arrival - t*|",
            "|timing error| (ms)",
            &all_te,
            30,
        )?,
        "Timing error of every judged trial.",
    ));
    let series: Vec<Series> = times
        .iter()
        .enumerate()
        .map(|(i, &t)| Series {
            name: format!("planned {t} s"),
            color: plot::COLORS[i % plot::COLORS.len()],
            style: Style::Dots,
            points: cells
                .iter()
                .filter(|c| c.movement_time_s == t)
                .flat_map(|c| c.trials.iter())
                .map(|v| (num(v, &["distance_m"]), field(v, "movement_time_s")))
                .collect(),
        })
        .collect();
    let refs: Vec<(f64, String)> = times.iter().map(|t| (*t, format!("{t} s"))).collect();
    let hl: Vec<(f64, &str)> = refs.iter().map(|(t, s)| (*t, s.as_str())).collect();
    figs.push((
        "isochrony.svg",
        plot::xy_chart(
            "Isochrony: measured movement time against distance",
            "distance (m)",
            "movement time (s)",
            &series,
            &hl,
        )?,
        "Movement time (fit of the ideal profile to the tool's measured progress) against the distance: flat lines are isochrony.",
    ));
    let (d, t) = (0.70, 1.5);
    let prof = |k: ProfileKind| -> Vec<(f64, f64)> {
        (0..=300)
            .map(|i| {
                let tau = f64::from(i) / 300.0;
                (tau * t, k.velocity(tau) * d / t)
            })
            .collect()
    };
    figs.push((
        "profiles.svg",
        plot::xy_chart(
            "Path speed for 0.70 m in 1.5 s: Hopf against minimum jerk",
            "time (s)",
            "path speed (m/s)",
            &[
                Series {
                    name: format!(
                        "Hopf: R_h (1 - cos wt), peak {:.3} m/s",
                        ProfileKind::Hopf.peak_velocity() * d / t
                    ),
                    color: plot::COLORS[0],
                    style: Style::Line,
                    points: prof(ProfileKind::Hopf),
                },
                Series {
                    name: format!(
                        "minimum jerk, peak {:.3} m/s",
                        ProfileKind::MinJerk.peak_velocity() * d / t
                    ),
                    color: plot::COLORS[1],
                    style: Style::Dashed,
                    points: prof(ProfileKind::MinJerk),
                },
            ],
            &[],
        )?,
        "The two velocity profiles of the same duration (the paper's Hopf profile and Flash and Hogan's minimum jerk).",
    ));
    let _ = writeln!(md, "\n## Figures\n");
    for (name, svg_text, caption) in &figs {
        std::fs::write(dir.join(name), svg_text)?;
        let _ = writeln!(md, "![{caption}]({name})\n\n{caption}\n");
    }
    let _ = writeln!(
        md,
        "## Reproduce\n\nEvery truthful-world number above comes from these commands (run in this folder):\n"
    );
    for c in cells {
        let _ = writeln!(md, "    {}", c.command);
    }
    if let Some((r, rows)) = reality {
        super::eval_reality::write_reality(&mut md, dir, r, rows)?;
    }
    let path = dir.join("report.md");
    std::fs::write(&path, md).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn cell(t: f64, band: (f64, f64), outcomes: &[(bool, f64, f64)]) -> Cell {
        Cell {
            movement_time_s: t,
            band_m: band,
            summary: json!({"timing_error_ms": {"p95": 4.0}, "position_error_m": {"p95": 0.006}}),
            trials: outcomes
                .iter()
                .map(|&(ok, d, te)| {
                    json!({"success": ok, "distance_m": d,
                           "failure": if ok { Value::Null } else { json!("timing_error 25.0 ms > 20 ms") },
                           "timing_error_ms": te, "movement_time_s": t + te / 1e3, "planned_movement_time_s": t})
                })
                .collect(),
            command: format!("isochron trials --t {t}"),
        }
    }

    #[test]
    fn the_report_counts_what_the_trials_said() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let cells = [
            cell(1.5, (0.35, 0.55), &[(true, 0.4, 1.0), (true, 0.5, 2.0)]),
            cell(1.5, (0.55, 0.80), &[(true, 0.6, 3.0), (false, 0.79, 25.0)]),
        ];
        let path = write_report(dir, &Scenario::default(), &cells, 7, None).unwrap();
        let md = std::fs::read_to_string(path).unwrap();
        assert!(
            md.contains("| isochron (simulated) | 1.5 s | 0.35..0.80 m | 4 | 75.0% |"),
            "{md}"
        );
        assert!(
            md.contains("| 1.5 s | 0.55..0.80 m | 2 | 1 | 50.0% |"),
            "{md}"
        );
        assert!(md.contains("timing_error 25.0 ms"));
        assert!(md.contains("93%"));
        for f in [
            "success_by_distance.svg",
            "timing_error_histogram.svg",
            "isochrony.svg",
            "profiles.svg",
        ] {
            let svg = std::fs::read_to_string(dir.join(f)).unwrap();
            assert!(svg.starts_with("<svg"), "{f}");
            assert!(md.contains(f));
        }
    }

    #[test]
    fn bad_arguments_are_refused() {
        let ok = EvalArgs {
            scenario: None,
            out: "x".into(),
            n: 3,
            seed: 1,
            movement_times_s: vec![1.5],
            distance_edges_m: vec![0.35, 0.8],
            reality: None,
            envelope: super::super::eval_envelope::EnvelopeArgs::default(),
        };
        assert!(check_args(&ok).is_ok());
        let bad = [
            EvalArgs { n: 0, ..clone(&ok) },
            EvalArgs {
                movement_times_s: vec![f64::NAN],
                ..clone(&ok)
            },
            EvalArgs {
                distance_edges_m: vec![0.8, 0.35],
                ..clone(&ok)
            },
            EvalArgs {
                distance_edges_m: vec![0.35],
                ..clone(&ok)
            },
        ];
        for b in bad {
            assert!(check_args(&b).is_err());
        }
    }

    fn clone(a: &EvalArgs) -> EvalArgs {
        EvalArgs {
            scenario: a.scenario.clone(),
            out: a.out.clone(),
            n: a.n,
            seed: a.seed,
            movement_times_s: a.movement_times_s.clone(),
            distance_edges_m: a.distance_edges_m.clone(),
            reality: a.reality.clone(),
            envelope: a.envelope.clone(),
        }
    }
}
