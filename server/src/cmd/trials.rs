//! `isochron trials --scenario FILE --n N [--seed S] [--json] [--per-trial FILE.jsonl]
//! [--shard I/N] [--block B]`: N closed-loop trials of a scenario in virtual time
//! (CONTRACT.md).
//!
//! A run is cut into *lab days* of `--block` trials: each day a freshly started
//! lab (a new simulated robot session, a new controller, as after restarting
//! `isochron serve`) runs its trials, whose draws follow from the seed and the
//! trial's index alone. So a day's outcomes do not depend on the days before it,
//! and `--shard I/N` (the I-th of N contiguous runs of whole days, I from 0) gives
//! exactly the trials the unsharded run gives for the same indices; `isochron
//! merge` ([`super::merge`]) puts the shards' `--json` outputs back together.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rt_core::control::{Summary, TrialRecord};
use rt_core::params::Scenario;
use rt_core::sim::VirtualLab;

/// Largest number of trials one run accepts.
const MAX_TRIALS: usize = 1_000_000;

/// Trials one freshly started lab runs (one lab day), unless `--block` says otherwise.
pub const DEFAULT_BLOCK: usize = 100;

/// Most shards one run may be cut into.
const MAX_SHARDS: usize = 100_000;

/// `--shard I/N`: the I-th (from 0) of N slices of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// Which slice, `0..count`.
    pub index: usize,
    /// How many slices.
    pub count: usize,
}

impl std::str::FromStr for Shard {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || format!("`{s}` is not I/N with 0 <= I < N <= {MAX_SHARDS} (e.g. 0/4)");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let index: usize = i.trim().parse().map_err(|_| bad())?;
        let count: usize = n.trim().parse().map_err(|_| bad())?;
        if count == 0 || count > MAX_SHARDS || index >= count {
            return Err(bad());
        }
        Ok(Self { index, count })
    }
}

/// The trial indices `lo..hi` shard `shard` runs of `n` trials in days of `block`:
/// days `index * days / count .. (index + 1) * days / count`.
pub fn shard_range(n: usize, block: usize, shard: Shard) -> std::ops::Range<usize> {
    let days = n.div_ceil(block);
    let first = shard.index * days / shard.count;
    let end = (shard.index + 1) * days / shard.count;
    (first * block).min(n)..(end * block).min(n)
}

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
    /// Run only the I-th of N slices (I from 0, e.g. `--shard 3/8`): whole lab days,
    /// contiguous; with `--json` the output also holds the slice's per-trial records
    /// for `isochron merge`.
    #[arg(long)]
    pub shard: Option<Shard>,
    /// Trials per lab day: each day a freshly started lab runs this many trials.
    #[arg(long, default_value_t = DEFAULT_BLOCK)]
    pub block: usize,
}

