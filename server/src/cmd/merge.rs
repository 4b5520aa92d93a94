//! `isochron merge FILE...`: puts the `--json` outputs of `isochron trials
//! --shard I/N` back together into the summary the unsharded run prints
//! (CONTRACT.md). Every number is recomputed from the shards' per-trial records,
//! so the merged summary equals the unsharded one; only the figures that measure
//! the machine rather than the trials differ (`wall_s`, `deadline_misses`,
//! `preempted_steps`: sums over the shards, as two unsharded runs differ in them too).

use std::path::PathBuf;

use anyhow::{Context, bail};
use rt_core::control::{Summary, TrialRecord};
use rt_core::ekf::EkfCounters;
use serde_json::Value;

use super::trials::{Shard, ShardInfo, shard_range, summary_json};

/// Largest shard output `merge` reads, bytes (a 1000-trial shard is ~1 MB).
const MAX_FILE_BYTES: u64 = 1 << 30;

/// Arguments of `isochron merge`.
#[derive(Debug, clap::Args)]
pub struct MergeArgs {
    /// The shards' `isochron trials --shard I/N --json` outputs, one file each, any order.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
}

/// One shard's output, read and checked.
struct Part {
    file: PathBuf,
    shard: ShardInfo,
    value: Value,
    records: Vec<TrialRecord>,
}

fn read_part(file: &PathBuf) -> anyhow::Result<Part> {
    let len = std::fs::metadata(file)
        .with_context(|| format!("cannot read {}", file.display()))?
        .len();
    if len > MAX_FILE_BYTES {
        bail!(
            "{}: {len} bytes is more than {MAX_FILE_BYTES}",
            file.display()
        );
    }
    let text =
        std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let mut value: Value = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a JSON summary", file.display()))?;
    let shard: ShardInfo =
        serde_json::from_value(value.get("shard").cloned().with_context(|| {
            format!(
                "{}: no \"shard\" object (write it with isochron trials --shard I/N --json)",
                file.display()
            )
        })?)
        .with_context(|| format!("{}: bad \"shard\" object", file.display()))?;
    let records: Vec<TrialRecord> = serde_json::from_value(
        value
            .get_mut("records")
            .map(Value::take)
            .with_context(|| format!("{}: no \"records\"", file.display()))?,
    )
    .with_context(|| format!("{}: bad \"records\"", file.display()))?;
    Ok(Part {
        file: file.clone(),
        shard,
        value,
        records,
    })
}

/// Merges the shards; returns the merged summary as one JSON line.
pub fn run(args: &MergeArgs) -> anyhow::Result<String> {
    let mut parts = args
        .files
        .iter()
        .map(read_part)
        .collect::<anyhow::Result<Vec<_>>>()?;
    parts.sort_by_key(|p| p.shard.index);
    let first = Part {
        records: Vec::new(),
        file: parts[0].file.clone(),
        shard: parts[0].shard,
        value: parts[0].value.clone(),
    };
    let run = ShardInfo {
        index: 0,
        ..first.shard
    };
    let name = first.value["scenario"].clone();
    for p in &parts {
        let same = ShardInfo {
            index: 0,
            ..p.shard
        } == run;
        if !same || p.value["scenario"] != name {
            bail!(
                "{} is a shard of another run ({}, {}/{} of n {} seed {} block {}) than {} ({}, n {} seed {} block {})",
                p.file.display(),
                p.value["scenario"],
                p.shard.index,
                p.shard.count,
                p.shard.n,
                p.shard.seed,
                p.shard.block,
                first.file.display(),
                name,
                run.n,
                run.seed,
                run.block
            );
        }
        for key in ["ekf", "vision"] {
            if p.value.get(key) != first.value.get(key) {
                bail!(
                    "{} ran with another {key} than {}",
                    p.file.display(),
                    first.file.display()
                );
            }
        }
    }
    let indices: Vec<usize> = parts.iter().map(|p| p.shard.index).collect();
    if indices != (0..run.count).collect::<Vec<_>>() {
        bail!(
            "the shards given are {indices:?} of {}: each of 0..{} exactly once is needed",
            run.count,
            run.count
        );
    }
    let mut records = Vec::with_capacity(run.n);
    let mut wall_s = 0.0;
    let mut counters = EkfCounters::default();
    for p in &mut parts {
        let shard = Shard {
            index: p.shard.index,
            count: p.shard.count,
        };
        let want = shard_range(run.n, run.block, shard);
        let got: Vec<usize> = p.records.iter().map(|r| r.trial).collect();
        if got != want.clone().collect::<Vec<_>>() {
            bail!(
                "{}: shard {}/{} should hold trials {}..{}, holds {} records",
                p.file.display(),
                p.shard.index,
                p.shard.count,
                want.start,
                want.end,
                got.len()
            );
        }
        wall_s += p.value["wall_s"].as_f64().unwrap_or(0.0);
        if let Some(c) = p.value.get("ekf_counters") {
            let n = |k: &str| c[k].as_u64().unwrap_or(0);
            counters.fused += n("fused");
            counters.rejected += n("rejected");
            counters.reinitialisations += n("reinitialisations");
        }
        records.append(&mut p.records);
    }
    let name = name.as_str().context("the shards name no scenario")?;
    let mut summary = Summary::of(name, &records, wall_s);
    summary.vision = first.value["vision"].as_str().map(str::to_owned);
    let ekf = first.value.get("ekf").map(|e| (e.clone(), counters));
    Ok(serde_json::to_string(&summary_json(&summary, ekf)?)?)
}
