//! Report figures as standalone SVG documents, drawn with `plotters` (SVG
//! backend only): lines, dots, bars with intervals, histograms (`isochron
//! eval`), and the paper's Fig. 4 (`isochron tune`). No scripts, readable in any
//! browser.

use plotters::{
    coord::Shift,
    prelude::*,
    style::text_anchor::{HPos, Pos, VPos},
};
use rt_core::tuning::figure::Fig4Data;

/// Okabe-Ito colours (distinguishable with colour-vision deficiencies).
pub const COLORS: [RGBColor; 7] = [
    RGBColor(0x00, 0x72, 0xB2),
    RGBColor(0xD5, 0x5E, 0x00),
    RGBColor(0x00, 0x9E, 0x73),
    RGBColor(0xE6, 0x9F, 0x00),
    RGBColor(0xCC, 0x79, 0xA7),
    RGBColor(0x56, 0xB4, 0xE9),
    RGBColor(0x77, 0x77, 0x77),
];

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// A polyline.
    Line,
    /// A dashed polyline.
    Dashed,
    /// Dots.
    Dots,
}

/// One named series of `(x, y)` points.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend text.
    pub name: String,
    /// Colour.
    pub color: RGBColor,
    /// Drawing style.
    pub style: Style,
    /// Points; non-finite ones are skipped.
    pub points: Vec<(f64, f64)>,
}

/// A bar with an interval (e.g. a success rate and its confidence interval).
#[derive(Debug, Clone)]
pub struct Bar {
    /// Category label under the bar.
    pub label: String,
    /// Height.
    pub value: f64,
    /// Lower and upper end of the interval drawn over the bar.
    pub interval: Option<(f64, f64)>,
    /// Text above the bar.
    pub note: String,
}

type Result<T> = anyhow::Result<T>;

fn err(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("cannot draw the figure: {e}")
}

const SIZE: (u32, u32) = (720, 360);
const GREY: RGBColor = RGBColor(0x44, 0x44, 0x44);

/// The finite range of `vals`, widened by `pad` of its span (`(0, 1)` when empty).
fn range(vals: impl Iterator<Item = f64>, pad: f64) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in vals.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if lo > hi {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-12 {
        return (lo - 0.5, hi + 0.5);
    }
    let p = (hi - lo) * pad;
    (lo - p, hi + p)
}

fn finite(points: &[(f64, f64)]) -> impl Iterator<Item = (f64, f64)> + Clone + '_ {
    points
        .iter()
        .copied()
        .filter(|p| p.0.is_finite() && p.1.is_finite())
}

/// Renders `draw` on a white SVG canvas of `size` into a string.
fn svg(
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<SVGBackend<'_>, Shift>) -> Result<()>,
) -> Result<String> {
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, size).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        draw(&root)?;
        root.present().map_err(err)?;
    }
    out.push('\n');
    Ok(out)
}

/// Lines and dots over numeric axes, with optional horizontal reference lines.
pub fn xy_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    series: &[Series],
    hlines: &[(f64, &str)],
) -> Result<String> {
    let (x0, x1) = range(
        series.iter().flat_map(|s| s.points.iter().map(|p| p.0)),
        0.02,
    );
    let (y0, y1) = range(
        series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1))
            .chain(hlines.iter().map(|h| h.0)),
        0.08,
    );
    svg(SIZE, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 15))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(xlabel)
            .y_desc(ylabel)
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        for (v, label) in hlines {
            let style = RGBColor(0x55, 0x55, 0x55).stroke_width(1);
            chart
                .draw_series(DashedLineSeries::new([(x0, *v), (x1, *v)], 6, 4, style))
                .map_err(err)?;
            chart
                .draw_series([Text::new(
                    label.to_string(),
                    (x1, *v),
                    ("sans-serif", 12)
                        .into_font()
                        .color(&GREY)
                        .pos(Pos::new(HPos::Right, VPos::Bottom)),
                )])
                .map_err(err)?;
        }
        for s in series {
            let color = s.color;
            let drawn = match s.style {
                Style::Dots => chart
                    .draw_series(
                        finite(&s.points).map(|p| Circle::new(p, 2.5, color.mix(0.7).filled())),
                    )
                    .map_err(err)?,
                Style::Line => chart
                    .draw_series(LineSeries::new(finite(&s.points), color.stroke_width(2)))
                    .map_err(err)?,
                Style::Dashed => chart
                    .draw_series(DashedLineSeries::new(
                        finite(&s.points),
                        7,
                        4,
                        color.stroke_width(2),
                    ))
                    .map_err(err)?,
            };
            drawn.label(s.name.as_str()).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
            });
        }
        if !series.is_empty() {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .background_style(WHITE.mix(0.8))
                .border_style(RGBColor(0xBB, 0xBB, 0xBB))
                .draw()
                .map_err(err)?;
        }
        Ok(())
    })
}

