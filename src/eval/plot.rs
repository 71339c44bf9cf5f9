//! The evaluation's charts — grouped bars (Fig. 3, Table 5, Figs. 16–17) and
//! grouped box plots (Figs. 11–15) — each written as PNG and SVG.
//!
//! Text is drawn with a TrueType font read from the system at run time
//! (DejaVu Sans and a few common alternatives), so the build needs no
//! fontconfig; without any font the plot is reported as an error and the
//! experiment keeps its CSV and summary.

use super::table::quantile;
use super::EvalError;
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint, Ranged};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

const WIDTH: u32 = 1200;
const HEIGHT: u32 = 640;

/// Series colours (colour-blind-safe "tab10" order).
const PALETTE: [RGBColor; 8] = [
    RGBColor(214, 39, 40),
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

/// Where fonts usually live on Debian/Ubuntu, Fedora and macOS.
const FONT_CANDIDATES: [&str; 6] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/Library/Fonts/Arial.ttf",
];

/// Register a sans-serif font with plotters once; the error names what is missing.
fn ensure_font() -> Result<(), String> {
    static FONT: OnceLock<Result<(), String>> = OnceLock::new();
    FONT.get_or_init(|| {
        let bytes = FONT_CANDIDATES
            .iter()
            .find_map(|p| std::fs::read(p).ok())
            .ok_or_else(|| {
                "no TrueType font found (install fonts-dejavu-core); plots skipped".to_string()
            })?;
        // Plotters keeps fonts for the life of the process.
        let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
            .map_err(|_| "the system font could not be parsed".to_string())
    })
    .clone()
}

/// Labels of a grouped chart: categories along x, one series per colour.
#[derive(Debug, Clone)]
pub struct Grouped {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub categories: Vec<String>,
    pub series: Vec<String>,
}

/// Grouped bars: `values[series][category]` (missing values leave a gap).
/// Writes `<stem>.png` and `<stem>.svg`; returns their paths.
pub fn bars(
    stem: &Path,
    spec: &Grouped,
    values: &[Vec<Option<f64>>],
) -> Result<Vec<PathBuf>, EvalError> {
    render_both(stem, &Bars { spec, values })
}

/// Grouped box plots of `samples[series][category]` (Tukey whiskers at 1.5
/// IQR, outliers as crosses; outliers above the axis are pinned to its top).
pub fn boxes(
    stem: &Path,
    spec: &Grouped,
    samples: &[Vec<Vec<f64>>],
) -> Result<Vec<PathBuf>, EvalError> {
    render_both(stem, &Boxes { spec, samples })
}

/// Lines over a numeric x axis: `series[k]` is `(name, points)`, each
/// point `(x, y)` (non-finite ones are skipped). Writes `<stem>.png` and
/// `<stem>.svg`; returns their paths.
pub fn lines(
    stem: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<Vec<PathBuf>, EvalError> {
    render_both(
        stem,
        &Lines {
            title,
            x_label,
            y_label,
            series,
        },
    )
}

type DrawResult = Result<(), String>;

/// An x axis of `n` categories: category `i` spans `i..i+1`, labelled at its centre.
#[derive(Debug, Clone, Copy)]
struct CategoryAxis {
    n: usize,
}

impl Ranged for CategoryAxis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        let f = value / self.n as f64;
        limit.0 + (f64::from(limit.1 - limit.0) * f).round() as i32
    }

    fn key_points<Hint: KeyPointHint>(&self, _hint: Hint) -> Vec<f64> {
        (0..self.n).map(|i| i as f64 + 0.5).collect()
    }

    fn range(&self) -> std::ops::Range<f64> {
        0.0..self.n as f64
    }
}

/// A chart that can be drawn on any plotters backend.
trait Chart {
    fn draw<DB: DrawingBackend>(&self, root: DrawingArea<DB, Shift>) -> DrawResult;
}

struct Bars<'a> {
    spec: &'a Grouped,
    values: &'a [Vec<Option<f64>>],
}

impl Chart for Bars<'_> {
    fn draw<DB: DrawingBackend>(&self, root: DrawingArea<DB, Shift>) -> DrawResult {
        draw_bars(root, self.spec, self.values)
    }
}

