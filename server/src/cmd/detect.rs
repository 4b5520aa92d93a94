//! `isochron detect --video FILE [--json]`: the ball detector over a recorded video.

use std::{io::Write, path::PathBuf, time::Instant};

use anyhow::Context;
use rt_core::vision::{Detector, DetectorParams, FrameSource, VideoFileSource};
use serde::Serialize;

/// Arguments of `isochron detect`.
#[derive(Debug, clap::Args)]
pub struct DetectArgs {
    /// The video (e.g. an MJPG .avi recorded by the lab).
    #[arg(long)]
    pub video: PathBuf,
    /// One JSON object per frame on stdout instead of a summary.
    #[arg(long)]
    pub json: bool,
}

/// One frame's result (CONTRACT.md, `isochron detect`).
#[derive(Debug, Serialize)]
struct FrameLine {
    frame: u64,
    t_s: f64,
    found: bool,
    x_px: Option<f64>,
    y_px: Option<f64>,
    r_px: Option<f64>,
    confidence: Option<f64>,
}

/// Runs `isochron detect`: per frame a JSON line, or a summary at the end.
pub fn run(args: &DetectArgs) -> anyhow::Result<()> {
    let mut source = VideoFileSource::open(&args.video, None, false)?;
    let mut detector = Detector::new(DetectorParams::default())?;
    let fps = source.fps();
    let mut out = std::io::stdout().lock();
    let (mut frames, mut found) = (0u64, 0u64);
    let mut times_ms = Vec::new();
    while let Some(frame) = source
        .next_frame()
        .with_context(|| format!("reading {}", args.video.display()))?
    {
        let t0 = Instant::now();
        let det = detector.detect(frame.image, frame.t_capture_s)?;
        times_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        frames += 1;
        found += u64::from(det.is_some());
        if args.json {
            let line = FrameLine {
                frame: frame.index,
                t_s: frame.t_capture_s,
                found: det.is_some(),
                x_px: det.map(|d| d.x_px),
                y_px: det.map(|d| d.y_px),
                r_px: det.map(|d| d.r_px),
                confidence: det.map(|d| d.confidence),
            };
            let text = serde_json::to_string(&line)?;
            match writeln!(out, "{text}") {
                // A closed pipe (`| head`) ends the run quietly.
                Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => return Ok(()),
                r => r?,
            }
        }
    }
    if frames == 0 {
        anyhow::bail!("{}: no frames could be decoded", args.video.display());
    }
    if !args.json {
        // The one quantile rule of every reported percentile.
        let p50 = rt_core::quantile::quantile_of(&times_ms, 0.5).unwrap_or(f64::NAN);
        let text = format!(
            "{}: {frames} frames at {fps:.1} fps, ball found in {found} ({:.1}%), detection p50 {p50:.2} ms",
            args.video.display(),
            100.0 * found as f64 / frames as f64
        );
        match writeln!(out, "{text}") {
            Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => {}
            r => r?,
        }
    }
    match out.flush() {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}
