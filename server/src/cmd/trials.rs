//! `isochron trials --scenario FILE --n N [--seed S] [--json] [--per-trial FILE.jsonl]`:
//! N closed-loop trials of a scenario in virtual time (CONTRACT.md).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rt_core::control::{Summary, TrialRecord};
use rt_core::lab::VirtualLab;
use rt_core::params::Scenario;

/// Largest number of trials one run accepts.
const MAX_TRIALS: usize = 1_000_000;

/// Arguments of `isochron trials`.
#[derive(Debug, clap::Args)]
pub struct TrialsArgs {
    /// The scenario (TOML), e.g. scenarios/paper.toml.
    #[arg(long)]
    pub scenario: PathBuf,
    /// Number of trials.
    #[arg(long)]
    pub n: usize,
    /// Seed: distances, release angles and every random draw follow from it.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Print the summary as one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Write one JSON line per trial (numbers and failure reason) to this file.
    #[arg(long)]
    pub per_trial: Option<PathBuf>,
    /// A parameter file laid over the scenario (a partial scenario, e.g. the [ekf] file
    /// `isochron tune` writes); repeat to lay several in order.
    #[arg(long)]
    pub params: Vec<PathBuf>,
    /// A calibration file (`isochron calibrate` writes it) laid over the scenario's
    /// beliefs after the parameter files: pendulum length and damping, camera latency,
    /// the robot latency prior.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
}

/// Runs the trials; returns the text for stdout.
pub fn run(args: &TrialsArgs) -> anyhow::Result<String> {
    if args.n == 0 || args.n > MAX_TRIALS {
        anyhow::bail!("--n = {} is out of range: must be 1..={MAX_TRIALS}", args.n);
    }
    let mut scenario = Scenario::from_file(&args.scenario)?;
    for p in &args.params {
        scenario = rt_core::tuning::overlay_params_file(&scenario, p)?;
    }
    if let Some(c) = &args.calibration {
        scenario = rt_core::calibration::CalibrationFile::from_file(c)?.apply(&scenario)?;
    }
    let mut per_trial = match &args.per_trial {
        Some(p) => Some(BufWriter::new(
            File::create(p).with_context(|| format!("cannot create {}", p.display()))?,
        )),
        None => None,
    };
    let started = Instant::now();
    let mut lab = VirtualLab::new(&scenario, args.seed)?;
    if scenario.camera.vision == rt_core::params::VisionMode::Full && lab.vision_used() != "full" {
        eprintln!(
            "isochron trials: camera.vision = \"full\" is not wired into the simulated lab yet; \
             using the measurement model (\"vision\": \"{}\" in the summary)",
            lab.vision_used()
        );
    }
    let bar =
        ProgressBar::with_draw_target(Some(args.n as u64), ProgressDrawTarget::stderr_with_hz(5));
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} trials {pos}/{len} [{bar:30}] {msg} ({elapsed}, eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let mut records: Vec<TrialRecord> = Vec::with_capacity(args.n);
    let mut successes = 0usize;
    let mut ekf_counters = rt_core::ekf::EkfCounters::default();
    for i in 0..args.n {
        let r = lab.run_trial(i);
        successes += usize::from(r.success);
        if let Some(c) = lab.controller().ekf().map(rt_core::ekf::Ekf::counters) {
            ekf_counters.fused += c.fused;
            ekf_counters.rejected += c.rejected;
            ekf_counters.reinitialisations += c.reinitialisations;
        }
        if let Some(w) = per_trial.as_mut() {
            serde_json::to_writer(&mut *w, &r)?;
            w.write_all(b"\n")?;
        }
        records.push(r);
        bar.set_message(format!("{successes} hits"));
        bar.inc(1);
    }
    bar.finish_and_clear();
    if let Some(mut w) = per_trial {
        w.flush()?;
    }
    let wall_s = started.elapsed().as_secs_f64();
    // Virtual time simulated (the lab's clock starts at 0), against the wall clock.
    eprintln!(
        "isochron trials: {:.0} s of lab time in {wall_s:.1} s of wall time ({:.0}x real time)",
        lab.t_s(),
        lab.t_s() / wall_s.max(1e-9)
    );
    let mut summary = Summary::of(&scenario.name, &records, wall_s);
    summary.vision = Some(lab.vision_used().to_owned());
    if args.json {
        let mut v = serde_json::to_value(&summary)?;
        // The filter the trials ran with (read back from the controller) and what it did.
        if let Some(ekf) = lab.controller().ekf() {
            v["ekf"] = serde_json::to_value(ekf.params())?;
            v["ekf_counters"] = serde_json::json!({
                "fused": ekf_counters.fused,
                "rejected": ekf_counters.rejected,
                "reinitialisations": ekf_counters.reinitialisations,
            });
        }
        return Ok(serde_json::to_string(&v)?);
    }
    Ok(human(&summary))
}

