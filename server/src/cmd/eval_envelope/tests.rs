use std::collections::BTreeMap;

use super::*;

fn reality() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    Scenario::from_file(&path).unwrap()
}

/// Every leaf of a world as JSON, by its path under `[world]` (a range is one leaf).
fn leaves(w: &WorldParams) -> BTreeMap<String, Value> {
    fn walk(prefix: &str, v: &Value, out: &mut BTreeMap<String, Value>) {
        match v {
            Value::Object(m) => {
                for (k, x) in m {
                    let p = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    walk(&p, x, out);
                }
            }
            _ => {
                out.insert(prefix.to_owned(), v.clone());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk("", &serde_json::to_value(w).unwrap(), &mut out);
    out
}

/// A lab whose every factor is away from its benign value (so every factor
/// has something to scale), inside the bounds.
fn harsh() -> Scenario {
    let mut s = reality();
    let mut w = WorldParams::default();
    for f in factors() {
        for k in &f.keys {
            let b = k.benign_of(&s);
            let (lo_b, hi_b) = k.bounds;
            let r = match (k.scaling, k.slot) {
                (Scaling::Inverse, Slot::Number(_)) => RangeParam::fixed(0.5 * hi_b),
                (Scaling::Inverse, _) => RangeParam::new(0.4 * hi_b, 0.5 * hi_b),
                (_, Slot::Number(_)) if hi_b > b => RangeParam::fixed(b + 0.1 * (hi_b - b)),
                (_, Slot::Number(_)) => RangeParam::fixed(b + 0.1 * (lo_b - b)),
                _ => RangeParam::new(b + 0.05 * (lo_b - b), b + 0.1 * (hi_b - b)),
            };
            k.set(&mut w, r);
        }
    }
    s.world = Some(w);
    s.validate().unwrap();
    s
}

#[test]
fn every_world_key_is_a_factor_or_said_not_to_be() {
    let mut w = WorldParams::default();
    w.pendulum.release_delay_ms = Some(RangeParam::fixed(1.0));
    w.robot.latency_ms = Some(RangeParam::fixed(1.0));
    let keys: Vec<String> = leaves(&w).into_keys().collect();
    let mut named: Vec<&str> = factors()
        .iter()
        .flat_map(|f| f.keys.iter().map(|k| k.path))
        .chain(NOT_FACTORS.iter().map(|(k, _)| *k))
        .collect();
    let before = named.len();
    named.sort_unstable();
    named.dedup();
    assert_eq!(named.len(), before, "a key named twice");
    for k in &keys {
        assert!(
            named.contains(&k.as_str()),
            "[world] key `{k}` is neither a factor of the envelope nor in NOT_FACTORS: \
             add one line to factors() in server/src/cmd/eval_envelope.rs (or its name and \
             why to NOT_FACTORS)"
        );
    }
    for k in &named {
        assert!(keys.iter().any(|x| x == k), "`{k}` is no [world] key");
    }
}

#[test]
fn the_tables_bounds_are_validates() {
    let s = reality();
    for f in factors() {
        for k in &f.keys {
            for (bound, outward) in [(k.bounds.0, -1.0), (k.bounds.1, 1.0)] {
                let mut w = WorldParams::default();
                k.set(&mut w, RangeParam::fixed(bound));
                assert!(w.validate().is_ok(), "{} = {bound}", k.path);
                let beyond = bound + outward * 1e-6 * bound.abs().max(1.0);
                k.set(&mut w, RangeParam::fixed(beyond));
                assert!(w.validate().is_err(), "{} = {beyond} validates", k.path);
            }
            let b = k.benign_of(&s);
            if k.scaling == Scaling::Spread {
                assert!(
                    (k.bounds.0..=k.bounds.1).contains(&b),
                    "{}: benign {b}",
                    k.path
                );
            }
        }
    }
}

#[test]
fn multiple_one_is_reality_and_multiple_zero_the_benign_values() {
    for s in [reality(), harsh()] {
        let table = factors();
        let all: Vec<&Factor> = table.iter().collect();
        let (at_one, clamped) = scaled(&s, &all, 1.0).unwrap();
        assert_eq!(at_one.world, s.world);
        assert!(clamped.is_empty(), "{clamped:?}");
        for f in &table {
            let (one, clamped) = scaled(&s, &[f], 1.0).unwrap();
            assert_eq!(one, s, "{}", f.name);
            assert!(clamped.is_empty());
            for k0 in [0.0, 1e-9] {
                let (zero, _) = scaled(&s, &[f], k0).unwrap();
                let w = zero.world.as_ref().unwrap();
                for k in &f.keys {
                    let Some(r) = k.get(w) else {
                        // Unset: the benign belief at every multiple.
                        assert_eq!(k.get(s.world.as_ref().unwrap()), None);
                        continue;
                    };
                    let want = match k.scaling {
                        Scaling::Spread => k.benign_of(&s),
                        Scaling::Inverse => k.bounds.1,
                    };
                    for v in [r.lo, r.hi] {
                        assert!(
                            // k0 times a distance of at most 1000 from benign.
                            (v - want).abs() <= k0 * 1e3 + 1e-12 * want.abs().max(1.0),
                            "{} at {k0}x: {v}, benign {want}",
                            k.path
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn every_multiple_validates_within_the_bounds_and_grows_away_from_benign() {
    for s in [reality(), harsh()] {
        let table = factors();
        let all: Vec<&Factor> = table.iter().collect();
        for i in 0..=64 {
            let k = 1.0 + 7.0 * f64::from(i) / 64.0;
            let (sc, _) = scaled(&s, &all, k).unwrap();
            sc.validate().unwrap();
            for f in &table {
                let (one, _) = scaled(&s, &[f], k).unwrap();
                let (next, _) = scaled(&s, &[f], k + 0.1).unwrap();
                let (w0, w1) = (one.world.unwrap(), next.world.unwrap());
                for key in &f.keys {
                    let (Some(a), Some(b)) = (key.get(&w0), key.get(&w1)) else {
                        continue;
                    };
                    assert!(key.bounds.0 <= a.lo && a.hi <= key.bounds.1 && a.lo <= a.hi);
                    // Harsher: never closer to the benign value.
                    let d = |v: f64| match key.scaling {
                        Scaling::Spread => (v - key.benign_of(&s)).abs(),
                        Scaling::Inverse => 1.0 / v,
                    };
                    for (x, y) in [(a.lo, b.lo), (a.hi, b.hi)] {
                        assert!(d(y) >= d(x) - 1e-12, "{} at {k}x: {x} -> {y}", key.path);
                    }
                }
            }
        }
    }
}

#[test]
fn clamps_hold_and_are_reported() {
    let mut s = reality();
    s.robot.latency_ms = 8.0;
    let mut w = WorldParams::default();
    w.camera.rolling_shutter_ms = RangeParam::fixed(25.0);
    w.robot.servo_natural_hz = RangeParam::new(10.0, 15.0);
    w.robot.latency_ms = Some(RangeParam::new(5.0, 14.0));
    w.pendulum.release_delay_ms = None;
    s.world = Some(w);
    let table = factors();
    let f = |name: &str| table.iter().find(|f| f.name == name).unwrap();
    let world = |sc: &Scenario| sc.world.clone().unwrap();

    // Rolling shutter 25 ms: 75 ms at 3x, 100 ms (the bound) from 4x.
    let shutter = f("rolling shutter");
    let (at3, c3) = scaled(&s, &[shutter], 3.0).unwrap();
    assert_eq!(
        world(&at3).camera.rolling_shutter_ms,
        RangeParam::fixed(75.0)
    );
    assert!(c3.is_empty());
    let (at8, c8) = scaled(&s, &[shutter], 8.0).unwrap();
    assert_eq!(
        world(&at8).camera.rolling_shutter_ms,
        RangeParam::fixed(100.0)
    );
    assert_eq!(c8, vec!["camera.rolling_shutter_ms"]);
    let k = &shutter.keys[0];
    assert_eq!(k.clamp_onset(RangeParam::fixed(25.0), 0.0), Some(4.0));

    // The servo: 10..15 Hz is 5..7.5 Hz at 2x; the 2 Hz floor from 5x.
    let servo = f("servo bandwidth");
    let (at2, c2) = scaled(&s, &[servo], 2.0).unwrap();
    assert_eq!(
        world(&at2).robot.servo_natural_hz,
        RangeParam::new(5.0, 7.5)
    );
    assert!(c2.is_empty());
    let (at8, c8) = scaled(&s, &[servo], 8.0).unwrap();
    assert_eq!(
        world(&at8).robot.servo_natural_hz,
        RangeParam::new(2.0, 2.0)
    );
    assert_eq!(c8, vec!["robot.servo_natural_hz"]);
    assert_eq!(
        servo.keys[0].clamp_onset(RangeParam::new(10.0, 15.0), f64::INFINITY),
        Some(5.0)
    );
    // 0 (the first-order lag) stays 0.
    let (r, c) = servo.keys[0].scale(RangeParam::fixed(0.0), f64::INFINITY, 3.0);
    assert_eq!((r, c), (RangeParam::fixed(0.0), false));

    // Robot latency about the believed 8 ms: [5, 14] -> [-1 -> 0, 26] at 3x.
    let lat = f("robot latency");
    let (at3, c3) = scaled(&s, &[lat], 3.0).unwrap();
    assert_eq!(
        world(&at3).robot.latency_ms,
        Some(RangeParam::new(0.0, 26.0))
    );
    assert_eq!(c3, vec!["robot.latency_ms"]);
    let onset = lat.keys[0]
        .clamp_onset(RangeParam::new(5.0, 14.0), 8.0)
        .unwrap();
    assert!((onset - 8.0 / 3.0).abs() < 1e-12, "{onset}");

    // An unset release delay is the believed one at every multiple: nothing to scale.
    let delay = f("magnet release delay");
    let (at8, _) = scaled(&s, &[delay], 8.0).unwrap();
    assert_eq!(world(&at8).pendulum.release_delay_ms, None);
    assert!(!is_active(&s, delay));
    assert!(is_active(&s, shutter));
}

#[test]
fn scaling_a_factor_changes_its_keys_and_nothing_else() {
    let s = harsh();
    let before = leaves(s.world.as_ref().unwrap());
    for f in factors() {
        let (sc, _) = scaled(&s, &[&f], 3.0).unwrap();
        let after = leaves(sc.world.as_ref().unwrap());
        let changed: Vec<&String> = before
            .iter()
            .filter(|(k, v)| after.get(*k) != Some(*v))
            .map(|(k, _)| k)
            .collect();
        let mut want: Vec<&str> = f.keys.iter().map(|k| k.path).collect();
        want.sort_unstable();
        assert_eq!(changed, want, "{}", f.name);
        // The rest of the scenario (beliefs, task, camera) is reality's.
        let mut back = sc.clone();
        back.world = s.world.clone();
        assert_eq!(back, s);
    }
}

#[test]
fn a_truthful_world_has_nothing_to_scale() {
    let err = scaled(&Scenario::default(), &[], 1.0).unwrap_err();
    assert!(err.to_string().contains("no [world]"), "{err}");
}

#[test]
fn the_bisection_brackets_a_threshold_within_its_resolution() {
    let (max, steps) = (8.0, 4);
    let res = resolution(max, steps);
    assert_eq!(res, 7.0 / 16.0);
    for t in [1.0, 1.3, 2.0, 3.0, 3.2, 5.5, 7.9] {
        let mut runs = 0;
        let (done, out) = bisect(
            max,
            steps,
            |k| {
                runs += 1;
                Ok(k <= t)
            },
            |p| *p,
        )
        .unwrap();
        let Outcome::Bracket { pass, fail } = out else {
            panic!("{t}: {out:?}");
        };
        assert!(pass <= t && t < fail, "{t}: {pass}..{fail}");
        assert!((fail - pass - res).abs() < 1e-12, "{t}: {pass}..{fail}");
        assert_eq!(runs, steps + 2);
        assert_eq!(done.len(), steps + 2);
        assert_eq!((done[0].0, done[1].0), (1.0, max));
        assert_eq!(out.largest_passing(), Some(pass));
        assert_eq!(out.first_failing(), Some(fail));
    }
    // Fails at reality's own range: one run.
    let (done, out) = bisect(max, steps, |k| Ok(k <= 0.5), |p| *p).unwrap();
    assert_eq!((done.len(), out), (1, Outcome::FailsAtOne));
    assert_eq!(out.largest_passing(), None);
    assert_eq!(out.first_failing(), Some(1.0));
    // Passes at the largest multiple: two runs.
    let (done, out) = bisect(max, steps, |k| Ok(k <= 100.0), |p| *p).unwrap();
    assert_eq!((done.len(), out), (2, Outcome::PassesAtMax { max }));
    assert_eq!(out.largest_passing(), Some(max));
    // --max-multiple 1: only reality.
    let (done, out) = bisect(1.0, steps, |_| Ok(true), |p| *p).unwrap();
    assert_eq!((done.len(), out), (1, Outcome::PassesAtMax { max: 1.0 }));
    // A run's error stops it.
    assert!(
        bisect(
            max,
            steps,
            |_| -> anyhow::Result<bool> { bail!("no") },
            |p| *p
        )
        .is_err()
    );
}

#[test]
fn a_step_passes_at_95_percent() {
    let step = |successes, trials| Step {
        k: 1.0,
        trials,
        successes,
        ci95: wilson_ci95(successes, trials),
        timing_error_p50_ms: None,
        timing_error_p95_ms: None,
        clamped: vec![],
        ranges: vec![],
        command: String::new(),
    };
    assert!(step(19, 20).passes());
    assert!(step(95, 100).passes());
    assert!(!step(94, 100).passes());
    assert!(!step(18, 20).passes());
    assert!(!step(0, 0).passes());
}

#[test]
fn the_shards_cover_every_item_once() {
    let len = item_names(&factors()).len();
    assert_eq!(len, factors().len() + 1);
    for count in 1..=len {
        let mut seen = Vec::new();
        for index in 0..count {
            let r = shard_items(len, Shard { index, count });
            assert!(!r.is_empty(), "{index}/{count}");
            seen.extend(r);
        }
        assert_eq!(seen, (0..len).collect::<Vec<_>>(), "{count} shards");
    }
}

fn args(out: &Path) -> EvalArgs {
    EvalArgs {
        scenario: None,
        out: out.to_owned(),
        n: 4,
        seed: 1,
        movement_times_s: vec![1.5],
        distance_edges_m: vec![0.35, 0.8],
        reality: Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml")),
        envelope: EnvelopeArgs {
            envelope: true,
            ..EnvelopeArgs::default()
        },
    }
}

#[test]
fn bad_arguments_are_refused_before_anything_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let ok = args(tmp.path());
    assert!(check_args(&ok).is_ok());
    let with = |f: &dyn Fn(&mut EvalArgs)| {
        let mut a = args(tmp.path());
        f(&mut a);
        a
    };
    for (bad, says) in [
        (with(&|a| a.n = 0), "--n"),
        (with(&|a| a.envelope.max_multiple = 0.5), "--max-multiple"),
        (
            with(&|a| a.envelope.max_multiple = f64::NAN),
            "--max-multiple",
        ),
        (
            with(&|a| a.envelope.max_multiple = f64::INFINITY),
            "--max-multiple",
        ),
        (with(&|a| a.envelope.steps = 21), "--steps"),
        (with(&|a| a.reality = None), "--reality"),
        (
            with(&|a| {
                a.envelope.shard = Some(Shard {
                    index: 0,
                    count: 100,
                });
            }),
            "fewer than 100 shards",
        ),
        (
            with(&|a| {
                a.reality =
                    Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml"));
            }),
            "no [world]",
        ),
    ] {
        let err = run(&bad).unwrap_err();
        assert!(format!("{err:#}").contains(says), "{says}: {err:#}");
    }
    // Nothing was run or written.
    assert!(!tmp.path().join("cells").exists());
    // --combine without shard files says so.
    let err = run(&with(&|a| a.envelope.combine = true)).unwrap_err();
    assert!(format!("{err:#}").contains("envelope"), "{err:#}");
}

fn step(k: f64, successes: usize, trials: usize, clamped: &[&str]) -> Step {
    Step {
        k,
        trials,
        successes,
        ci95: wilson_ci95(successes, trials),
        timing_error_p50_ms: Some(2.0),
        timing_error_p95_ms: Some(9.5),
        clamped: clamped.iter().map(|c| (*c).to_owned()).collect(),
        ranges: vec![KeyRange {
            key: "camera.latency_ms".into(),
            range: Some([-5.0 * k, 15.0 * k]),
        }],
        command: format!(
            "isochron trials --scenario cells/x-k{k}.toml --n {trials} --seed 1 --json"
        ),
    }
}

#[test]
fn the_report_is_written_from_the_shard_files_there() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::create_dir_all(dir.join("envelope")).unwrap();
    let mut r = reality();
    r.camera.vision = VisionMode::Full;
    if let Some(w) = r.world.as_mut() {
        w.camera.latency_ms = RangeParam::new(-5.0, 15.0);
    }
    let table = factors();
    let items = item_names(&table);
    let run = RunKey {
        scenario_toml: r.to_toml_string(),
        n: 20,
        seed: 1,
        max_multiple: 8.0,
        steps: 2,
        shard_count: 3,
        items: items.clone(),
    };
    let world = r.world.clone().unwrap();
    let item = |index: usize, steps: Vec<Step>, outcome| ItemResult {
        index,
        name: items[index].clone(),
        reality: key_ranges(
            table.get(index).map_or(&[][..], |f| f.keys.as_slice()),
            &world,
        ),
        clamp_onset: None,
        steps,
        outcome,
    };
    let cam = items
        .iter()
        .position(|n| n == "camera latency offset")
        .unwrap();
    let last = items.len() - 1;
    let shard = |index: usize, results: Vec<ItemResult>| ShardFile {
        format: SHARD_FORMAT,
        run: run.clone(),
        shard_index: index,
        command: format!("isochron eval --envelope --shard {index}/3"),
        results,
    };
    // Shard 0 (items 0..8) with the camera latency bracketed at 4.5..6.25x;
    // shard 2 with all together failing at 1x; shard 1 missing.
    let first = shard_items(items.len(), Shard { index: 0, count: 3 });
    assert!(first.contains(&cam));
    let mut zero: Vec<ItemResult> = first
        .clone()
        .filter(|&i| i != cam)
        .map(|i| {
            item(
                i,
                vec![step(1.0, 20, 20, &[]), step(8.0, 20, 20, &["x.y"])],
                Outcome::PassesAtMax { max: 8.0 },
            )
        })
        .collect();
    zero.push(item(
        cam,
        vec![
            step(1.0, 20, 20, &[]),
            step(8.0, 10, 20, &[]),
            step(4.5, 19, 20, &[]),
            step(6.25, 17, 20, &[]),
        ],
        Outcome::Bracket {
            pass: 4.5,
            fail: 6.25,
        },
    ));
    let two = shard_items(items.len(), Shard { index: 2, count: 3 })
        .map(|i| {
            if i == last {
                item(i, vec![step(1.0, 15, 20, &[])], Outcome::FailsAtOne)
            } else {
                item(i, vec![], Outcome::NotScaled)
            }
        })
        .collect();
    let write = |name: &str, f: &ShardFile| {
        std::fs::write(
            dir.join("envelope").join(name),
            serde_json::to_string(f).unwrap(),
        )
        .unwrap();
    };
    write("shard-0-of-3.json", &shard(0, zero));
    write("shard-2-of-3.json", &shard(2, two));
    let path = combine(dir, None).unwrap();
    let md = std::fs::read_to_string(&path).unwrap();
    assert!(
        md.contains("## Robustness envelope (reality-lab figures)"),
        "{md}"
    );
    assert!(md.contains("Camera vision mode: **full"), "{md}");
    assert!(md.contains("**20 trials per step, seed 1**"), "{md}");
    assert!(
        md.contains(
            "| camera latency offset | `camera.latency_ms` | [-5, 15] | 4.5x | \
             [-22.5, 67.5] | 19/20 = 95.0% ("
        ),
        "{md}"
    );
    assert!(md.contains("| 6.25x: 17/20 = 85.0% ("), "{md}");
    assert!(md.contains("| success < 95% |"), "{md}");
    assert!(
        md.contains("| all factors together | every factor above that reality.toml sets | – | none (fails at 1x) |"),
        "{md}"
    );
    assert!(
        md.contains("success < 95% already at reality.toml's range"),
        "{md}"
    );
    assert!(md.contains("clamped at 8x: `x.y`"), "{md}");
    // Shard 1's items are listed as missing, with the shard.
    let missing = shard_items(items.len(), Shard { index: 1, count: 3 });
    for i in missing {
        assert!(
            md.contains(&format!(
                "| {} | | | not run: shard 1/3 missing |",
                items[i]
            )),
            "{}: {md}",
            items[i]
        );
    }
    assert!(md.contains("Missing shards (their items are not in this report yet): 1/3"));
    // Every step, with its command; the factor table; the not-factors.
    assert!(md.contains("`isochron trials --scenario cells/x-k6.25.toml --n 20 --seed 1 --json`"));
    assert!(
        md.contains("| servo bandwidth | `robot.servo_natural_hz` |"),
        "{md}"
    );
    assert!(md.contains("`control.release_delay_prior_ms`"), "{md}");
    assert!(md.contains("- `geometry.contact_disc_radius_m`"), "{md}");
    // The goal line names what is short of it.
    assert!(md.contains("not shown for: "), "{md}");
    assert!(
        md.contains("all factors together (none (fails at 1x))"),
        "{md}"
    );
    let svg = std::fs::read_to_string(dir.join("envelope.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("goal 3x"), "{svg}");
    assert!(svg.contains("4.5-6.25x"), "{svg}");

    // A stale file of another run: refused by --combine, left out by a run.
    let mut other = shard(1, vec![]);
    other.run.n = 30;
    write("shard-1-of-3.json", &other);
    let err = combine(dir, None).unwrap_err();
    assert!(format!("{err:#}").contains("another run"), "{err:#}");
    combine(dir, Some(&run)).unwrap();
    let md = std::fs::read_to_string(&path).unwrap();
    assert!(md.contains("Missing shards (their items are not in this report yet): 1/3"));
}

#[test]
fn numbers_are_written_short() {
    assert_eq!(num(4.5), "4.5");
    assert_eq!(num(8.0), "8");
    assert_eq!(num(1.4375), "1.438");
    assert_eq!(num(-0.0005), "-0.0005");
    assert_eq!(num(0.0), "0");
    assert_eq!(num(f64::INFINITY), "∞");
    assert_eq!(slug("camera latency offset!", 24), "camera-latency-offset");
}