/// Bars with intervals (e.g. success rate with its 95% confidence interval),
/// values on `y`.
pub fn bar_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    bars: &[Bar],
    y: (f64, f64),
) -> Result<String> {
    let n = bars.len().max(1);
    svg(SIZE, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 15))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..n as f64, y.0..y.1)
            .map_err(err)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .disable_x_axis()
            .x_desc(xlabel)
            .y_desc(ylabel)
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        let clamp = |v: f64| v.clamp(y.0, y.1);
        chart
            .draw_series(bars.iter().enumerate().map(|(i, b)| {
                let i = i as f64;
                Rectangle::new(
                    [(i + 0.15, y.0), (i + 0.85, clamp(b.value))],
                    COLORS[0].mix(0.75).filled(),
                )
            }))
            .map_err(err)?;
        let whisker = RGBColor(0x22, 0x22, 0x22).stroke_width(2);
        for (i, b) in bars.iter().enumerate() {
            let xm = i as f64 + 0.5;
            if let Some((lo, hi)) = b.interval {
                let (lo, hi) = (clamp(lo), clamp(hi));
                chart
                    .draw_series([
                        PathElement::new(vec![(xm, lo), (xm, hi)], whisker),
                        PathElement::new(vec![(xm - 0.08, lo), (xm + 0.08, lo)], whisker),
                        PathElement::new(vec![(xm - 0.08, hi), (xm + 0.08, hi)], whisker),
                    ])
                    .map_err(err)?;
            }
            let centred = |vpos| Pos::new(HPos::Center, vpos);
            chart
                .draw_series([
                    Text::new(
                        b.note.clone(),
                        (xm, y.1),
                        ("sans-serif", 11)
                            .into_font()
                            .color(&BLACK)
                            .pos(centred(VPos::Top)),
                    ),
                    Text::new(
                        b.label.clone(),
                        (xm, y.0),
                        ("sans-serif", 12)
                            .into_font()
                            .color(&GREY)
                            .pos(centred(VPos::Top)),
                    ),
                ])
                .map_err(err)?;
        }
        Ok(())
    })
}

/// A histogram of `values` in `bins` equal bins over their range (from 0 when
/// all are positive).
pub fn histogram(title: &str, xlabel: &str, values: &[f64], bins: usize) -> Result<String> {
    let bins = bins.max(1);
    let (lo, hi) = range(values.iter().copied(), 0.0);
    let lo = lo.min(0.0);
    let width = (hi - lo) / bins as f64;
    let mut counts = vec![0usize; bins];
    for v in values.iter().filter(|v| v.is_finite()) {
        let i = (((v - lo) / width) as usize).min(bins - 1);
        counts[i] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1).max(1) as f64;
    svg(SIZE, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 15))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(lo..hi, 0.0..top * 1.1)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(xlabel)
            .y_desc("trials")
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        chart
            .draw_series(counts.iter().enumerate().map(|(i, &c)| {
                let x = lo + i as f64 * width;
                Rectangle::new([(x, 0.0), (x + width, c as f64)], COLORS[0].filled())
            }))
            .map_err(err)?;
        Ok(())
    })
}

/// One curve of a Fig. 4 panel: name, colour, times, values, drawn as dots (else a line).
type Curve<'a> = (&'a str, RGBColor, &'a [f64], &'a [f64], bool);

