//! `isochron eval`'s report says exactly what `isochron trials` says for the same
//! scenario and seed: a small evaluation (model camera, 2 movement times x 2
//! distance bands x 4 trials) is run with the binary, then every command line the
//! report lists under "Reproduce" is run again on its own and its numbers are
//! compared with the report's rows.

use std::{
    path::{Path, PathBuf},
    process::Command,
};

use serde_json::Value;

/// The `isochron` binary with `eval`.
fn isochron() -> Option<PathBuf> {
    isochron_tests::isochron_bin(&[(&["eval", "--help"], "")])
}

fn run_json(bin: &Path, dir: &Path, args: &[&str]) -> Value {
    let out = Command::new(bin)
        .current_dir(dir)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "isochron {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// The cells of a Markdown table row.
fn cells(row: &str) -> Vec<String> {
    row.trim()
        .trim_matches('|')
        .split('|')
        .map(|c| c.trim().to_owned())
        .collect()
}

/// Per trial, what the report is made of (other fields, such as deadline misses
/// and step costs, depend on the machine's wall clock).
fn per_trial(text: &str) -> Vec<Value> {
    const KEYS: [&str; 9] = [
        "success",
        "failure",
        "distance_m",
        "release_angle_deg",
        "planned_movement_time_s",
        "timing_error_ms",
        "position_error_m",
        "movement_time_s",
        "t_star_s",
    ];
    text.lines()
        .map(|l| {
            let v: Value = serde_json::from_str(l).unwrap();
            let flat = |k: &str| match v.get(k) {
                Some(x) if !x.is_null() => x.clone(),
                _ => v["judgement"][k].clone(),
            };
            KEYS.iter().map(|k| (k.to_string(), flat(k))).collect()
        })
        .collect()
}

#[test]
fn the_reports_numbers_are_what_isochron_trials_prints_for_the_same_seeds() {
    let Some(bin) = isochron() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let lab = dir.join("lab.toml");
    std::fs::write(&lab, "name = \"evalcheck\"\n[camera]\nvision = \"model\"\n").unwrap();
    let out = Command::new(&bin)
        .arg("eval")
        .arg("--scenario")
        .arg(&lab)
        .arg("--out")
        .arg(dir)
        .args([
            "--n",
            "4",
            "--seed",
            "5",
            "--movement-times-s",
            "1.2,1.5",
            "--distance-edges-m",
            "0.35,0.6,0.8",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let md = std::fs::read_to_string(dir.join("report.md")).unwrap();
    let reproduce: Vec<&str> = md
        .split("## Reproduce")
        .nth(1)
        .unwrap()
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("isochron trials"))
        .collect();
    assert_eq!(reproduce.len(), 4, "{md}");
    let mut headline: Vec<(String, u64, u64)> = Vec::new();
    for line in reproduce {
        // e.g. isochron trials --scenario cells/evalcheck-T1.50-d0.35-0.60.toml --n 4 --seed 5 --json
        let mut args: Vec<&str> = line.split_whitespace().skip(1).collect();
        let cell = args[2]
            .trim_start_matches("cells/")
            .trim_end_matches(".toml");
        let again = dir.join(format!("{cell}.again.jsonl"));
        let again_s = again.display().to_string();
        args.extend(["--per-trial", &again_s]);
        let summary = run_json(&bin, dir, &args);
        // The report's row for this cell.
        let t: f64 = cell.split("-T").nth(1).unwrap()[..4].parse().unwrap();
        let band = cell.rsplit("-d").next().unwrap().replace('-', "..");
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| {t} s | {band} m |")))
            .unwrap_or_else(|| panic!("no row for {cell} in\n{md}"));
        let c = cells(row);
        let n = summary["trials"].as_u64().unwrap();
        let ok = summary["successes"].as_u64().unwrap();
        assert_eq!(c[2], n.to_string(), "{row}");
        assert_eq!(c[3], ok.to_string(), "{row}");
        assert_eq!(
            c[4],
            format!("{:.1}%", 100.0 * summary["success_rate"].as_f64().unwrap()),
            "{row}"
        );
        assert_eq!(
            c[6],
            format!("{:.1}", summary["timing_error_ms"]["p95"].as_f64().unwrap()),
            "{row}"
        );
        assert_eq!(
            c[7],
            format!(
                "{:.1}",
                1e3 * summary["position_error_m"]["p95"].as_f64().unwrap()
            ),
            "{row}"
        );
        // Trial by trial, the raw results behind the report are the rerun's.
        let raw = std::fs::read_to_string(dir.join("cells").join(format!("{cell}.jsonl"))).unwrap();
        assert_eq!(
            per_trial(&raw),
            per_trial(&std::fs::read_to_string(&again).unwrap()),
            "{cell}"
        );
        match headline.iter_mut().find(|h| h.0 == format!("{t} s")) {
            Some(h) => {
                h.1 += n;
                h.2 += ok;
            }
            None => headline.push((format!("{t} s"), n, ok)),
        }
    }
    // The headline rows pool the cells of each movement time.
    for (t, n, ok) in &headline {
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| isochron (simulated) | {t} |")))
            .unwrap_or_else(|| panic!("no headline row for {t} in\n{md}"));
        let c = cells(row);
        assert_eq!(c[3], n.to_string(), "{row}");
        assert_eq!(
            c[4],
            format!("{:.1}%", 100.0 * *ok as f64 / *n as f64),
            "{row}"
        );
    }
}

/// `isochron eval --reality`: the reality lab's section (smallest size: one
/// trial per row, model camera) has its tables, says its figures are
/// reality-lab figures, and its paper row is what `isochron trials` prints.
#[test]
fn the_reality_section_reports_its_rows_as_reality_lab_figures() {
    let Some(bin) = isochron() else { return };
    let dir = std::env::temp_dir().join(format!("isochron-evalreal-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let reality = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    let text = std::fs::read_to_string(&reality).unwrap();
    let lab = dir.join("reality.toml");
    std::fs::write(&lab, format!("{text}\n[camera]\nvision = \"model\"\n")).unwrap();
    let truthful = dir.join("lab.toml");
    std::fs::write(&truthful, "name = \"t\"\n[camera]\nvision = \"model\"\n").unwrap();
    let out = Command::new(&bin)
        .arg("eval")
        .arg("--scenario")
        .arg(&truthful)
        .arg("--reality")
        .arg(&lab)
        .arg("--out")
        .arg(&dir)
        .args([
            "--n",
            "1",
            "--seed",
            "3",
            "--movement-times-s",
            "1.5",
            "--distance-edges-m",
            "0.35,0.8",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let md = std::fs::read_to_string(dir.join("report.md")).unwrap();
    let section = md
        .split("## Reality lab")
        .nth(1)
        .expect("a reality section");
    assert!(section.contains("every figure in this section is a reality-lab figure"));
    assert!(md.contains("**truthful-world**"));
    for table in [
        "By distance band",
        "By movement time",
        "The paper's condition",
        "Ablation",
    ] {
        assert!(section.contains(table), "{table}");
    }
    for row in [
        "| pendulum effects alone |",
        "| camera effects alone |",
        "| robot effects alone |",
        "| geometry effects alone |",
        "| all effects |",
        "| all effects, online estimation off |",
        "| no world effect (truthful world) |",
    ] {
        assert!(section.contains(row), "{row}");
    }
    assert!(dir.join("reality_signed_timing_error.svg").exists());
    // Issue #40: the ablation's control rows succeed, and every row is timed
    // by its judge's arrival rule and judged by the judge its world calls for.
    for control in [
        "| no world effect (truthful world) |",
        "| no world effect (world as believed) |",
    ] {
        let row = section.lines().find(|l| l.starts_with(control)).unwrap();
        let c = cells(row);
        assert_eq!(c[1], c[2], "every trial succeeds: {row}");
    }
    let ablation = section.split("### Ablation").nth(1).unwrap();
    // Its table: the second paragraph (after the title), header and rule skipped.
    let rows: Vec<Vec<String>> = ablation
        .split("\n\n")
        .nth(1)
        .unwrap()
        .lines()
        .skip(2)
        .map(cells)
        .collect();
    assert!(rows.len() >= 8, "{ablation}");
    let commands: Vec<&str> = section
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("isochron trials"))
        .collect();
    // The ablation's rows are the last of the reality section's commands.
    let first = commands.len() - rows.len();
    for (c, command) in rows.iter().zip(&commands[first..]) {
        let cell = command.split_whitespace().nth(3).unwrap();
        let sc = rt_core::params::Scenario::from_file(&dir.join(cell)).unwrap();
        let judge = &c[8];
        if sc.world.is_some() {
            assert!(judge.starts_with("physical"), "{c:?}");
            assert_eq!(sc.control.arrival_settle_m, 0.002, "{c:?}");
        } else {
            assert!(judge.starts_with("truthful"), "{c:?}");
            assert_eq!(sc.control.arrival_settle_m, 0.0, "{c:?}");
            assert!(c[9].contains("release_delay_prior_ms = 0"), "{c:?}");
        }
        // Each trial was judged by that judge (a `physical` verdict exactly
        // in a world).
        let jsonl = std::fs::read_to_string(dir.join(cell).with_extension("jsonl")).unwrap();
        for line in jsonl.lines() {
            let v: Value = serde_json::from_str(line).unwrap();
            assert_eq!(
                v.get("physical").is_some(),
                sc.world.is_some(),
                "{c:?}: {line}"
            );
        }
    }
    // The paper's row is what its command prints again.
    let row = section
        .lines()
        .find(|l| l.starts_with("| 0.70 m, 1.5 s (the paper's condition) |"))
        .unwrap();
    let c = cells(row);
    let paper = section
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("isochron trials"))
        .nth(2)
        .unwrap();
    let args: Vec<&str> = paper.split_whitespace().skip(1).collect();
    let summary = run_json(&bin, &dir, &args);
    assert_eq!(
        c[1],
        summary["trials"].as_u64().unwrap().to_string(),
        "{row}"
    );
    assert_eq!(
        c[2],
        summary["successes"].as_u64().unwrap().to_string(),
        "{row}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