fn human(s: &Summary) -> String {
    format!(
        "{}: {}/{} successes ({:.1}%, 95% CI {:.1}..{:.1}%)\n\
         timing error   p50 {:.2} ms, p95 {:.2} ms, max {:.2} ms\n\
         position error p50 {:.4} m, p95 {:.4} m, max {:.4} m\n\
         movement time  mean {:.4} s, std {:.5} s ({:.4}..{:.4})\n\
         distance       {:.3}..{:.3} m\n\
         aborted {}, limit violations {}, deadline misses {}, wall {:.1} s, vision {}",
        s.scenario,
        s.successes,
        s.trials,
        100.0 * s.success_rate,
        100.0 * s.success_ci95[0],
        100.0 * s.success_ci95[1],
        s.timing_error_ms.p50,
        s.timing_error_ms.p95,
        s.timing_error_ms.max,
        s.position_error_m.p50,
        s.position_error_m.p95,
        s.position_error_m.max,
        s.movement_time_s.mean,
        s.movement_time_s.std,
        s.movement_time_s.min,
        s.movement_time_s.max,
        s.distance_m.min,
        s.distance_m.max,
        s.aborted,
        s.limit_violations,
        s.deadline_misses,
        s.wall_s,
        s.vision.as_deref().unwrap_or("?"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(n: usize, per_trial: Option<PathBuf>) -> TrialsArgs {
        // One directory per call: the tests run in parallel and must not read
        // each other's half-written scenario.
        static CALLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let k = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("isochron-trials-{}-{k}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scenario = dir.join("model.toml");
        std::fs::write(
            &scenario,
            "name = \"model\"\n[camera]\nvision = \"model\"\n",
        )
        .unwrap();
        TrialsArgs {
            scenario,
            n,
            seed: 1,
            json: true,
            per_trial,
            params: Vec::new(),
            calibration: None,
        }
    }

    #[test]
    fn the_json_summary_and_per_trial_lines_follow_the_contract() {
        let lines =
            std::env::temp_dir().join(format!("isochron-trials-{}.jsonl", std::process::id()));
        let out = run(&args(2, Some(lines.clone()))).unwrap();
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(v["scenario"], "model");
        assert_eq!(v["trials"], 2);
        for key in [
            "success_rate",
            "success_ci95",
            "timing_error_ms",
            "movement_time_s",
            "wall_s",
        ] {
            assert!(v.get(key).is_some(), "{key}");
        }
        let text = std::fs::read_to_string(&lines).unwrap();
        let per: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(per.len(), 2);
        assert!(per[0]["distance_m"].is_number() && per[0].get("failure").is_some());
    }

    #[test]
    fn bad_arguments_are_refused() {
        assert!(run(&args(0, None)).unwrap_err().to_string().contains("--n"));
        let mut a = args(1, None);
        a.scenario = PathBuf::from("/nonexistent/s.toml");
        assert!(
            run(&a)
                .unwrap_err()
                .to_string()
                .contains("/nonexistent/s.toml")
        );
    }
}