struct Boxes<'a> {
    spec: &'a Grouped,
    samples: &'a [Vec<Vec<f64>>],
}

impl Chart for Boxes<'_> {
    fn draw<DB: DrawingBackend>(&self, root: DrawingArea<DB, Shift>) -> DrawResult {
        draw_boxes(root, self.spec, self.samples)
    }
}

struct Lines<'a> {
    title: &'a str,
    x_label: &'a str,
    y_label: &'a str,
    series: &'a [(String, Vec<(f64, f64)>)],
}

impl Chart for Lines<'_> {
    fn draw<DB: DrawingBackend>(&self, root: DrawingArea<DB, Shift>) -> DrawResult {
        root.fill(&WHITE).map_err(s)?;
        let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
        let pts = || {
            self.series
                .iter()
                .flat_map(|(_, v)| v.iter().filter(finite))
        };
        let x0 = pts().map(|p| p.0).fold(f64::INFINITY, f64::min);
        let x1 = pts().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
        let (x0, x1) = if x0 < x1 { (x0, x1) } else { (0.0, 1.0) };
        let pad = 0.04 * (x1 - x0);
        let top = y_top(pts().map(|p| p.1).fold(0.0, f64::max));
        let mut chart = ChartBuilder::on(&root)
            .caption(self.title, ("sans-serif", 24))
            .margin(14)
            .x_label_area_size(46)
            .y_label_area_size(80)
            .build_cartesian_2d(x0 - pad..x1 + pad, 0f64..top)
            .map_err(s)?;
        chart
            .configure_mesh()
            .x_desc(self.x_label)
            .y_desc(self.y_label)
            .label_style(("sans-serif", 15))
            .draw()
            .map_err(s)?;
        for (k, (name, v)) in self.series.iter().enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            let v: Vec<(f64, f64)> = v.iter().filter(finite).copied().collect();
            chart
                .draw_series(LineSeries::new(v.clone(), color.stroke_width(2)))
                .map_err(s)?
                .label(name.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
                });
            chart
                .draw_series(v.into_iter().map(|p| Circle::new(p, 4, color.filled())))
                .map_err(s)?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .position(SeriesLabelPosition::UpperLeft)
            .draw()
            .map_err(s)?;
        root.present().map_err(s)
    }
}

fn render_both(stem: &Path, chart: &impl Chart) -> Result<Vec<PathBuf>, EvalError> {
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    let err = |path: &Path| {
        let path = path.to_path_buf();
        move |reason: String| EvalError::Plot { path, reason }
    };
    ensure_font().map_err(err(&png))?;
    let mut buf = vec![255u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        chart.draw(root).map_err(err(&png))?;
    }
    image::save_buffer(&png, &buf, WIDTH, HEIGHT, image::ExtendedColorType::Rgb8)
        .map_err(|e| err(&png)(e.to_string()))?;
    {
        let root = SVGBackend::new(&svg, (WIDTH, HEIGHT)).into_drawing_area();
        chart.draw(root).map_err(err(&svg))?;
    }
    Ok(vec![png, svg])
}

fn s<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// The y range `0..top` with some headroom; at least `0..1`.
fn y_top(max: f64) -> f64 {
    if max.is_finite() && max > 0.0 {
        max * 1.12
    } else {
        1.0
    }
}

