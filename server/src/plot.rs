//! Report figures as standalone SVG documents, drawn with `plotters` (SVG
//! backend only): lines, dots, bars with intervals, histograms (`isochron
//! eval`), and the paper's Fig. 4 (`isochron tune`). No scripts, readable in any
//! browser.

use plotters::{
    coord::{
        Shift,
        ranged1d::{KeyPointHint, NoDefaultFormatting, Ranged, ValueFormatter},
        types::RangedCoordf64,
    },
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
const FONT: &str = "sans-serif";

/// At most this many ticks on an axis.
pub const MAX_TICKS: usize = 10;
/// At least this many ticks on an axis.
pub const MIN_TICKS: usize = 4;

/// Round tick marks of one axis: every multiple of a 1-2-5 step (1, 2 or 5 x
/// 10^k) from the last at or below the data's low end to the first at or above
/// its high end. Figures draw their axes over exactly these ticks, so an axis
/// reads 0.2 / 0.4 / 0.6 ms, never 0.205 / 0.41 / 0.614.
#[derive(Debug, Clone, PartialEq)]
pub struct Ticks {
    /// The step's leading digit: 1, 2 or 5.
    pub mantissa: i64,
    /// The step's power of ten: the step is `mantissa` x 10^`exponent`.
    pub exponent: i32,
    /// The ticks, increasing: 4 to 10 of them.
    pub values: Vec<f64>,
}

/// `m` x 10^`e` as the nearest double (an exact integer scaled once, so 3 x 0.2
/// is 0.6, not 0.6000000000000001).
fn decimal(m: i64, e: i32) -> f64 {
    if e >= 0 {
        m as f64 * 10f64.powi(e)
    } else {
        m as f64 / 10f64.powi(-e)
    }
}

impl Ticks {
    /// The axis range: first tick to last.
    pub fn range(&self) -> std::ops::Range<f64> {
        let first = self.values.first().copied().unwrap_or(0.0);
        first..self.values.last().copied().unwrap_or(1.0)
    }

    /// A tick's label with the step's decimals ("0.2", "1.15", "20"), never "-0".
    pub fn label(&self, v: f64) -> String {
        let decimals = usize::try_from(-self.exponent).unwrap_or(0);
        let s = format!("{v:.decimals$}");
        match s.strip_prefix('-') {
            Some(pos) if pos.chars().all(|c| c == '0' || c == '.') => pos.to_string(),
            _ => s,
        }
    }
}

/// Round ticks for data over `lo..=hi` (either order; a non-finite end is
/// ignored, a one-point range widened): the smallest 1-2-5 step that covers the
/// range with at most 10 ticks, which makes 4 to 10 of them (the next smaller
/// step needed 11 or more, so this one spans at least 3.2 steps). With
/// `integer` (trial counts, trial numbers) the step is at least 1, every tick a
/// whole number, and a range too short for 4 ticks is extended upwards.
pub fn ticks(lo: f64, hi: f64, integer: bool) -> Ticks {
    let (mut lo, mut hi) = match (lo.is_finite(), hi.is_finite()) {
        (true, true) => (lo.min(hi), lo.max(hi)),
        (true, false) => (lo, lo),
        (false, true) => (hi, hi),
        (false, false) => (0.0, 1.0),
    };
    if hi - lo <= 1e-9 * lo.abs().max(hi.abs()) || hi == lo {
        let d = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
        lo -= d;
        hi += d;
    }
    // A tolerance for values a rounding error beside a tick (0.6 / 0.2 = 2.9999999999999996).
    let near = |x: f64| 1e-9 * x.abs().max(1.0);
    let mut e = ((hi - lo) / MAX_TICKS as f64).log10().floor() as i32 - 1;
    if integer {
        e = e.max(0);
    }
    loop {
        for m in [1, 2, 5] {
            let step = decimal(m, e);
            let first = (lo / step + near(lo / step)).floor();
            let last = (hi / step - near(hi / step)).ceil();
            if last - first + 1.0 <= MAX_TICKS as f64 {
                let first = first as i64;
                let mut last = last as i64;
                if integer {
                    last = last.max(first + MIN_TICKS as i64 - 1);
                }
                let values = (first..=last).map(|i| decimal(i * m, e) + 0.0).collect();
                return Ticks {
                    mantissa: m,
                    exponent: e,
                    values,
                };
            }
        }
        e += 1;
    }
}

/// The 1-2-5 value (1, 2 or 5 x 10^k) nearest to `x` (> 0) on a log scale, e.g. a
/// histogram's bin width for about the asked number of bins.
fn nearest_125(x: f64) -> f64 {
    let e = x.log10().floor() as i32;
    [
        decimal(1, e),
        decimal(2, e),
        decimal(5, e),
        decimal(1, e + 1),
    ]
    .into_iter()
    .min_by(|a, b| (a / x).ln().abs().total_cmp(&(b / x).ln().abs()))
    .unwrap_or(x)
}

/// A plotters axis over `range` whose tick marks and labels are exactly `ticks`
/// (none: an axis without marks, e.g. under categories).
struct TickAxis {
    coord: RangedCoordf64,
    ticks: Option<Ticks>,
}

impl TickAxis {
    fn of(t: &Ticks) -> Self {
        Self {
            coord: t.range().into(),
            ticks: Some(t.clone()),
        }
    }

    fn bare(range: std::ops::Range<f64>) -> Self {
        Self {
            coord: range.into(),
            ticks: None,
        }
    }
}

impl Ranged for TickAxis {
    type FormatOption = NoDefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        self.coord.map(value, limit)
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        match &self.ticks {
            Some(t) if !hint.weight().allow_light_points() => t.values.clone(),
            _ => Vec::new(),
        }
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.coord.range()
    }
}

