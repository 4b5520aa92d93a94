//! `isochron trials --shard I/N` and `isochron merge` as a cluster runs them:
//! each shard is its own process (as one pod of a Kubernetes Indexed Job or one
//! task of a Slurm array), and merging their JSON gives the summary the
//! unsharded run prints, field for field (all but the wall time). A missing,
//! doubled or foreign shard is refused with a one-line error.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

fn isochron() -> Option<PathBuf> {
    isochron_tests::isochron_bin(&[(&["merge", "--help"], "shard")])
}

fn run(bin: &Path, args: &[&str]) -> Output {
    Command::new(bin)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("isochron {args:?}: {e}"))
}

fn json(out: &Output, what: &str) -> Value {
    assert!(
        out.status.success(),
        "{what} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{what}: {e}"))
}

/// A directory of this test's own, removed at the end.
struct TempDir(PathBuf);

impl TempDir {
    fn new() -> Self {
        let d = std::env::temp_dir().join(format!("isochron-shards-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        Self(d)
    }

    fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The summary without the figures that measure the machine rather than the
/// trials (wall time, and control steps over the period by CPU or wall clock):
/// two unsharded runs differ in them too.
fn comparable(mut v: Value) -> Value {
    for k in ["wall_s", "deadline_misses", "preempted_steps"] {
        v.as_object_mut().unwrap().remove(k);
    }
    v
}

#[test]
fn shards_run_as_separate_processes_merge_into_the_unsharded_summary() {
    let Some(bin) = isochron() else { return };
    let dir = TempDir::new();
    let scenario = dir.path().join("lab.toml");
    std::fs::write(
        &scenario,
        "name = \"shards\"\n[camera]\nvision = \"model\"\n",
    )
    .unwrap();
    let sc = scenario.to_str().unwrap();
    let common = [
        "trials",
        "--scenario",
        sc,
        "--n",
        "7",
        "--seed",
        "5",
        "--block",
        "2",
        "--json",
    ];

    let whole = json(&run(&bin, &common), "the unsharded run");
    assert_eq!(whole["trials"], 7);

    // Four days (2+2+2+1 trials) over three shards, all running at once, each
    // started by deploy/run-shard.sh with its index as a Kubernetes Indexed Job,
    // a Slurm array or a person passes it.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/run-shard.sh");
    let out_dir = dir.path().join("results");
    let index_vars = ["JOB_COMPLETION_INDEX", "SLURM_ARRAY_TASK_ID", "SHARD_INDEX"];
    let children: Vec<_> = index_vars
        .iter()
        .enumerate()
        .map(|(i, var)| {
            Command::new("sh")
                .arg(&script)
                .env_remove("JOB_COMPLETION_INDEX")
                .env_remove("SLURM_ARRAY_TASK_ID")
                .env_remove("SHARD_INDEX")
                .env(var, i.to_string())
                .env("SHARD_COUNT", "3")
                .env("SCENARIO", sc)
                .env("N", "7")
                .env("SEED", "5")
                .env("BLOCK", "2")
                .env("OUT_DIR", &out_dir)
                .env("ISOCHRON", &bin)
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut files = Vec::new();
    let mut held = 0;
    for (i, c) in children.into_iter().enumerate() {
        let c = c.wait_with_output().unwrap();
        assert!(
            c.status.success(),
            "run-shard.sh {}={i}: {}",
            index_vars[i],
            String::from_utf8_lossy(&c.stderr)
        );
        let f = out_dir.join(format!("shard-{i}.json"));
        let v: Value = serde_json::from_str(&std::fs::read_to_string(&f).unwrap()).unwrap();
        assert_eq!(v["shard"]["index"], i);
        held += v["records"].as_array().unwrap().len();
        files.push(f.to_str().unwrap().to_owned());
    }
    assert_eq!(held, 7, "the shards are disjoint and cover the run");

    // Any order of the files.
    let merged = json(
        &run(&bin, &["merge", &files[2], &files[0], &files[1]]),
        "merge",
    );
    assert_eq!(comparable(merged), comparable(whole));

    // A missing shard, a doubled one, a shard of another run: refused, nothing printed.
    let refused = |args: &[&str], needle: &str| {
        let out = run(&bin, args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && out.stdout.is_empty(), "{args:?}");
        assert!(err.contains(needle), "{args:?}: {err}");
    };
    refused(&["merge", &files[0], &files[1]], "exactly once");
    refused(&["merge", &files[0], &files[0], &files[1]], "exactly once");
    let other = json(
        &run(
            &bin,
            &[
                "trials",
                "--scenario",
                sc,
                "--n",
                "7",
                "--seed",
                "6",
                "--block",
                "2",
                "--json",
                "--shard",
                "2/3",
            ],
        ),
        "a shard of another seed",
    );
    let f = dir.path().join("other.json");
    std::fs::write(&f, serde_json::to_string(&other).unwrap()).unwrap();
    refused(
        &["merge", &files[0], &files[1], f.to_str().unwrap()],
        "another run",
    );
    let whole_file = dir.path().join("whole.json");
    std::fs::write(&whole_file, "{\"trials\": 7}").unwrap();
    refused(&["merge", whole_file.to_str().unwrap()], "no \"shard\"");
    // More shards than lab days.
    refused(
        &[
            "trials",
            "--scenario",
            sc,
            "--n",
            "7",
            "--block",
            "2",
            "--shard",
            "0/5",
        ],
        "4 lab days",
    );
}
