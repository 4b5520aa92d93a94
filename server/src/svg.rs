//! Small SVG charts for reports (`isochron eval`): lines, scatter, bars with error
//! bars, histograms. Standalone documents, no scripts, readable in any browser.

use std::fmt::Write as _;

/// Okabe-Ito colours (distinguishable with colour-vision deficiencies).
pub const COLORS: [&str; 7] = [
    "#0072B2", "#D55E00", "#009E73", "#E69F00", "#CC79A7", "#56B4E9", "#777777",
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
    pub color: &'static str,
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

const W: f64 = 720.0;
const H: f64 = 360.0;
const L: f64 = 70.0;
const R: f64 = 20.0;
const T: f64 = 40.0;
const B: f64 = 50.0;

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn tick(v: f64) -> String {
    if v != 0.0 && (v.abs() < 0.01 || v.abs() >= 1e5) {
        format!("{v:.1e}")
    } else if (v - v.round()).abs() < 1e-9 {
        format!("{v:.0}")
    } else {
        format!("{v:.3}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_owned()
    }
}

/// The frame of a chart: axes ranges and the mapping to pixels.
struct Frame {
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
}

impl Frame {
    fn x(&self, v: f64) -> f64 {
        L + (v - self.x0) / (self.x1 - self.x0) * (W - L - R)
    }
    fn y(&self, v: f64) -> f64 {
        T + (H - T - B) * (1.0 - (v - self.y0) / (self.y1 - self.y0))
    }
}

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

fn open(svg: &mut String, title: &str, xlabel: &str, ylabel: &str, f: &Frame, xticks: bool) {
    let _ = writeln!(
        svg,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(
        svg,
        r##"<rect width="100%" height="100%" fill="white"/><text x="{L}" y="22" font-size="15" font-weight="bold">{}</text>"##,
        esc(title)
    );
    let _ = writeln!(
        svg,
        r##"<rect x="{L}" y="{T}" width="{}" height="{}" fill="none" stroke="#888"/>"##,
        W - L - R,
        H - T - B
    );
    for i in 0..=5 {
        let v = f.y0 + (f.y1 - f.y0) * f64::from(i) / 5.0;
        let y = f.y(v);
        let _ = writeln!(
            svg,
            r##"<line x1="{L}" x2="{}" y1="{y:.1}" y2="{y:.1}" stroke="#eee"/><text x="{}" y="{:.1}" text-anchor="end" fill="#444">{}</text>"##,
            W - R,
            L - 6.0,
            y + 4.0,
            tick(v)
        );
        if xticks {
            let xv = f.x0 + (f.x1 - f.x0) * f64::from(i) / 5.0;
            let _ = writeln!(
                svg,
                r##"<text x="{:.1}" y="{}" text-anchor="middle" fill="#444">{}</text>"##,
                f.x(xv),
                H - B + 16.0,
                tick(xv)
            );
        }
    }
    let _ = writeln!(
        svg,
        r##"<text x="{}" y="{}" text-anchor="middle">{}</text><text transform="translate(16 {}) rotate(-90)" text-anchor="middle">{}</text>"##,
        L + (W - L - R) / 2.0,
        H - 12.0,
        esc(xlabel),
        T + (H - T - B) / 2.0,
        esc(ylabel)
    );
}

/// Lines and dots over numeric axes, with optional horizontal reference lines.
pub fn xy_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    series: &[Series],
    hlines: &[(f64, &str)],
) -> String {
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
    let f = Frame { x0, x1, y0, y1 };
    let mut svg = String::new();
    open(&mut svg, title, xlabel, ylabel, &f, true);
    for (v, label) in hlines {
        let y = f.y(*v);
        let _ = writeln!(
            svg,
            r##"<line x1="{L}" x2="{}" y1="{y:.1}" y2="{y:.1}" stroke="#555" stroke-dasharray="6 4"/><text x="{}" y="{:.1}" text-anchor="end" fill="#555">{}</text>"##,
            W - R,
            W - R - 4.0,
            y - 4.0,
            esc(label)
        );
    }
    for (i, s) in series.iter().enumerate() {
        let pts = s
            .points
            .iter()
            .filter(|p| p.0.is_finite() && p.1.is_finite());
        match s.style {
            Style::Dots => {
                let _ = write!(svg, r#"<g fill="{}" fill-opacity="0.7">"#, s.color);
                for p in pts {
                    let _ = write!(
                        svg,
                        r#"<circle cx="{:.1}" cy="{:.1}" r="2.5"/>"#,
                        f.x(p.0),
                        f.y(p.1)
                    );
                }
                svg.push_str("</g>\n");
            }
            Style::Line | Style::Dashed => {
                let dash = if s.style == Style::Dashed {
                    r#" stroke-dasharray="7 4""#
                } else {
                    ""
                };
                let _ = write!(
                    svg,
                    r#"<polyline fill="none" stroke="{}" stroke-width="2"{dash} points=""#,
                    s.color
                );
                for p in pts {
                    let _ = write!(svg, "{:.1},{:.1} ", f.x(p.0), f.y(p.1));
                }
                svg.push_str("\"/>\n");
            }
        }
        let _ = writeln!(
            svg,
            r#"<text x="{}" y="{}" fill="{}">{}</text>"#,
            L + 10.0,
            T + 16.0 + 15.0 * i as f64,
            s.color,
            esc(&s.name)
        );
    }
    svg.push_str("</svg>\n");
    svg
}

/// Bars with intervals (e.g. success rate with its 95% confidence interval).
pub fn bar_chart(title: &str, xlabel: &str, ylabel: &str, bars: &[Bar], y: (f64, f64)) -> String {
    let f = Frame {
        x0: 0.0,
        x1: bars.len().max(1) as f64,
        y0: y.0,
        y1: y.1,
    };
    let mut svg = String::new();
    open(&mut svg, title, xlabel, ylabel, &f, false);
    for (i, b) in bars.iter().enumerate() {
        let (xa, xb) = (f.x(i as f64 + 0.15), f.x(i as f64 + 0.85));
        let top = f.y(b.value.clamp(y.0, y.1));
        let _ = writeln!(
            svg,
            r##"<rect x="{xa:.1}" y="{top:.1}" width="{:.1}" height="{:.1}" fill="{}" fill-opacity="0.75"/>"##,
            xb - xa,
            (f.y(y.0) - top).max(0.0),
            COLORS[0]
        );
        if let Some((lo, hi)) = b.interval {
            let xm = (xa + xb) / 2.0;
            let (ya, yb) = (f.y(lo.clamp(y.0, y.1)), f.y(hi.clamp(y.0, y.1)));
            let _ = writeln!(
                svg,
                r##"<path d="M{xm:.1} {ya:.1}V{yb:.1}M{:.1} {ya:.1}H{:.1}M{:.1} {yb:.1}H{:.1}" stroke="#222" stroke-width="1.5"/>"##,
                xm - 6.0,
                xm + 6.0,
                xm - 6.0,
                xm + 6.0
            );
        }
        let _ = writeln!(
            svg,
            r##"<text x="{:.1}" y="{}" text-anchor="middle" fill="#444">{}</text><text x="{:.1}" y="{:.1}" text-anchor="middle" font-size="11">{}</text>"##,
            (xa + xb) / 2.0,
            H - B + 16.0,
            esc(&b.label),
            (xa + xb) / 2.0,
            f.y(y.1) + 14.0,
            esc(&b.note)
        );
    }
    svg.push_str("</svg>\n");
    svg
}

/// A histogram of `values` in `bins` equal bins over their range.
pub fn histogram(title: &str, xlabel: &str, values: &[f64], bins: usize) -> String {
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
    let f = Frame {
        x0: lo,
        x1: hi,
        y0: 0.0,
        y1: top * 1.1,
    };
    let mut svg = String::new();
    open(&mut svg, title, xlabel, "trials", &f, true);
    for (i, c) in counts.iter().enumerate() {
        let (xa, xb) = (f.x(lo + i as f64 * width), f.x(lo + (i + 1) as f64 * width));
        let y = f.y(*c as f64);
        let _ = writeln!(
            svg,
            r##"<rect x="{xa:.1}" y="{y:.1}" width="{:.1}" height="{:.1}" fill="{}" stroke="white"/>"##,
            (xb - xa).max(0.5),
            f.y(0.0) - y,
            COLORS[0]
        );
    }
    svg.push_str("</svg>\n");
    svg
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
        );
        assert!(s.starts_with("<svg") && s.trim_end().ends_with("</svg>"));
        assert!(s.contains("a&lt;b"));
        assert_eq!(s.matches("<polyline").count(), 1);
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
        );
        assert_eq!(b.matches("<rect").count(), 3);
        let h = histogram("h", "ms", &[1.0, 2.0, 2.5, f64::NAN], 4);
        assert_eq!(h.matches("fill=\"#0072B2\"").count(), 4);
    }
}
