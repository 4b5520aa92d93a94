//! `isochron eval --envelope` as a user runs it: one shard of many on a small
//! lab (the reality lab with the model camera, 4 trials a step, multiples up to
//! 2, one halving), then `--combine`; and its refusals of bad arguments.

use std::path::Path;

use rt_core::params::{Scenario, VisionMode};
use serde_json::Value;

use crate::isochron;

/// The reality lab with the model camera (no rendering): cheap trials.
fn small_lab(dir: &Path) -> std::path::PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    let mut s = Scenario::from_file(&path).unwrap();
    s.name = "small".into();
    s.camera.vision = VisionMode::Model;
    let file = dir.join("small.toml");
    std::fs::write(&file, s.to_toml_string()).unwrap();
    file
}

#[test]
fn one_shard_of_the_envelope_writes_its_file_and_the_report() {
    let tmp = tempfile::tempdir().unwrap();
    let lab = small_lab(tmp.path());
    let out = tmp.path().join("out");
    // Shard 23 of 24: the last items (the last factor, then all together).
    let run = isochron()
        .args(["eval", "--envelope", "--reality"])
        .arg(&lab)
        .arg("--out")
        .arg(&out)
        .args([
            "--n",
            "4",
            "--seed",
            "3",
            "--max-multiple",
            "2",
            "--steps",
            "1",
        ])
        .args(["--shard", "23/24"])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let shard_file = out.join("envelope/shard-23-of-24.json");
    let shard: Value =
        serde_json::from_str(&std::fs::read_to_string(&shard_file).unwrap()).unwrap();
    let items: Vec<&str> = shard["run"]["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    let results = shard["results"].as_array().unwrap();
    let names: Vec<&str> = results
        .iter()
        .map(|r| r["name"].as_str().unwrap())
        .collect();
    // This shard's slice of the items: index 23 * len / 24 to the end.
    assert_eq!(names, items[23 * items.len() / 24..].to_vec());
    assert_eq!(names.last(), Some(&"all factors together"));
    for r in results {
        let steps = r["steps"].as_array().unwrap();
        // 1x, then 2x (passing: stop) or 2x and one halving (1.5x).
        assert!(matches!(steps.len(), 1..=3), "{r}");
        assert_eq!(steps[0]["k"], 1.0);
        for s in steps {
            assert_eq!(s["trials"], 4, "{s}");
            let cmd = s["command"].as_str().unwrap();
            let cell = cmd.split_whitespace().nth(3).unwrap();
            assert!(out.join(cell).exists(), "{cmd}");
            assert!(cmd.ends_with("--n 4 --seed 3 --json"), "{cmd}");
        }
        let kind = r["outcome"]["kind"].as_str().unwrap();
        assert!(
            ["fails_at_one", "passes_at_max", "bracket"].contains(&kind),
            "{r}"
        );
    }
    // The report: a row per item, this shard's filled in, the others missing.
    let md = std::fs::read_to_string(out.join("envelope.md")).unwrap();
    assert!(
        md.contains("## Robustness envelope (reality-lab figures)"),
        "{md}"
    );
    assert!(md.contains("Camera vision mode: **model"), "{md}");
    assert!(md.contains("**4 trials per step, seed 3**"), "{md}");
    for (i, name) in items.iter().enumerate() {
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| {name} |")))
            .unwrap_or_else(|| panic!("no row for {name}: {md}"));
        assert_eq!(
            row.contains("not run: shard"),
            !names.contains(name),
            "{row}"
        );
        if i == 0 {
            assert!(row.contains("not run: shard 0/24 missing"), "{row}");
        }
    }
    assert!(
        std::fs::read_to_string(out.join("envelope.svg"))
            .unwrap()
            .starts_with("<svg")
    );
    // --combine rewrites the report from the shard files alone.
    std::fs::remove_file(out.join("envelope.md")).unwrap();
    let combine = isochron()
        .args(["eval", "--envelope", "--combine", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        combine.status.success(),
        "{}",
        String::from_utf8_lossy(&combine.stderr)
    );
    assert_eq!(
        std::fs::read_to_string(out.join("envelope.md")).unwrap(),
        md
    );
}

#[test]
fn bad_envelope_arguments_get_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let lab = small_lab(tmp.path());
    let paper = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
    let out = tmp.path().join("out");
    let cases: [(Vec<&str>, &Path, &str); 6] = [
        (vec!["--n", "0"], &lab, "--n = 0"),
        (vec!["--max-multiple", "0.5"], &lab, "--max-multiple"),
        (vec!["--max-multiple", "NaN"], &lab, "--max-multiple"),
        (vec!["--shard", "3/3"], &lab, "--shard"),
        (vec!["--shard", "0/1000"], &lab, "--shard 0/1000"),
        (vec![], &paper, "no [world]"),
    ];
    for (extra, reality, says) in cases {
        let o = isochron()
            .args(["eval", "--envelope", "--reality"])
            .arg(reality)
            .arg("--out")
            .arg(&out)
            .args(&extra)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{extra:?}");
        assert!(err.contains(says), "{extra:?}: {err}");
    }
    // The envelope's options without --envelope are refused.
    let o = isochron()
        .args(["eval", "--max-multiple", "3"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--envelope"));
    assert!(!out.join("cells").exists(), "a refused run ran trials");
}
