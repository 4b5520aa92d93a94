//! The signals of the paper's Fig. 4 for a recording: measured angle and
//! estimate, a 300-step prediction, the estimated angular velocity and the
//! Kalman gain (drawn by the server's plotting module, `isochron tune`).

use super::{Series, TuneError, run_filter};
use crate::ekf::{EkfParams, Prediction};
use crate::pendulum::{PendulumGeometry, PendulumModel};

/// Steps of the prediction panel (the paper's horizon).
pub const PREDICTION_STEPS: usize = 300;

/// The signals of the figure.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Fig4Data {
    /// Measurement capture times, seconds.
    pub t_s: Vec<f64>,
    /// Measured angle asin(z / l), degrees.
    pub measured_deg: Vec<f64>,
    /// Estimated angle after each measurement, degrees.
    pub estimate_deg: Vec<f64>,
    /// Estimated angular velocity after each measurement, degrees/s.
    pub rate_degps: Vec<f64>,
    /// Kalman gain for the angle, rad/m.
    pub gain_angle: Vec<f64>,
    /// Kalman gain for the angular velocity, rad/(s m).
    pub gain_rate: Vec<f64>,
    /// Prediction start, seconds.
    pub prediction_from_s: f64,
    /// Predicted times, seconds.
    pub prediction_t_s: Vec<f64>,
    /// Predicted angle, degrees.
    pub prediction_deg: Vec<f64>,
}

/// Runs the filter over the recording and collects the figure's signals; the
/// prediction starts after a third of the recording and runs 300 capture intervals.
///
/// # Errors
///
/// As [`run_filter`].
pub fn fig4_data(
    series: &Series,
    params: &EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
) -> Result<Fig4Data, TuneError> {
    let l = model.length_m;
    let dt = series.mean_interval_s();
    let start_at = series.t_s.first().copied().unwrap_or(0.0)
        + (series.t_s.last().copied().unwrap_or(0.0) - series.t_s.first().copied().unwrap_or(0.0))
            / 3.0;
    let mut d = Fig4Data {
        prediction_from_s: f64::NAN,
        ..Fig4Data::default()
    };
    run_filter(series, params, model, geometry, |i, pred, _, _, s, ekf| {
        let t = series.t_s[i];
        d.t_s.push(t);
        d.measured_deg
            .push((series.z_m[i] / l).clamp(-1.0, 1.0).asin().to_degrees());
        let (phi, rate) = ekf
            .posterior()
            .map_or((f64::NAN, f64::NAN), |(_, x, _)| (x[0], x[1]));
        d.estimate_deg.push(phi.to_degrees());
        d.rate_degps.push(rate.to_degrees());
        let c = l * pred.state[0].cos();
        d.gain_angle.push(pred.cov[(0, 0)] * c / s);
        d.gain_rate.push(pred.cov[(1, 0)] * c / s);
        if d.prediction_t_s.is_empty() && t >= start_at && dt.is_finite() {
            d.prediction_from_s = t;
            let mut p = Prediction::default();
            for k in 1..=PREDICTION_STEPS {
                let tk = t + k as f64 * dt;
                if ekf.predict_at(tk, &mut p).is_ok() {
                    d.prediction_t_s.push(tk);
                    d.prediction_deg.push(p.state[0].to_degrees());
                }
            }
        }
    })?;
    Ok(d)
}