impl ValueFormatter<f64> for TickAxis {
    fn format_ext(&self, value: &f64) -> String {
        self.ticks
            .as_ref()
            .map_or_else(|| value.to_string(), |t| t.label(*value))
    }
}

/// Whether every finite value is a whole number (and there is one): such an axis gets whole ticks.
fn whole(vals: impl Iterator<Item = f64>) -> bool {
    let mut any = false;
    for v in vals.filter(|v| v.is_finite()) {
        if v.fract() != 0.0 {
            return false;
        }
        any = true;
    }
    any
}

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

/// A legend's entry: its text and how its series is drawn.
#[derive(Clone, Copy)]
struct Entry<'a> {
    name: &'a str,
    color: RGBColor,
    style: Style,
}

const LEGEND_FONT: u32 = 12;
const LEGEND_ROW: i32 = 20;
const LEGEND_SAMPLE: i32 = 18;

/// The legend entries' places, `(x, row)`, flowing in rows of at most `width` pixels.
fn legend_layout(entries: &[Entry<'_>], width: i32) -> Vec<(i32, i32)> {
    let (mut x, mut row) = (0, 0);
    entries
        .iter()
        .map(|e| {
            // An estimate of the text's width: sans-serif at 12 px is about 6.5 px a character.
            let w = LEGEND_SAMPLE + 8 + (e.name.chars().count() as i32 * 13) / 2 + 24;
            if x > 0 && x + w > width {
                x = 0;
                row += 1;
            }
            let at = (x, row);
            x += w;
            at
        })
        .collect()
}

/// Draws the legend on `area` (outside the data) from `(x0, y0)`: `flow` in rows
/// of the area's width, else one entry a line.
fn draw_legend(
    area: &DrawingArea<SVGBackend<'_>, Shift>,
    entries: &[Entry<'_>],
    (x0, y0): (i32, i32),
    flow: bool,
) -> Result<()> {
    let width = area.dim_in_pixel().0 as i32 - x0;
    let places: Vec<(i32, i32)> = if flow {
        legend_layout(entries, width)
    } else {
        (0..entries.len() as i32).map(|i| (0, i)).collect()
    };
    for (e, (x, row)) in entries.iter().zip(places) {
        let (x, y) = (x0 + x, y0 + row * LEGEND_ROW + LEGEND_ROW / 2);
        let stroke = e.color.stroke_width(2);
        match e.style {
            Style::Line => area
                .draw(&PathElement::new(
                    vec![(x, y), (x + LEGEND_SAMPLE, y)],
                    stroke,
                ))
                .map_err(err)?,
            Style::Dashed => {
                let half = LEGEND_SAMPLE / 2;
                area.draw(&PathElement::new(vec![(x, y), (x + half - 2, y)], stroke))
                    .map_err(err)?;
                area.draw(&PathElement::new(
                    vec![(x + half + 2, y), (x + LEGEND_SAMPLE, y)],
                    stroke,
                ))
                .map_err(err)?;
            }
            Style::Dots => area
                .draw(&Circle::new(
                    (x + LEGEND_SAMPLE / 2, y),
                    3,
                    e.color.mix(0.9).filled(),
                ))
                .map_err(err)?,
        }
        area.draw(&Text::new(
            e.name.to_string(),
            (x + LEGEND_SAMPLE + 6, y),
            (FONT, LEGEND_FONT)
                .into_font()
                .color(&BLACK)
                .pos(Pos::new(HPos::Left, VPos::Center)),
        ))
        .map_err(err)?;
    }
    Ok(())
}

/// Lines and dots over numeric axes with round ticks, with optional horizontal
/// reference lines (labelled right of the plot); the legend is below the axes,
/// outside the data. `xlabel` and `ylabel` carry the units, e.g. "distance (m)".
pub fn xy_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    series: &[Series],
    hlines: &[(f64, &str)],
) -> Result<String> {
    let xs = || series.iter().flat_map(|s| finite(&s.points).map(|p| p.0));
    let ys = || {
        series
            .iter()
            .flat_map(|s| finite(&s.points).map(|p| p.1))
            .chain(hlines.iter().map(|h| h.0))
    };
    let (x0, x1) = range(xs(), 0.02);
    let (y0, y1) = range(ys(), 0.08);
    let xt = ticks(x0, x1, whole(xs()));
    let yt = ticks(y0, y1, whole(ys()));
    let entries: Vec<Entry<'_>> = series
        .iter()
        .map(|s| Entry {
            name: &s.name,
            color: s.color,
            style: s.style,
        })
        .collect();
    const LEFT: i32 = 12 + 60;
    let rows = legend_layout(&entries, SIZE.0 as i32 - LEFT - 12)
        .last()
        .map_or(0, |p| p.1 + 1);
    let legend_h = if rows == 0 { 0 } else { rows * LEGEND_ROW + 8 };
    let size = (SIZE.0, SIZE.1 + legend_h as u32);
    let right = if hlines.is_empty() { 12 } else { 60 };
    svg(size, |root| {
        let (top, bottom) = root.split_vertically(SIZE.1);
        let mut chart = ChartBuilder::on(&top)
            .caption(title, (FONT, 15))
            .margin(12)
            .margin_right(right)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(TickAxis::of(&xt), TickAxis::of(&yt))
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(xlabel)
            .y_desc(ylabel)
            .bold_line_style(RGBColor(0xE4, 0xE4, 0xE4))
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        let (xa, xb) = (xt.range().start, xt.range().end);
        for (v, label) in hlines {
            let style = RGBColor(0x55, 0x55, 0x55).stroke_width(1);
            chart
                .draw_series(DashedLineSeries::new([(xa, *v), (xb, *v)], 6, 4, style))
                .map_err(err)?;
            // The line's label right of the plot area, outside the data.
            let (px, py) = chart.backend_coord(&(xb, *v));
            top.draw(&Text::new(
                label.to_string(),
                (px + 6, py),
                (FONT, 12)
                    .into_font()
                    .color(&GREY)
                    .pos(Pos::new(HPos::Left, VPos::Center)),
            ))
            .map_err(err)?;
        }
        for s in series {
            let color = s.color;
            match s.style {
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
        }
        draw_legend(&bottom, &entries, (LEFT, 0), true)
    })
}

/// Bars with intervals (e.g. success rate with its 95% confidence interval),
/// values on `y` (round ticks over `y`). A label's lines (split at `\n`) and the
/// note are written under its bar, outside the data.
pub fn bar_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    bars: &[Bar],
    y: (f64, f64),
) -> Result<String> {
    bar_chart_with_lines(title, xlabel, ylabel, bars, y, &[])
}

/// [`bar_chart`] with horizontal reference lines (e.g. a goal), dashed across
/// the bars and labelled right of the plot area, outside the data.
pub fn bar_chart_with_lines(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    bars: &[Bar],
    y: (f64, f64),
    hlines: &[(f64, &str)],
) -> Result<String> {
    let n = bars.len().max(1);
    let yt = ticks(y.0, y.1, false);
    let (ya, yb) = (yt.range().start, yt.range().end);
    let lines = bars
        .iter()
        .map(|b| b.label.lines().count() + usize::from(!b.note.is_empty()))
        .max()
        .unwrap_or(1) as u32;
    let width = SIZE.0.max(100 + 70 * n as u32);
    svg((width, SIZE.1 + 14 * lines), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, (FONT, 15))
            .margin(12)
            .margin_right(if hlines.is_empty() { 12 } else { 70 })
            .x_label_area_size(14 * lines + 30)
            .y_label_area_size(60)
            .build_cartesian_2d(TickAxis::bare(0.0..n as f64), TickAxis::of(&yt))
            .map_err(err)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_desc(xlabel)
            .y_desc(ylabel)
            .bold_line_style(RGBColor(0xE4, 0xE4, 0xE4))
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        let clamp = |v: f64| v.clamp(ya, yb);
        chart
            .draw_series(bars.iter().enumerate().map(|(i, b)| {
                let i = i as f64;
                Rectangle::new(
                    [(i + 0.15, ya), (i + 0.85, clamp(b.value))],
                    COLORS[0].mix(0.75).filled(),
                )
            }))
            .map_err(err)?;
        for (v, label) in hlines {
            let v = clamp(*v);
            let style = RGBColor(0x55, 0x55, 0x55).stroke_width(1);
            chart
                .draw_series(DashedLineSeries::new(
                    [(0.0, v), (n as f64, v)],
                    6,
                    4,
                    style,
                ))
                .map_err(err)?;
            let (px, py) = chart.backend_coord(&(n as f64, v));
            root.draw(&Text::new(
                label.to_string(),
                (px + 6, py),
                (FONT, 12)
                    .into_font()
                    .color(&GREY)
                    .pos(Pos::new(HPos::Left, VPos::Center)),
            ))
            .map_err(err)?;
        }
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
            let (px, py) = chart.backend_coord(&(xm, ya));
            let under = b
                .label
                .lines()
                .map(|l| (l, GREY, 12))
                .chain((!b.note.is_empty()).then_some((b.note.as_str(), BLACK, 11)));
            for (k, (text, color, size)) in under.enumerate() {
                root.draw(&Text::new(
                    text.to_string(),
                    (px, py + 6 + 14 * k as i32),
                    (FONT, size)
                        .into_font()
                        .color(&color)
                        .pos(Pos::new(HPos::Center, VPos::Top)),
                ))
                .map_err(err)?;
            }
        }
        Ok(())
    })
}