/// The paper's Fig. 4 for a recording (`isochron tune`): measured angle and
/// estimate, a 300-step prediction, the estimated angular velocity and the
/// Kalman gain, one panel each over a shared time axis; the prediction's start
/// is marked.
pub fn fig4(d: &Fig4Data, title: &str) -> Result<String> {
    let [blue, orange, green, yellow, pink, ..] = COLORS;
    let panels: [(&str, &str, Vec<Curve<'_>>); 4] = [
        (
            "Angle: measured (asin(z/l)) and estimated",
            "deg",
            vec![
                ("measured", yellow, &d.t_s, &d.measured_deg, true),
                ("estimated", blue, &d.t_s, &d.estimate_deg, false),
            ],
        ),
        (
            "300-step prediction against the measurements",
            "deg",
            vec![
                ("measured", yellow, &d.t_s, &d.measured_deg, true),
                (
                    "predicted",
                    green,
                    &d.prediction_t_s,
                    &d.prediction_deg,
                    false,
                ),
            ],
        ),
        (
            "Estimated angular velocity",
            "deg/s",
            vec![("rate", blue, &d.t_s, &d.rate_degps, false)],
        ),
        (
            "Kalman gain",
            "1/m, 1/(s m)",
            vec![
                ("K angle", orange, &d.t_s, &d.gain_angle, false),
                ("K rate", pink, &d.t_s, &d.gain_rate, false),
            ],
        ),
    ];
    let (t0, t1) = range(d.t_s.iter().chain(&d.prediction_t_s).copied(), 0.0);
    svg((900, 1000), |root| {
        let root = root.titled(title, ("sans-serif", 15)).map_err(err)?;
        for (area, (name, unit, curves)) in root.split_evenly((panels.len(), 1)).iter().zip(&panels)
        {
            let (v0, v1) = range(curves.iter().flat_map(|c| c.3.iter().copied()), 0.05);
            let mut chart = ChartBuilder::on(area)
                .caption(format!("{name} ({unit})"), ("sans-serif", 13))
                .margin(8)
                .x_label_area_size(25)
                .y_label_area_size(65)
                .build_cartesian_2d(t0..t1, v0..v1)
                .map_err(err)?;
            chart
                .configure_mesh()
                .x_label_formatter(&|t| format!("{t:.1} s"))
                .light_line_style(WHITE)
                .draw()
                .map_err(err)?;
            if d.prediction_from_s.is_finite() {
                let m = d.prediction_from_s;
                chart
                    .draw_series(DashedLineSeries::new(
                        [(m, v0), (m, v1)],
                        4,
                        3,
                        green.into(),
                    ))
                    .map_err(err)?;
            }
            for &(label, color, ts, vs, dots) in curves {
                let pts: Vec<(f64, f64)> = ts.iter().copied().zip(vs.iter().copied()).collect();
                let drawn = if dots {
                    chart
                        .draw_series(finite(&pts).map(|p| Circle::new(p, 1.5, color.filled())))
                        .map_err(err)?
                } else {
                    chart
                        .draw_series(LineSeries::new(finite(&pts), color.stroke_width(2)))
                        .map_err(err)?
                };
                drawn.label(label).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                });
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.8))
                .border_style(RGBColor(0xBB, 0xBB, 0xBB))
                .draw()
                .map_err(err)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charts_are_standalone_svg_with_their_data() {
        let s = xy_chart(
            "t",
            "x",
            "y",
            &[Series {
                name: "a<b".into(),
                color: COLORS[0],
                style: Style::Line,
                points: vec![(0.0, 1.0), (1.0, f64::NAN), (2.0, 3.0)],
            }],
            &[(2.0, "ref")],
        )
        .unwrap();
        assert!(
            s.starts_with("<svg") && s.trim_end().ends_with("</svg>"),
            "{s}"
        );
        assert!(s.contains("a&lt;b"), "{s}");
        assert!(s.contains(">\nref\n<"), "{s}");
        // The series' line (its legend sample is a second polyline).
        assert!(s.matches("<polyline").count() >= 1, "{s}");
        let b = bar_chart(
            "b",
            "x",
            "y",
            &[Bar {
                label: "0.35".into(),
                value: 0.9,
                interval: Some((0.8, 0.95)),
                note: "9/10".into(),
            }],
            (0.0, 1.0),
        )
        .unwrap();
        assert!(b.contains(">\n9/10\n<") && b.contains(">\n0.35\n<"), "{b}");
        // Background, plot area and the bar.
        assert!(b.matches("<rect").count() >= 2, "{b}");
        let h = histogram("h", "ms", &[1.0, 2.0, 2.5, f64::NAN], 4).unwrap();
        // Four bins in the bar colour (plotters writes colours as #RRGGBB).
        assert_eq!(h.matches("fill=\"#0072B2\"").count(), 4, "{h}");
    }

    #[test]
    fn fig4_has_every_panel() {
        let t: Vec<f64> = (0..50).map(|i| f64::from(i) / 30.0).collect();
        let v: Vec<f64> = t.iter().map(|t| (2.0 * t).sin()).collect();
        let d = Fig4Data {
            t_s: t.clone(),
            measured_deg: v.clone(),
            estimate_deg: v.clone(),
            rate_degps: v.clone(),
            gain_angle: v.clone(),
            gain_rate: v.clone(),
            prediction_from_s: 0.5,
            prediction_t_s: t.clone(),
            prediction_deg: v,
        };
        let svg = fig4(&d, "test").unwrap();
        assert!(svg.starts_with("<svg"));
        for title in [
            "Angle",
            "300-step prediction",
            "angular velocity",
            "Kalman gain",
        ] {
            assert!(svg.contains(title), "{title}");
        }
        // Five lines over the four panels, each with its legend sample.
        assert!(svg.matches("<polyline").count() >= 5, "{svg}");
        assert!(svg.matches("<circle").count() >= 2 * 50, "{svg}");
    }
}
