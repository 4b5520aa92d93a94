//! The import rules between the core's parts (issue #19), checked on the
//! source text: `params` composes the parts' sections into a `Scenario`, so
//! `control` never imports `params`, and the parts `control` builds on import
//! neither `params` nor `control` (their `tests.rs` files may: test code only);
//! `control` never imports `sim` (issue #35: the controller and its judges
//! know the world only by measurement), nor does `lab` (the trial driver
//! and the runtime: the world plugs in through their traits, implemented in
//! `sim`).

use std::path::{Path, PathBuf};

/// A part (`src/<part>/` or `src/<part>.rs`), the modules it must not import,
/// the names it must not use (`params`' own types, reachable only through it),
/// and whether its `tests.rs` files are held to the rule too.
struct Rule {
    part: &'static str,
    modules: &'static [&'static str],
    names: &'static [&'static str],
    tests_too: bool,
}

const RULES: &[Rule] = &[
    Rule {
        part: "control",
        modules: &["params"],
        names: &["Scenario"],
        tests_too: true,
    },
    // The controller and its judges never see the simulated world (issue
    // #35): only its beliefs, measurements and calibration.
    Rule {
        part: "control",
        modules: &["sim"],
        names: &[],
        tests_too: false,
    },
    // The trial driver and the runtime hold no truth (issue #35): the world
    // plugs in through `lab`'s traits (`lab::TruthObserver`, the runtime's
    // simulated links), implemented in `sim`.
    Rule {
        part: "lab",
        modules: &["sim"],
        names: &[],
        tests_too: false,
    },
    Rule {
        part: "ekf",
        modules: &["params", "control"],
        names: &["Scenario"],
        tests_too: false,
    },
    Rule {
        part: "pendulum",
        modules: &["params", "control"],
        names: &["Scenario"],
        tests_too: false,
    },
    Rule {
        part: "timing",
        modules: &["params", "control"],
        names: &["Scenario"],
        tests_too: false,
    },
    Rule {
        part: "trajectory",
        modules: &["params", "control"],
        names: &["Scenario"],
        tests_too: false,
    },
    Rule {
        part: "kinematics",
        modules: &["params", "control"],
        names: &["Scenario"],
        tests_too: false,
    },
    Rule {
        part: "check",
        modules: &["params", "control"],
        names: &["Scenario"],
        tests_too: false,
    },
];

fn is_ident(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// The source without `//` comments (doc comments included).
fn code_of(source: &str) -> String {
    source
        .lines()
        .map(|l| l.find("//").map_or(l, |i| &l[..i]))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Where `word` occurs in `code` as a whole identifier (byte offsets).
fn word_at(code: &str, word: &str) -> Vec<usize> {
    code.match_indices(word)
        .map(|(i, _)| i)
        .filter(|&i| {
            let before = code[..i].chars().next_back();
            let after = code[i + word.len()..].chars().next();
            !before.is_some_and(is_ident) && !after.is_some_and(is_ident)
        })
        .collect()
}

/// Whether a path ends in the segment `crate` or `super`.
fn ends_in_crate_or_super(path: &str) -> bool {
    let path = path.trim_end();
    ["crate", "super"].iter().any(|w| {
        path.strip_suffix(w)
            .is_some_and(|head| !head.chars().next_back().is_some_and(is_ident))
    })
}

/// Whether the path segment at `i` is a crate-level module: right after
/// `crate::` or `super::`, or first in a `crate::{...}`/`super::{...}` group.
fn is_crate_level(code: &str, i: usize) -> bool {
    let before = code[..i].trim_end();
    if let Some(path) = before.strip_suffix("::") {
        return ends_in_crate_or_super(path);
    }
    if !(before.ends_with('{') || before.ends_with(',')) {
        return false;
    }
    // Inside a group: walk back to its opening brace at depth 0.
    let mut depth = 0usize;
    for (j, c) in before.char_indices().rev() {
        match c {
            '}' => depth += 1,
            '{' if depth > 0 => depth -= 1,
            '{' => {
                let head = before[..j].trim_end();
                let Some(path) = head.strip_suffix("::") else {
                    return false;
                };
                return ends_in_crate_or_super(path);
            }
            ';' => return false,
            _ => {}
        }
    }
    false
}

/// Each line of `source` that imports one of `modules` or names one of `names`.
fn violations(source: &str, modules: &[&str], names: &[&str]) -> Vec<String> {
    let code = code_of(source);
    let mut at: Vec<(usize, &str)> = Vec::new();
    for m in modules {
        at.extend(
            word_at(&code, m)
                .into_iter()
                .filter(|&i| is_crate_level(&code, i))
                .map(|i| (i, *m)),
        );
    }
    for n in names {
        at.extend(word_at(&code, n).into_iter().map(|i| (i, *n)));
    }
    at.sort_unstable();
    at.into_iter()
        .map(|(i, what)| {
            let line = code[..i].matches('\n').count() + 1;
            let text = code.lines().nth(line - 1).unwrap_or("").trim();
            format!("line {line}: {what}: {text}")
        })
        .collect()
}

/// The `.rs` files of `src/<part>/` (recursively) or `src/<part>.rs`.
fn files_of(part: &str) -> Vec<PathBuf> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut out = Vec::new();
    let single = src.join(format!("{part}.rs"));
    if single.is_file() {
        out.push(single);
    }
    let mut dirs = vec![src.join(part)];
    while let Some(dir) = dirs.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries {
            let p = e.expect("a directory entry").path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn the_detector_finds_each_way_to_import_a_module() {
    let params = |s: &str| violations(s, &["params"], &["Scenario"]);
    for bad in [
        "use crate::params::Scenario;",
        "use crate::params;",
        "use crate :: params::RobotParams;",
        "use crate::{check, params::SuccessParams};",
        "use crate::{\n    check,\n    params::{self, TaskParams},\n};",
        "use super::super::params::TaskParams;",
        "let t = crate::params::TaskParams::default();",
        "fn f(s: &Scenario) {}",
        "fn f(s: &crate::Scenario) {}",
    ] {
        assert!(!params(bad).is_empty(), "not found in {bad:?}");
    }
    for fine in [
        "use crate::pendulum::params::PendulumParams;",
        "use crate::ekf::{EkfParams, params};",
        "let params = &beliefs.control; let x = self.params.hold_time_s;",
        "// use crate::params::Scenario;",
        "/// Built by `params::Scenario::beliefs` from a scenario.",
        "use crate::{ekf::{EkfParams, params}, check};",
        "struct ScenarioName;",
        "use mycrate::params::X;",
    ] {
        assert_eq!(params(fine), Vec::<String>::new(), "flagged in {fine:?}");
    }
}

#[test]
fn control_never_imports_params_and_its_foundations_import_neither() {
    let mut found = Vec::new();
    for rule in RULES {
        let files = files_of(rule.part);
        assert!(!files.is_empty(), "no source files for {}", rule.part);
        for f in files {
            if !rule.tests_too && f.file_name().is_some_and(|n| n == "tests.rs") {
                continue;
            }
            let source = std::fs::read_to_string(&f).expect("a readable source file");
            for v in violations(&source, rule.modules, rule.names) {
                found.push(format!("{}: {v}", f.display()));
            }
        }
    }
    assert!(
        found.is_empty(),
        "back-imports (control -/-> params; control, lab -/-> sim; ekf, pendulum, \
         timing, trajectory, kinematics, check -/-> params, control):\n{}",
        found.join("\n")
    );
}
