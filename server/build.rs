//! Records the git revision for `isochron --version`, and collects the doc
//! comments of the scenario's fields from `rt-core/src` (the parameters'
//! descriptions in `/api/openapi.json`, shown by the dashboard's Parameters panel).
use std::{fmt::Write as _, path::Path, process::Command};

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_owned())
}

fn main() {
    let rev = git(&["rev-parse", "--short=12", "HEAD"]).unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=ISOCHRON_GIT_REV={rev}");
    if let Some(dir) = git(&["rev-parse", "--absolute-git-dir"]) {
        println!("cargo:rerun-if-changed={dir}/HEAD");
        if let Some(head) = git(&["symbolic-ref", "-q", "HEAD"]) {
            println!("cargo:rerun-if-changed={dir}/{head}");
        }
    }
    println!("cargo:rerun-if-changed=build.rs");
    param_docs();
}

/// Every `pub struct`'s named fields with their type's last path segment and
/// the first paragraph of their doc comment, as `(struct, field, type, doc)`,
/// written to `OUT_DIR/param_docs.rs`.
fn param_docs() {
    // Read when the script runs, not baked in when it was compiled: cargo
    // reuses one build script's binary for the same package built from
    // another checkout (a worktree sharing the target directory), and a
    // baked-in path then points at the other checkout, or at nothing.
    let manifest = std::env::var("CARGO_MANIFEST_DIR").unwrap_or_else(|_| ".".into());
    let root = Path::new(&manifest).join("../rt-core/src");
    println!("cargo:rerun-if-changed={}", root.display());
    let mut files = Vec::new();
    walk(&root, &mut files);
    files.sort();
    let mut out =
        String::from("/// (struct, field, type, doc) of rt-core's documented struct fields.\n");
    out.push_str("pub const PARAM_DOCS: &[(&str, &str, &str, &str)] = &[\n");
    for f in &files {
        println!("cargo:rerun-if-changed={}", f.display());
        let Ok(text) = std::fs::read_to_string(f) else {
            continue;
        };
        let mut current: Option<String> = None;
        let mut doc: Vec<String> = Vec::new();
        for line in text.lines() {
            let t = line.trim();
            if let Some(rest) = t.strip_prefix("pub struct ") {
                let name: String = rest
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                current = (t.ends_with('{')).then_some(name);
                doc.clear();
                continue;
            }
            if current.is_some() && (t == "}" || line.starts_with('}')) {
                current = None;
            }
            if let Some(d) = t.strip_prefix("///") {
                doc.push(d.trim().to_owned());
                continue;
            }
            if t.starts_with("#[") {
                continue;
            }
            if let (Some(s), Some(rest)) = (&current, t.strip_prefix("pub "))
                && let Some((field, ty)) = rest.split_once(':')
                && !doc.is_empty()
            {
                let para: Vec<&str> = doc
                    .iter()
                    .map(String::as_str)
                    .take_while(|l| !l.is_empty())
                    .collect();
                let ty = ty.trim().trim_end_matches(',');
                let ty = ty.rsplit("::").next().unwrap_or(ty);
                let _ = writeln!(
                    out,
                    "    ({s:?}, {:?}, {:?}, {:?}),",
                    field.trim(),
                    ty,
                    para.join(" ")
                );
            }
            doc.clear();
        }
    }
    out.push_str("];\n");
    let dest = Path::new(&std::env::var("OUT_DIR").expect("OUT_DIR")).join("param_docs.rs");
    std::fs::write(dest, out).expect("cannot write param_docs.rs");
}

fn walk(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            walk(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}
