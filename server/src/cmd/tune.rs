//! `isochron tune --recording FILE [--recording FILE ...] [--scenario FILE] [--json]`:
//! EKF noise from recorded trials.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rt_core::{
    params::Scenario,
    pendulum::{PendulumGeometry, PendulumModel},
    tuning::{self, Series, figure},
};

/// Arguments of `isochron tune`.
#[derive(Debug, clap::Args)]
pub struct TuneArgs {
    /// The recording: a trial's recording.csv from the service (only the measurements
    /// after the release are used), or a CSV with columns t_s,x_m. Repeat the option to
    /// tune on several trials of the same lab together (each is run by a fresh filter).
    #[arg(long, required = true, num_args = 1)]
    pub recording: Vec<PathBuf>,
    /// The lab the recordings come from (default: the paper's lab): its pendulum, and its
    /// [ekf] section, which is the starting point of the search and whose settings other
    /// than the two estimated noise values are written out unchanged.
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Where to write the tuned `[ekf]` parameters (default: next to the first recording,
    /// .ekf.toml). Load it with `isochron trials --params FILE` or `isochron serve --params FILE`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Where to write the paper's Fig. 4 for the longest recording (default: next to the
    /// first recording, .fig4.svg).
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

/// Runs `isochron tune`. Nothing is written unless the recordings were read, the
/// estimate found and the figure drawn.
pub fn run(args: TuneArgs) -> anyhow::Result<String> {
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    let Some(first) = args.recording.first().cloned() else {
        anyhow::bail!("--recording: at least one recording is needed");
    };
    let mut recordings = Vec::with_capacity(args.recording.len());
    for path in &args.recording {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let series = Series::from_csv(&text).with_context(|| path.display().to_string())?;
        recordings.push(series);
    }
    let model = PendulumModel::from_params(&scenario.pendulum)?;
    let geometry = PendulumGeometry::new(
        scenario.pendulum.length_m,
        scenario.task.distance_m.lo,
        scenario.task.intercept_height_m,
    )?;
    // The scenario's filter: tune replaces its two noise values, nothing else.
    let base = scenario.ekf.clone();
    let report = tuning::tune_recordings(&recordings, &base, model, geometry)?;
    let tuned = tuning::with_noise(
        &base,
        report.estimate.measurement_noise_m,
        report.estimate.process_noise,
    );
    let Some(longest) = recordings.iter().max_by_key(|s| s.len()) else {
        anyhow::bail!("--recording: at least one recording is needed");
    };
    let data = figure::fig4_data(longest, &tuned, model, geometry)?;
    let title = format!(
        "{}: EKF with measurement noise {:.2} mm, {} = {:.3e}",
        first.display(),
        1e3 * report.estimate.measurement_noise_m,
        report.estimate.process_noise_param,
        report.estimate.process_noise
    );
    let params_text = tuning::params_toml(&base, &report);
    let svg = crate::plot::fig4(&data, &title)?;
    let out = args.out.unwrap_or_else(|| beside(&first, ".ekf.toml"));
    let fig_path = args.figure.unwrap_or_else(|| beside(&first, ".fig4.svg"));
    std::fs::write(&out, params_text).with_context(|| format!("cannot write {}", out.display()))?;
    std::fs::write(&fig_path, svg)
        .with_context(|| format!("cannot write {}", fig_path.display()))?;
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        v["params_file"] = out.display().to_string().into();
        v["figure_file"] = fig_path.display().to_string().into();
        v["ekf"] = serde_json::to_value(&tuned)?;
        return Ok(serde_json::to_string(&v)?);
    }
    let c = &report.consistency;
    Ok(format!(
        "{} measurements from {} recording(s), mean interval {:.1} ms (the likelihood over every {}{} frame)\n\
         measurement noise: {:.3} mm (was {:.3} mm)\n\
         {}: {:.4e} (was {:.4e})\n\
         NIS mean {:.3} (95% bounds {:.3}..{:.3}: {}), innovation lag-1 autocorrelation {:.3}, {} rejected\n\
         parameters: {}\nfigure: {}",
        report.measurements,
        report.recordings,
        1e3 * report.mean_interval_s,
        match report.stride {
            1 => String::new(),
            k => k.to_string(),
        },
        match report.stride {
            1 => "",
            2 => "nd",
            3 => "rd",
            _ => "th",
        },
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

#[cfg(test)]
mod tests {
    use super::super::trials::{TrialsArgs, run as trials};

    /// `isochron trials --params FILE` in process: the filter the trials ran with
    /// is the file's, and a bad file costs hits (the file is honoured).
    #[test]
    fn trials_run_with_the_params_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let scenario = dir.join("lab.toml");
        std::fs::write(
            &scenario,
            "name = \"lab\"\n[camera]\nvision = \"model\"\n[ekf]\ngate_nis = 20.0\n",
        )
        .unwrap();
        let good = dir.join("good.ekf.toml");
        std::fs::write(
            &good,
            "[ekf]\nmeasurement_noise_m = 0.0021\naccel_psd_rad2ps3 = 1e-8\n",
        )
        .unwrap();
        let bad = dir.join("bad.ekf.toml");
        std::fs::write(&bad, "[ekf]\nmeasurement_noise_m = 0.00002\n").unwrap();
        let run = |params: Vec<std::path::PathBuf>| -> serde_json::Value {
            let out = trials(&TrialsArgs {
                scenario: scenario.clone(),
                n: 6,
                seed: 2,
                json: true,
                per_trial: None,
                params,
                calibration: None,
                shard: None,
                block: super::super::trials::DEFAULT_BLOCK,
            })
            .unwrap();
            serde_json::from_str(&out).unwrap()
        };
        let (before, after, worse) = (run(vec![]), run(vec![good]), run(vec![bad]));
        assert_eq!(before["ekf"]["measurement_noise_m"], 0.002);
        assert_eq!(after["ekf"]["measurement_noise_m"], 0.0021);
        assert_eq!(after["ekf"]["accel_psd_rad2ps3"], 1e-8);
        assert_eq!(
            after["ekf"]["gate_nis"], 20.0,
            "the scenario's other settings stay"
        );
        assert_eq!(worse["ekf"]["measurement_noise_m"], 0.00002);
        let hits = |v: &serde_json::Value| v["successes"].as_u64().unwrap();
        assert!(hits(&before) >= 5, "{before}");
        assert!(hits(&after) >= hits(&before), "{after}");
        assert!(hits(&worse) < hits(&before), "{worse}");
        assert!(
            worse["ekf_counters"]["rejected"].as_u64().unwrap() > 100,
            "{worse}"
        );
    }
}
