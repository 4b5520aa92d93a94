//! Helpers shared by the end-to-end tests in `tests/tests/`.

use std::time::Duration;

use anyhow::Context;

pub mod procs;
mod served;
pub mod service;
mod table;
pub use served::{ServedLab, TrialEnds};
pub use table::CsvTable;

/// A plain HTTP/1.1 response.
#[derive(Debug)]
pub struct HttpResponse {
    /// Status code.
    pub status: u16,
    /// Headers, names lower-cased.
    pub headers: Vec<(String, String)>,
    /// Body bytes.
    pub body: Vec<u8>,
}

impl HttpResponse {
    /// The body parsed as JSON.
    ///
    /// # Errors
    ///
    /// When the body is not JSON.
    pub fn json(&self) -> anyhow::Result<serde_json::Value> {
        serde_json::from_slice(&self.body).context("body is not JSON")
    }

    /// A header's value.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

/// Sends one request (`reqwest`: no proxy, no redirects followed, a fresh
/// connection) with a 10 s timeout.
///
/// # Errors
///
/// When the client cannot be built, `method` is not a method, the request fails
/// (including the 10 s timeout) or the body cannot be read.
pub async fn http(
    addr: std::net::SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> anyhow::Result<HttpResponse> {
    let client = reqwest::Client::builder()
        .no_proxy()
        .redirect(reqwest::redirect::Policy::none())
        .pool_max_idle_per_host(0)
        .timeout(Duration::from_secs(10))
        .build()?;
    let method = reqwest::Method::from_bytes(method.as_bytes())?;
    let mut req = client
        .request(method, format!("http://{addr}{path}"))
        .body(body.to_vec());
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let resp = req.send().await.context("HTTP request failed")?;
    let status = resp.status().as_u16();
    let headers = resp
        .headers()
        .iter()
        .map(|(k, v)| {
            (
                k.as_str().to_owned(),
                String::from_utf8_lossy(v.as_bytes()).into_owned(),
            )
        })
        .collect();
    let body = resp.bytes().await.context("HTTP body")?.to_vec();
    Ok(HttpResponse {
        status,
        headers,
        body,
    })
}

/// The `isochron` binary that `cargo test --workspace` built next to the
/// running test (or `ISOCHRON_BIN`), if every `(args, needle)` check passes:
/// `isochron ARGS` exits 0 and its standard output contains `needle`.
///
/// Engineers may share one target folder, so a binary there can come from
/// another branch and lack what the test needs: that is a skip (`None`, said
/// on stderr), except under `CI=true`, where it fails the test.
pub fn isochron_bin(checks: &[(&[&str], &str)]) -> Option<std::path::PathBuf> {
    let bin = if let Some(b) = std::env::var_os("ISOCHRON_BIN") {
        std::path::PathBuf::from(b)
    } else {
        let exe = std::env::current_exe().ok()?;
        exe.parent()?.parent()?.join("isochron")
    };
    let passes = |args: &[&str], needle: &str| {
        std::process::Command::new(&bin)
            .args(args)
            .output()
            .is_ok_and(|o| {
                o.status.success() && String::from_utf8_lossy(&o.stdout).contains(needle)
            })
    };
    if let Some((args, needle)) = checks.iter().find(|(a, n)| !passes(a, n)) {
        let msg = format!(
            "{} missing, or `isochron {}` does not show `{needle}` (run `cargo build -p server`)",
            bin.display(),
            args.join(" ")
        );
        assert!(std::env::var("CI").as_deref() != Ok("true"), "{msg}");
        eprintln!("SKIPPED: {msg}");
        return None;
    }
    Some(bin)
}
