//! The paper's Fig. 4 for a recording, as SVG: measured angle and estimate, a
//! 300-step prediction, the estimated angular velocity and the Kalman gain.

use std::fmt::Write as _;

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

/// One curve: name, colour, times, values, drawn as dots (else a line).
type Curve<'a> = (&'a str, &'a str, &'a [f64], &'a [f64], bool);

struct Panel<'a> {
    title: &'a str,
    unit: &'a str,
    lines: Vec<Curve<'a>>,
}

const W: f64 = 900.0;
const PH: f64 = 200.0;
const LEFT: f64 = 70.0;
const RIGHT: f64 = 20.0;
const TOP: f64 = 30.0;
const GAP: f64 = 45.0;

/// Renders the figure as a standalone SVG document.
pub fn fig4_svg(d: &Fig4Data, title: &str) -> String {
    let panels = [
        Panel {
            title: "Angle: measured (asin(z/l)) and estimated",
            unit: "deg",
            lines: vec![
                ("measured", "#E69F00", &d.t_s, &d.measured_deg, true),
                ("estimated", "#0072B2", &d.t_s, &d.estimate_deg, false),
            ],
        },
        Panel {
            title: "300-step prediction against the measurements",
            unit: "deg",
            lines: vec![
                ("measured", "#E69F00", &d.t_s, &d.measured_deg, true),
                (
                    "predicted",
                    "#009E73",
                    &d.prediction_t_s,
                    &d.prediction_deg,
                    false,
                ),
            ],
        },
        Panel {
            title: "Estimated angular velocity",
            unit: "deg/s",
            lines: vec![("rate", "#0072B2", &d.t_s, &d.rate_degps, false)],
        },
        Panel {
            title: "Kalman gain",
            unit: "1/m, 1/(s m)",
            lines: vec![
                ("K angle", "#D55E00", &d.t_s, &d.gain_angle, false),
                ("K rate", "#CC79A7", &d.t_s, &d.gain_rate, false),
            ],
        },
    ];
    let h = TOP + panels.len() as f64 * (PH + GAP);
    let mut svg = String::new();
    let _ = writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{h}" viewBox="0 0 {W} {h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(svg, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        svg,
        r#"<text x="{LEFT}" y="18" font-size="15" font-weight="bold">{}</text>"#,
        escape(title)
    );
    let (t0, t1) = finite_range(d.t_s.iter().chain(&d.prediction_t_s));
    for (k, p) in panels.iter().enumerate() {
        let y0 = TOP + k as f64 * (PH + GAP) + 20.0;
        draw_panel(&mut svg, p, y0, (t0, t1), d.prediction_from_s);
    }
    svg.push_str("</svg>\n");
    svg
}

fn finite_range<'a>(v: impl Iterator<Item = &'a f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &x in v {
        if x.is_finite() {
            lo = lo.min(x);
            hi = hi.max(x);
        }
    }
    if lo > hi {
        (0.0, 1.0)
    } else if lo == hi {
        (lo - 1.0, hi + 1.0)
    } else {
        (lo, hi)
    }
}

fn draw_panel(svg: &mut String, p: &Panel<'_>, y0: f64, (t0, t1): (f64, f64), mark: f64) {
    let pw = W - LEFT - RIGHT;
    let (v0, v1) = finite_range(p.lines.iter().flat_map(|l| l.3.iter()));
    let pad = (v1 - v0) * 0.05;
    let (v0, v1) = (v0 - pad, v1 + pad);
    let x = |t: f64| LEFT + (t - t0) / (t1 - t0) * pw;
    let y = |v: f64| y0 + PH - (v - v0) / (v1 - v0) * PH;
    let _ = writeln!(
        svg,
        r##"<text x="{LEFT}" y="{}" font-weight="bold">{} ({})</text><rect x="{LEFT}" y="{y0}" width="{pw}" height="{PH}" fill="none" stroke="#888"/>"##,
        y0 - 6.0,
        escape(p.title),
        escape(p.unit)
    );
    for i in 0..=4 {
        let v = v0 + (v1 - v0) * f64::from(i) / 4.0;
        let _ = writeln!(
            svg,
            r##"<text x="{}" y="{}" text-anchor="end" fill="#444">{}</text><line x1="{LEFT}" x2="{}" y1="{yy}" y2="{yy}" stroke="#eee"/>"##,
            LEFT - 6.0,
            y(v) + 4.0,
            short(v),
            LEFT + pw,
            yy = y(v)
        );
        let t = t0 + (t1 - t0) * f64::from(i) / 4.0;
        let _ = writeln!(
            svg,
            r##"<text x="{}" y="{}" text-anchor="middle" fill="#444">{:.1} s</text>"##,
            x(t),
            y0 + PH + 15.0,
            t
        );
    }
    if mark.is_finite() {
        let _ = writeln!(
            svg,
            r##"<line x1="{xm}" x2="{xm}" y1="{y0}" y2="{}" stroke="#009E73" stroke-dasharray="4 3"/>"##,
            y0 + PH,
            xm = x(mark)
        );
    }
    for (i, (name, color, ts, vs, dots)) in p.lines.iter().enumerate() {
        if *dots {
            let _ = write!(svg, r#"<g fill="{color}">"#);
            for (&t, &v) in ts.iter().zip(vs.iter()) {
                if t.is_finite() && v.is_finite() {
                    let _ = write!(
                        svg,
                        r#"<circle cx="{:.1}" cy="{:.1}" r="1.5"/>"#,
                        x(t),
                        y(v)
                    );
                }
            }
            svg.push_str("</g>\n");
        } else {
            let _ = write!(
                svg,
                r#"<polyline fill="none" stroke="{color}" stroke-width="1.5" points=""#
            );
            for (&t, &v) in ts.iter().zip(vs.iter()) {
                if t.is_finite() && v.is_finite() {
                    let _ = write!(svg, "{:.1},{:.1} ", x(t), y(v));
                }
            }
            svg.push_str("\"/>\n");
        }
        let _ = writeln!(
            svg,
            r#"<text x="{}" y="{}" fill="{color}">{}</text>"#,
            LEFT + pw - 120.0,
            y0 + 16.0 + 14.0 * i as f64,
            escape(name)
        );
    }
}

fn short(v: f64) -> String {
    if v != 0.0 && (v.abs() < 0.01 || v.abs() >= 1e4) {
        format!("{v:.1e}")
    } else {
        format!("{v:.2}")
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
