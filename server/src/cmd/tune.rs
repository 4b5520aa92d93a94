//! `isochron tune --recording FILE [--json]`: EKF noise from a recorded trial.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rt_core::{
    ekf::EkfParams,
    params::Scenario,
    pendulum::{PendulumGeometry, PendulumModel},
    tuning::{self, Series, figure},
};

/// Arguments of `isochron tune`.
#[derive(Debug, clap::Args)]
pub struct TuneArgs {
    /// The recording: a trial's recording.csv from the service, or a CSV with columns t_s,x_m.
    #[arg(long)]
    pub recording: PathBuf,
    /// The lab the recording comes from (pendulum length); default: the paper's lab.
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Where to write the tuned `[ekf]` parameters (default: next to the recording, .ekf.toml).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Where to write the paper's Fig. 4 for the recording (default: next to it, .fig4.svg).
    #[arg(long)]
    pub figure: Option<PathBuf>,
    /// Print one JSON object instead of a summary.
    #[arg(long)]
    pub json: bool,
}

fn beside(recording: &Path, suffix: &str) -> PathBuf {
    let stem = recording
        .file_stem()
        .map_or_else(|| "recording".into(), |s| s.to_string_lossy().into_owned());
    recording.with_file_name(format!("{stem}{suffix}"))
}

/// Runs `isochron tune`.
pub fn run(args: TuneArgs) -> anyhow::Result<String> {
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    let text = std::fs::read_to_string(&args.recording)
        .with_context(|| format!("cannot read {}", args.recording.display()))?;
    let series = Series::from_csv(&text)?;
    let model = PendulumModel::from_params(&scenario.pendulum)?;
    let geometry = PendulumGeometry::new(
        scenario.pendulum.length_m,
        scenario.task.distance_m.lo,
        scenario.task.intercept_height_m,
    )?;
    let base = EkfParams::default();
    let report = tuning::tune(&series, &base, model, geometry)?;
    let out = args
        .out
        .unwrap_or_else(|| beside(&args.recording, ".ekf.toml"));
    std::fs::write(&out, tuning::params_toml(&base, &report))
        .with_context(|| format!("cannot write {}", out.display()))?;
    let tuned = tuning::with_noise(
        &base,
        report.estimate.measurement_noise_m,
        report.estimate.process_noise,
    );
    let fig_path = args
        .figure
        .unwrap_or_else(|| beside(&args.recording, ".fig4.svg"));
    let data = figure::fig4_data(&series, &tuned, model, geometry)?;
    let title = format!(
        "{}: EKF with measurement noise {:.2} mm, {} = {:.3e}",
        args.recording.display(),
        1e3 * report.estimate.measurement_noise_m,
        report.estimate.process_noise_param,
        report.estimate.process_noise
    );
    std::fs::write(&fig_path, figure::fig4_svg(&data, &title))
        .with_context(|| format!("cannot write {}", fig_path.display()))?;
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        v["params_file"] = out.display().to_string().into();
        v["figure_file"] = fig_path.display().to_string().into();
        return Ok(serde_json::to_string(&v)?);
    }
    let c = &report.consistency;
    Ok(format!(
        "{} measurements, mean interval {:.1} ms\n\
         measurement noise: {:.3} mm (was {:.3} mm)\n\
         {}: {:.4e} (was {:.4e})\n\
         NIS mean {:.3} (95% bounds {:.3}..{:.3}: {}), innovation lag-1 autocorrelation {:.3}, {} rejected\n\
         parameters: {}\nfigure: {}",
        report.measurements,
        1e3 * report.mean_interval_s,
        1e3 * report.estimate.measurement_noise_m,
        1e3 * report.before.measurement_noise_m,
        report.estimate.process_noise_param,
        report.estimate.process_noise,
        report.before.process_noise,
        c.nis_mean,
        c.nis_bounds_95[0],
        c.nis_bounds_95[1],
        if c.nis_consistent {
            "consistent"
        } else {
            "NOT consistent"
        },
        c.innovation_autocorr_lag1,
        c.rejected,
        out.display(),
        fig_path.display()
    ))
}