fn draw_bars<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    spec: &Grouped,
    values: &[Vec<Option<f64>>],
) -> DrawResult {
    root.fill(&WHITE).map_err(s)?;
    let n = spec.categories.len().max(1);
    let max = values
        .iter()
        .flatten()
        .flatten()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    let mut chart = ChartBuilder::on(&root)
        .caption(&spec.title, ("sans-serif", 24))
        .margin(14)
        .x_label_area_size(46)
        .y_label_area_size(80)
        // Headroom above the tallest bar for the legend's rows (~5 % of the
        // plot's height each), so it covers no bar.
        .build_cartesian_2d(
            CategoryAxis { n },
            0f64..y_top(max) * (1.0 + 0.05 * spec.series.len() as f64),
        )
        .map_err(s)?;
    let cats = spec.categories.clone();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_desc(spec.x_label.as_str())
        .y_desc(spec.y_label.as_str())
        .x_label_formatter(&|x: &f64| cats.get(x.floor() as usize).cloned().unwrap_or_default())
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(s)?;
    let ns = spec.series.len().max(1) as f64;
    let width = 0.8 / ns;
    for (k, name) in spec.series.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let row = values.get(k).cloned().unwrap_or_default();
        chart
            .draw_series(row.iter().enumerate().filter_map(|(i, v)| {
                let v = (*v)?;
                let x0 = i as f64 + 0.1 + k as f64 * width;
                v.is_finite()
                    .then(|| Rectangle::new([(x0, 0.0), (x0 + width * 0.92, v)], color.filled()))
            }))
            .map_err(s)?
            .label(name.as_str())
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], color.filled()));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 15))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(s)?;
    root.present().map_err(s)
}

/// Tukey's box: quartiles, whiskers to the last datum within 1.5 IQR, outliers.
struct TukeyBox {
    /// Finite samples in the box.
    n: usize,
    q1: f64,
    q2: f64,
    q3: f64,
    lo: f64,
    hi: f64,
    outliers: Vec<f64>,
}

/// The largest whisker the y axis is scaled to: that of the boxes drawn
/// from a fair sample (at least [`FAIR_BOX_MIN`] values and a quarter of the
/// largest box's) whose whisker is within [`WILD_FACTOR`] of the median
/// box's (the lower median of an even count). Not that of a box of a few
/// wild values (a detector that reads a quarter of the frames in murky
/// water, some of them metres off), which would flatten every other box to
/// the axis; such a box is cut at the top.
fn scale_max<'a>(boxes: impl Iterator<Item = &'a TukeyBox> + Clone) -> f64 {
    let most = boxes.clone().map(|b| b.n).max().unwrap_or(0);
    let fair = FAIR_BOX_MIN.max(most / 4);
    let mut tops: Vec<f64> = boxes.clone().map(|b| b.hi).collect();
    tops.sort_by(f64::total_cmp);
    let typical = tops
        .get(tops.len().saturating_sub(1) / 2)
        .copied()
        .unwrap_or(0.0);
    let within = |b: &&TukeyBox| typical <= 0.0 || b.hi <= WILD_FACTOR * typical;
    let over = |min_n: usize| {
        boxes
            .clone()
            .filter(|b| b.n >= min_n)
            .filter(within)
            .map(|b| b.hi)
            .fold(0.0, f64::max)
    };
    match over(fair) {
        m if m > 0.0 => m,
        _ => tops.last().copied().unwrap_or(0.0),
    }
}

/// Fewest values for a box to set the y axis' scale ([`scale_max`]).
const FAIR_BOX_MIN: usize = 5;
/// A whisker more than this many times the median box's does not set the
/// y axis' scale ([`scale_max`]).
const WILD_FACTOR: f64 = 30.0;

fn tukey(v: &[f64]) -> Option<TukeyBox> {
    let (q1, q2, q3) = (quantile(v, 0.25)?, quantile(v, 0.5)?, quantile(v, 0.75)?);
    let iqr = q3 - q1;
    let (fence_lo, fence_hi) = (q1 - 1.5 * iqr, q3 + 1.5 * iqr);
    let inside: Vec<f64> = v
        .iter()
        .copied()
        .filter(|x| x.is_finite() && *x >= fence_lo && *x <= fence_hi)
        .collect();
    let lo = inside.iter().copied().fold(q1, f64::min);
    let hi = inside.iter().copied().fold(q3, f64::max);
    let outliers = v
        .iter()
        .copied()
        .filter(|x| x.is_finite() && (*x < fence_lo || *x > fence_hi))
        .collect();
    Some(TukeyBox {
        n: v.iter().filter(|x| x.is_finite()).count(),
        q1,
        q2,
        q3,
        lo,
        hi,
        outliers,
    })
}