/// Runs the trials; returns the text for stdout.
pub fn run(args: &TrialsArgs) -> anyhow::Result<String> {
    if args.n == 0 || args.n > MAX_TRIALS {
        anyhow::bail!("--n = {} is out of range: must be 1..={MAX_TRIALS}", args.n);
    }
    if args.block == 0 || args.block > MAX_TRIALS {
        anyhow::bail!(
            "--block = {} is out of range: must be 1..={MAX_TRIALS}",
            args.block
        );
    }
    let days = args.n.div_ceil(args.block);
    if let Some(sh) = args.shard
        && sh.count > days
    {
        anyhow::bail!(
            "--shard {}/{}: {} trials in days of {} make {days} lab days, fewer than {} shards \
             (use --shard I/{days} or fewer, or a smaller --block)",
            sh.index,
            sh.count,
            args.n,
            args.block,
            sh.count
        );
    }
    let range = shard_range(
        args.n,
        args.block,
        args.shard.unwrap_or(Shard { index: 0, count: 1 }),
    );
    let mut scenario = Scenario::from_file(&args.scenario)?;
    for p in &args.params {
        scenario = rt_core::tuning::overlay_params_file(&scenario, p)?;
    }
    if let Some(c) = &args.calibration {
        scenario = rt_core::calibration::CalibrationFile::from_file(c)?.apply(&scenario)?;
    }
    if scenario.world.is_some() && scenario.control.arrival_settle_m <= 0.0 {
        // A world's trials are judged by its physical judge, whose arrival
        // is the true tool settling within 2 mm; timed for the ideal
        // profile's end instead, the arm settles 137 ms early at 1.5 s.
        scenario.control.arrival_settle_m = rt_core::control::measured::ARRIVAL_SETTLE_M;
        eprintln!(
            "isochron trials: the scenario has a [world], judged by the tool settling within \
             {:.0} mm: control.arrival_settle_m = {} (the file's 0 times the ideal profile's end)",
            rt_core::control::measured::ARRIVAL_SETTLE_M * 1e3,
            rt_core::control::measured::ARRIVAL_SETTLE_M
        );
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
    let bar = ProgressBar::with_draw_target(
        Some(range.len() as u64),
        ProgressDrawTarget::stderr_with_hz(5),
    );
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} trials {pos}/{len} [{bar:30}] {msg} ({elapsed}, eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let mut records: Vec<TrialRecord> = Vec::with_capacity(range.len());
    let mut successes = 0usize;
    let mut ekf_counters = rt_core::ekf::EkfCounters::default();
    // Lab time of the days already run (each lab's clock starts at 0).
    let mut lab_time_s = 0.0;
    for i in range.clone() {
        if i % args.block == 0 && i != range.start {
            // A new lab day: a freshly started lab, as after a restart.
            lab_time_s += lab.t_s();
            lab = VirtualLab::new(&scenario, args.seed)?;
        }
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
    lab_time_s += lab.t_s();
    eprintln!(
        "isochron trials: {lab_time_s:.0} s of lab time in {wall_s:.1} s of wall time ({:.0}x real time)",
        lab_time_s / wall_s.max(1e-9)
    );
    let mut summary = Summary::of(&scenario.name, &records, wall_s);
    summary.vision = Some(lab.vision_used().to_owned());
    if args.json {
        // The filter the trials ran with (read back from the controller) and what it did.
        let ekf = match lab.controller().ekf() {
            Some(ekf) => Some((serde_json::to_value(ekf.params())?, ekf_counters)),
            None => None,
        };
        let mut v = summary_json(&summary, ekf)?;
        if let Some(sh) = args.shard {
            v["shard"] = serde_json::to_value(ShardInfo {
                index: sh.index,
                count: sh.count,
                n: args.n,
                block: args.block,
                seed: args.seed,
            })?;
            v["records"] = serde_json::to_value(&records)?;
        }
        return Ok(serde_json::to_string(&v)?);
    }
    Ok(human(&summary))
}

/// What a shard's `--json` output says of the run it is a slice of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ShardInfo {
    /// Which slice, from 0.
    pub index: usize,
    /// How many slices.
    pub count: usize,
    /// Trials in the whole run.
    pub n: usize,
    /// Trials per lab day.
    pub block: usize,
    /// The run's seed.
    pub seed: u64,
}

/// The `--json` summary object (CONTRACT.md): the summary, and the filter's
/// parameters and counters when the controller ran one.
pub fn summary_json(
    summary: &Summary,
    ekf: Option<(serde_json::Value, rt_core::ekf::EkfCounters)>,
) -> anyhow::Result<serde_json::Value> {
    let mut v = serde_json::to_value(summary)?;
    if let Some((params, c)) = ekf {
        v["ekf"] = params;
        v["ekf_counters"] = serde_json::json!({
            "fused": c.fused,
            "rejected": c.rejected,
            "reinitialisations": c.reinitialisations,
        });
    }
    Ok(v)
}

fn human(s: &Summary) -> String {
    let strike = s.strike.map_or_else(String::new, |k| {
        format!(
            "\nstrike         contact in time {}/{} ({:.1}%), outgoing speed within 20% {}/{} ({:.1}%), \
             |speed error| p50 {:.1}%, p95 {:.1}%, tool speed at contact p50 {:.3} m/s, \
             refused as infeasible {}{}",
            k.contact_in_time,
            k.trials,
            100.0 * k.contact_in_time_rate,
            k.speed_within_tolerance,
            k.trials,
            100.0 * k.speed_within_tolerance_rate,
            100.0 * k.speed_error.p50,
            100.0 * k.speed_error.p95,
            k.tool_speed_mps.p50,
            k.refused,
            k.predicted_error.map_or_else(String::new, |p| format!(
                ", outgoing speed against the predicted rebound |error| p50 {:.1}%, p95 {:.1}%",
                100.0 * p.p50,
                100.0 * p.p95
            )),
        )
    });
    let summary = format!(
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
    );
    let measured = s.measured.map_or_else(String::new, |m| {
        let speed = m.strike.map_or_else(String::new, |k| {
            format!(
                ", strike speed ok agrees {}/{}, outgoing speed - true mean {:+.1}% of the target \
                 (|.| p50 {:.1}%, p95 {:.1}%)",
                k.speed_ok_agree,
                k.trials,
                100.0 * k.speed_difference_mean,
                100.0 * k.speed_difference.p50,
                100.0 * k.speed_difference.p95,
            )
        });
        format!(
            "\nmeasured judge agrees with the physical one {}/{}, |timing difference| p50 {:.2} ms, \
             p95 {:.2} ms, contact seen in {}/{} hits, claimed in {}/{} misses{speed}",
            m.agree,
            m.trials,
            m.timing_difference_ms.p50,
            m.timing_difference_ms.p95,
            m.contact_in_hits,
            m.hits,
            m.contact_in_misses,
            m.misses,
        )
    });
    summary + &strike + &measured
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(n: usize, per_trial: Option<PathBuf>) -> TrialsArgs {
        // One directory per call: the tests run in parallel and must not read
        // each other's half-written scenario.
        let dir = tempfile::Builder::new()
            .prefix("isochron-trials-")
            .tempdir()
            .expect("a temporary directory")
            .keep();
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
            shard: None,
            block: DEFAULT_BLOCK,
        }
    }

    #[test]
    fn the_json_summary_and_per_trial_lines_follow_the_contract() {
        let tmp = tempfile::tempdir().unwrap();
        let lines = tmp.path().join("trials.jsonl");
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
    fn shards_are_disjoint_runs_of_whole_days_covering_the_run() {
        for (n, block, count) in [(10, 3, 4), (7, 100, 1), (1000, 100, 7), (5, 1, 5)] {
            let mut next = 0;
            for index in 0..count {
                let r = shard_range(n, block, Shard { index, count });
                assert_eq!(r.start, next, "n {n} block {block} shard {index}/{count}");
                assert!(r.start % block == 0 || r.is_empty());
                next = r.end;
            }
            assert_eq!(next, n);
        }
        assert_eq!("3/8".parse::<Shard>(), Ok(Shard { index: 3, count: 8 }));
        for bad in ["8/8", "1", "-1/2", "a/b", "0/0", "1/2/3", ""] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
    }

    #[test]
    fn bad_arguments_are_refused() {
        let mut a = args(4, None);
        a.block = 2;
        a.shard = Some(Shard { index: 0, count: 3 });
        let e = run(&a).unwrap_err().to_string();
        assert!(e.contains("--shard 0/3") && e.contains("2 lab days"), "{e}");
        let mut a = args(4, None);
        a.block = 0;
        assert!(run(&a).unwrap_err().to_string().contains("--block"));
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