/// A histogram of `values` in bins of a round width (1, 2 or 5 x 10^k, nearest
/// to `bins` of them) over their range (from 0 when all are positive); `xlabel`
/// carries the unit, the count axis is "trials" with whole ticks.
pub fn histogram(title: &str, xlabel: &str, values: &[f64], bins: usize) -> Result<String> {
    let (lo, hi) = range(values.iter().copied(), 0.0);
    let lo = lo.min(0.0);
    let width = nearest_125((hi - lo) / bins.max(1) as f64);
    let start = (lo / width + 1e-9).floor() * width;
    let nbins = (((hi - start) / width - 1e-9).ceil() as usize).max(1);
    let mut counts = vec![0usize; nbins];
    for v in values.iter().filter(|v| v.is_finite()) {
        let i = (((v - start) / width).floor().max(0.0) as usize).min(nbins - 1);
        counts[i] += 1;
    }
    let xt = ticks(start, start + nbins as f64 * width, false);
    let top = counts.iter().copied().max().unwrap_or(0) as f64;
    let yt = ticks(0.0, top, true);
    svg(SIZE, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, (FONT, 15))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(TickAxis::of(&xt), TickAxis::of(&yt))
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(xlabel)
            .y_desc("trials")
            .bold_line_style(RGBColor(0xE4, 0xE4, 0xE4))
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        chart
            .draw_series(counts.iter().enumerate().map(|(i, &c)| {
                let x = start + i as f64 * width;
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
/// Kalman gain, one panel each over a shared time axis with round ticks; the
/// prediction's start is marked; each panel's legend is right of its axes.
pub fn fig4(d: &Fig4Data, title: &str) -> Result<String> {
    let [blue, orange, green, yellow, pink, ..] = COLORS;
    let panels: [(&str, &str, Vec<Curve<'_>>); 4] = [
        (
            "Angle: measured (asin(z/l)) and estimated",
            "angle (deg)",
            vec![
                ("measured", yellow, &d.t_s, &d.measured_deg, true),
                ("estimated", blue, &d.t_s, &d.estimate_deg, false),
            ],
        ),
        (
            "300-step prediction against the measurements",
            "angle (deg)",
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
            "rate (deg/s)",
            vec![("rate", blue, &d.t_s, &d.rate_degps, false)],
        ),
        (
            "Kalman gain",
            "gain (1/m, 1/(s m))",
            vec![
                ("K angle", orange, &d.t_s, &d.gain_angle, false),
                ("K rate", pink, &d.t_s, &d.gain_rate, false),
            ],
        ),
    ];
    let (t0, t1) = range(d.t_s.iter().chain(&d.prediction_t_s).copied(), 0.0);
    let xt = ticks(t0, t1, false);
    const LEGEND_W: u32 = 130;
    svg((900, 1000), |root| {
        let root = root.titled(title, (FONT, 15)).map_err(err)?;
        for (area, (name, unit, curves)) in root.split_evenly((panels.len(), 1)).iter().zip(&panels)
        {
            let (plot_area, legend_area) =
                area.split_horizontally(area.dim_in_pixel().0 - LEGEND_W);
            let (v0, v1) = range(curves.iter().flat_map(|c| c.3.iter().copied()), 0.05);
            let yt = ticks(v0, v1, false);
            let mut chart = ChartBuilder::on(&plot_area)
                .caption(*name, (FONT, 13))
                .margin(8)
                .x_label_area_size(38)
                .y_label_area_size(75)
                .build_cartesian_2d(TickAxis::of(&xt), TickAxis::of(&yt))
                .map_err(err)?;
            chart
                .configure_mesh()
                .x_desc("time (s)")
                .y_desc(*unit)
                .bold_line_style(RGBColor(0xE4, 0xE4, 0xE4))
                .light_line_style(WHITE)
                .draw()
                .map_err(err)?;
            let (ya, yb) = (yt.range().start, yt.range().end);
            if d.prediction_from_s.is_finite() {
                let m = d.prediction_from_s;
                chart
                    .draw_series(DashedLineSeries::new(
                        [(m, ya), (m, yb)],
                        4,
                        3,
                        green.into(),
                    ))
                    .map_err(err)?;
            }
            let mut entries = Vec::new();
            for &(label, color, ts, vs, dots) in curves {
                let pts: Vec<(f64, f64)> = ts.iter().copied().zip(vs.iter().copied()).collect();
                if dots {
                    chart
                        .draw_series(finite(&pts).map(|p| Circle::new(p, 1.5, color.filled())))
                        .map_err(err)?;
                } else {
                    chart
                        .draw_series(LineSeries::new(finite(&pts), color.stroke_width(2)))
                        .map_err(err)?;
                }
                entries.push(Entry {
                    name: label,
                    color,
                    style: if dots { Style::Dots } else { Style::Line },
                });
            }
            draw_legend(&legend_area, &entries, (4, 30), false)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Checks the tick rules for data over `lo..=hi`; returns the ticks.
    fn checked(lo: f64, hi: f64, integer: bool) -> Ticks {
        let t = ticks(lo, hi, integer);
        let ctx = format!("{lo}..{hi} (integer {integer}): {t:?}");
        assert!([1, 2, 5].contains(&t.mantissa), "{ctx}");
        assert!(
            (MIN_TICKS..=MAX_TICKS).contains(&t.values.len()),
            "{} ticks: {ctx}",
            t.values.len()
        );
        let step = decimal(t.mantissa, t.exponent);
        for (i, v) in t.values.iter().enumerate() {
            // Every tick a whole multiple of the step, one step after the other.
            let k = v / step;
            assert!(
                (k - k.round()).abs() < 1e-6,
                "{v} is not a multiple of {step}: {ctx}"
            );
            if i > 0 {
                let d = v - t.values[i - 1];
                assert!((d - step).abs() <= 1e-9 * step.max(v.abs()), "{ctx}");
            }
            if integer {
                assert!(step >= 1.0 && v.fract() == 0.0, "{v} is not whole: {ctx}");
            }
        }
        // The ticks cover the data, and one step less would not.
        let (a, b) = (lo.min(hi), lo.max(hi));
        let r = t.range();
        assert!(r.start <= a + 1e-9 * a.abs().max(1.0), "{ctx}");
        assert!(r.end >= b - 1e-9 * b.abs().max(1.0), "{ctx}");
        assert!(
            r.start + step > a - 1e-9 * a.abs().max(1.0) || b - a == 0.0,
            "{ctx}"
        );
        // The labels are distinct, never "-0", and round ("0.6", not "0.6000000000000001").
        let labels: Vec<String> = t.values.iter().map(|v| t.label(*v)).collect();
        let mut uniq = labels.clone();
        uniq.dedup();
        assert_eq!(uniq, labels, "{ctx}");
        for l in &labels {
            let zero = l
                .trim_start_matches('-')
                .chars()
                .all(|c| c == '0' || c == '.');
            assert!(!(zero && l.starts_with('-')), "{l}: {ctx}");
        }
        for (l, v) in labels.iter().zip(&t.values) {
            let back: f64 = l.parse().unwrap();
            assert!((back - v).abs() <= 1e-9 * step, "{l} for {v}: {ctx}");
        }
        t
    }

    #[test]
    fn ticks_are_round_steps_covering_the_range() {
        // The odd axes: 0.205 / 0.41 / 0.614 ms, 6.6 / 13.2 trials, 1.12 / 1.309 / 1.498 s.
        let ms = checked(0.0, 0.614, false);
        assert_eq!(ms.values, [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]);
        assert_eq!(ms.label(0.3), "0.3");
        let trials = checked(0.0, 13.2, true);
        assert_eq!(trials.values, [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0]);
        assert_eq!(trials.label(14.0), "14");
        let s = checked(1.12, 1.498, false);
        assert_eq!(s.values.first(), Some(&1.1));
        assert_eq!(s.values.last(), Some(&1.5));
        assert_eq!(
            s.values.iter().map(|v| s.label(*v)).collect::<Vec<_>>(),
            [
                "1.10", "1.15", "1.20", "1.25", "1.30", "1.35", "1.40", "1.45", "1.50"
            ]
        );
        // Percent and distance axes.
        assert_eq!(
            checked(0.0, 100.0, false).values,
            [0.0, 20.0, 40.0, 60.0, 80.0, 100.0]
        );
        assert_eq!(
            checked(0.341, 0.809, false).values,
            [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
        );
        // Signed, negative and large ranges; "-0" is never a label.
        let signed = checked(-23.4, 41.0, false);
        assert!(signed.values.contains(&0.0));
        assert_eq!(signed.label(-0.0), "0");
        checked(-0.0031, -0.0012, false);
        checked(12_345.0, 98_765.0, false);
        checked(1e-7, 3e-7, false);
        // Integer axes: few trials still get whole ticks, at least four of them.
        assert_eq!(checked(0.0, 1.0, true).values, [0.0, 1.0, 2.0, 3.0]);
        assert_eq!(checked(0.0, 0.0, true).values.len(), MIN_TICKS);
        checked(3.0, 5.0, true);
        checked(0.0, 1000.0, true);
        // Degenerate input: one point, reversed, non-finite ends.
        checked(1.5, 1.5, false);
        checked(0.0, 0.0, false);
        checked(2.0, 1.0, false);
        let t = ticks(f64::NAN, f64::INFINITY, false);
        assert!((MIN_TICKS..=MAX_TICKS).contains(&t.values.len()), "{t:?}");
        // Many ranges, seeded: the rules hold for every one.
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..5000 {
            let scale = 10f64.powf(next() * 12.0 - 6.0);
            let lo = (next() - 0.5) * scale * 4.0;
            let hi = lo + next() * scale;
            checked(lo, hi, false);
            checked((lo * 100.0).round(), (hi * 100.0).round(), true);
        }
    }

    #[test]
    fn a_histograms_bins_are_round() {
        for (x, r) in [
            (0.0217, 0.02),
            (0.037, 0.05),
            (0.05, 0.05),
            (0.08, 0.1),
            (1.2, 1.0),
            (3.0, 2.0),
            (7.0, 5.0),
            (8.0, 10.0),
        ] {
            assert_eq!(nearest_125(x), r, "{x}");
        }
    }

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
        // A reference line's label is right of the bars, outside the data.
        let g = bar_chart_with_lines(
            "g",
            "x",
            "y",
            &[Bar {
                label: "lens".into(),
                value: 4.0,
                interval: Some((4.0, 4.5)),
                note: "4-4.5x".into(),
            }],
            (0.0, 8.0),
            &[(3.0, "goal 3x")],
        )
        .unwrap();
        let (goal_x, _) = text_at(&g, "goal 3x");
        let (bar_x, _) = text_at(&g, "lens");
        assert!(goal_x > bar_x + 30.0, "{g}");
        assert!(g.matches("<polyline").count() >= 1, "{g}");
        // Background, plot area and the bar.
        assert!(b.matches("<rect").count() >= 2, "{b}");
        let h = histogram("h", "ms", &[1.0, 2.0, 2.5, f64::NAN], 4).unwrap();
        // Bins of a round width (0.5 ms for about 4 over 0..2.5 ms): five in the bar
        // colour (plotters writes colours as #RRGGBB).
        assert_eq!(h.matches("fill=\"#0072B2\"").count(), 5, "{h}");
    }

    /// The `(x, y)` of the SVG text element that reads `text`.
    fn text_at(svg: &str, text: &str) -> (f64, f64) {
        let end = svg
            .find(&format!(">\n{text}\n</text>"))
            .unwrap_or_else(|| panic!("no text {text}"));
        let start = svg[..end].rfind("<text").unwrap();
        let attr = |name: &str| -> f64 {
            let tag = &svg[start..end];
            let from = tag.find(&format!(" {name}=\"")).unwrap() + name.len() + 3;
            tag[from..from + tag[from..].find('"').unwrap()]
                .parse()
                .unwrap()
        };
        (attr("x"), attr("y"))
    }

    /// The centres of the SVG circles (data dots).
    fn circles(svg: &str) -> Vec<(f64, f64)> {
        svg.split("<circle")
            .skip(1)
            .map(|c| {
                let attr = |name: &str| -> f64 {
                    let from = c.find(&format!(" {name}=\"")).unwrap() + name.len() + 3;
                    c[from..from + c[from..].find('"').unwrap()]
                        .parse()
                        .unwrap()
                };
                (attr("cx"), attr("cy"))
            })
            .collect()
    }

    #[test]
    fn legends_and_reference_labels_lie_outside_the_data() {
        // The isochrony figure's shape: dots along reference lines, legend and labels.
        let series: Vec<Series> = [1.2, 1.5, 2.0]
            .iter()
            .enumerate()
            .map(|(i, &t)| Series {
                name: format!("planned {t} s"),
                color: COLORS[i],
                style: Style::Dots,
                points: (0..40)
                    .map(|k| {
                        (
                            0.35 + 0.45 * f64::from(k) / 39.0,
                            t - 0.014 + 1e-4 * f64::from(k % 5),
                        )
                    })
                    .collect(),
            })
            .collect();
        let svg = xy_chart(
            "iso",
            "distance (m)",
            "movement time (s)",
            &series,
            &[(1.2, "1.2 s"), (1.5, "1.5 s"), (2.0, "2 s")],
        )
        .unwrap();
        let dots = circles(&svg);
        let max_x = dots.iter().map(|d| d.0).fold(f64::MIN, f64::max);
        let max_y = dots.iter().map(|d| d.1).fold(f64::MIN, f64::max);
        for s in &series {
            // Legend entries (text and their dot sample) below the axes.
            let (_, y) = text_at(&svg, &s.name);
            assert!(y >= f64::from(SIZE.1), "legend {} at y {y}", s.name);
        }
        let data: Vec<_> = dots.iter().filter(|d| d.1 < f64::from(SIZE.1)).collect();
        assert_eq!(data.len(), 3 * 40, "{svg}");
        assert!(
            max_y > f64::from(SIZE.1),
            "the legend's samples are dots too"
        );
        for label in ["1.2 s", "1.5 s", "2 s"] {
            let (x, _) = text_at(&svg, label);
            let right = data.iter().map(|d| d.0).fold(f64::MIN, f64::max);
            assert!(x > right, "{label} at x {x}, data up to {right} ({max_x})");
        }
        // Tick labels are the round ticks: 0.3 .. 0.8 m, 1.2 .. 2.0 s.
        for tick in ["0.3", "0.5", "0.8", "1.2", "1.6", "2.0"] {
            text_at(&svg, tick);
        }
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
        // Each panel's legend right of its axes (the plot areas end 130 px before the edge).
        for name in ["estimated", "predicted", "rate", "K angle", "K rate"] {
            let (x, _) = text_at(&svg, name);
            assert!(x > f64::from(900 - 130), "{name} at x {x}");
        }
        // Five lines over the four panels, each with its legend sample.
        assert!(svg.matches("<polyline").count() >= 5, "{svg}");
        assert!(svg.matches("<circle").count() >= 2 * 50, "{svg}");
    }
}