fn draw_boxes<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    spec: &Grouped,
    samples: &[Vec<Vec<f64>>],
) -> DrawResult {
    root.fill(&WHITE).map_err(s)?;
    let n = spec.categories.len().max(1);
    let boxes: Vec<Vec<Option<TukeyBox>>> = samples
        .iter()
        .map(|row| row.iter().map(|v| tukey(v)).collect())
        .collect();
    let top = y_top(scale_max(boxes.iter().flatten().flatten()) * 1.6);
    let mut chart = ChartBuilder::on(&root)
        .caption(&spec.title, ("sans-serif", 24))
        .margin(14)
        .x_label_area_size(46)
        .y_label_area_size(80)
        .build_cartesian_2d(CategoryAxis { n }, 0f64..top)
        .map_err(s)?;
    let cats = spec.categories.clone();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_desc(spec.x_label.as_str())
        .y_desc(spec.y_label.as_str())
        .x_label_formatter(&|x: &f64| cats.get(x.floor() as usize).cloned().unwrap_or_default())
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(s)?;
    let ns = spec.series.len().max(1) as f64;
    let width = 0.8 / ns;
    for (k, name) in spec.series.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let mut shapes: Vec<PathElement<(f64, f64)>> = Vec::new();
        let mut crosses: Vec<(f64, f64)> = Vec::new();
        for (i, b) in boxes.get(k).into_iter().flatten().enumerate() {
            let Some(b) = b else { continue };
            let x0 = i as f64 + 0.1 + k as f64 * width + 0.08 * width;
            let x1 = x0 + 0.84 * width;
            let xm = 0.5 * (x0 + x1);
            let c = |v: f64| v.min(top);
            let st = color.stroke_width(2);
            shapes.push(PathElement::new(
                vec![
                    (x0, c(b.q1)),
                    (x1, c(b.q1)),
                    (x1, c(b.q3)),
                    (x0, c(b.q3)),
                    (x0, c(b.q1)),
                ],
                st,
            ));
            shapes.push(PathElement::new(
                vec![(x0, c(b.q2)), (x1, c(b.q2))],
                color.stroke_width(3),
            ));
            shapes.push(PathElement::new(vec![(xm, c(b.q3)), (xm, c(b.hi))], st));
            shapes.push(PathElement::new(vec![(xm, c(b.q1)), (xm, c(b.lo))], st));
            let (w0, w1) = (xm - 0.25 * width, xm + 0.25 * width);
            shapes.push(PathElement::new(vec![(w0, c(b.hi)), (w1, c(b.hi))], st));
            shapes.push(PathElement::new(vec![(w0, c(b.lo)), (w1, c(b.lo))], st));
            crosses.extend(b.outliers.iter().map(|&o| (xm, o.min(top * 0.995))));
        }
        chart
            .draw_series(shapes)
            .map_err(s)?
            .label(name.as_str())
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], color.filled()));
        chart
            .draw_series(
                crosses
                    .into_iter()
                    .map(|p| Cross::new(p, 4, color.stroke_width(1))),
            )
            .map_err(s)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 15))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(s)?;
    root.present().map_err(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_box_of_a_few_wild_values_does_not_set_the_scale() {
        let good: Vec<f64> = (0..20).map(|i| 5.0 + 0.1 * f64::from(i)).collect();
        let wild = [4.0, 5000.0, 5500.0, 5900.0];
        // Five values (a fair count), but a whisker 800x the others'.
        let wild5 = [3.0, 4.0, 5000.0, 5500.0, 5900.0];
        let boxes: Vec<TukeyBox> = [&good[..], &good[..], &wild[..], &wild5[..]]
            .iter()
            .filter_map(|v| tukey(v))
            .collect();
        let m = scale_max(boxes.iter());
        assert!((m - 6.9).abs() < 1e-9, "{m}");
        // A box 20x the others (an unrestored baseline in murky water) sets it.
        let far: Vec<f64> = good.iter().map(|v| 20.0 * v).collect();
        let boxes: Vec<TukeyBox> = [&good[..], &good[..], &far[..]]
            .iter()
            .filter_map(|v| tukey(v))
            .collect();
        assert!((scale_max(boxes.iter()) - 138.0).abs() < 1e-9);
        // With only small boxes, they set it.
        let only_wild: Vec<TukeyBox> = tukey(&wild).into_iter().collect();
        assert!(scale_max(only_wild.iter()) > 5000.0);
    }
}
