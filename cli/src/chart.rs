//! Charts of the bench command, as SVG and PNG (plotters), drawn with the bundled DejaVu Sans
//! (`assets/fonts`) so that they render the same on any machine, without system fonts.

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

/// The font every chart uses (Bitstream Vera / DejaVu licence, `assets/fonts/LICENSE-DejaVu.txt`).
const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
/// Chart size in pixels (PNG) and user units (SVG).
const SIZE: (u32, u32) = (900, 600);

/// How a series is drawn.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Markers joined by a line, in the points' order.
    Line,
    /// Markers only.
    Markers,
    /// A thin line without markers (a fitted model).
    Fit,
    /// The Pareto front: a thin line through hollow rings in order of x, black (in the
    /// series' colour when a chart has several fronts).
    Front,
}

/// One named set of points.
pub struct Series {
    /// Legend text (empty: not in the legend).
    pub name: String,
    /// (x, y) points, in drawing order.
    pub points: Vec<(f64, f64)>,
    /// How it is drawn.
    pub style: Style,
    /// Palette index of its colour (series with the same index share a colour).
    pub color: usize,
    /// Text beside each point (empty: none).
    pub labels: Vec<String>,
}

impl Series {
    /// Markers joined by a line, in palette colour `color`.
    pub fn line(name: impl Into<String>, points: Vec<(f64, f64)>, color: usize) -> Self {
        Series {
            name: name.into(),
            points,
            style: Style::Line,
            color,
            labels: Vec::new(),
        }
    }

    /// The same series drawn as `style`.
    pub fn styled(mut self, style: Style) -> Self {
        self.style = style;
        self
    }

    /// The same series with a text beside each point.
    pub fn labelled(mut self, labels: Vec<String>) -> Self {
        self.labels = labels;
        self
    }
}

/// Where the legend goes.
#[derive(Clone, Copy)]
pub enum Legend {
    /// Top left corner.
    UpperLeft,
    /// Top right corner.
    UpperRight,
    /// Bottom left corner.
    LowerLeft,
    /// Bottom right corner.
    LowerRight,
}

/// A chart: title, axis labels, series, and whether each axis is logarithmic.
pub struct Chart {
    /// Title above the plot.
    pub title: String,
    /// X axis label.
    pub x_label: String,
    /// Y axis label.
    pub y_label: String,
    /// Logarithmic x and y axes.
    pub log: (bool, bool),
    /// The lines.
    pub series: Vec<Series>,
    /// Where the legend goes.
    pub legend: Legend,
}

fn register_font() -> Result<()> {
    static DONE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let ok = *DONE.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(anyhow!("the bundled chart font could not be loaded"))
    }
}

/// Writes `chart` as `<stem>.svg` and `<stem>.png`, each atomically.
pub fn write(chart: &Chart, stem: &Path) -> Result<()> {
    register_font()?;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        draw(chart, root)?;
    }
    crate::write_file_atomic(&stem.with_extension("svg"), svg.as_bytes())?;
    let mut rgb = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area();
        draw(chart, root)?;
    }
    let mut png_bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png_bytes, SIZE.0, SIZE.1);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(&rgb)?;
    }
    crate::write_file_atomic(&stem.with_extension("png"), &png_bytes)?;
    Ok(())
}

/// The range of `values`, padded (multiplicatively on a log axis).
fn range(values: impl Iterator<Item = f64>, log: bool) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && (!log || *v > 0.0))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return if log { 0.1..10.0 } else { 0.0..1.0 };
    }
    if log {
        lo / 1.5..hi * 1.5
    } else {
        let pad = ((hi - lo) * 0.05).max(1e-9);
        (lo - pad).min(0.0f64.max(lo - pad))..hi + pad
    }
}

/// Tick values of a logarithmic axis over `r`: 1, 2 and 5 times each power of ten, thinned
/// to 1 and 3 when the range spans more than three decades and to powers of ten beyond six.
fn log_ticks(r: &std::ops::Range<f64>) -> Vec<f64> {
    if !(r.start > 0.0 && r.end > r.start) {
        return Vec::new();
    }
    let (lo, hi) = (r.start.log10().floor() as i32, r.end.log10().ceil() as i32);
    let steps: &[f64] = match hi - lo {
        0..=3 => &[1.0, 2.0, 5.0],
        4..=6 => &[1.0, 3.0],
        _ => &[1.0],
    };
    (lo..=hi)
        .flat_map(|e| steps.iter().map(move |m| m * 10f64.powi(e)))
        .filter(|v| r.contains(v))
        .collect()
}

/// `v` with two significant digits at most, without trailing zeros (axis labels).
fn short(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let decimals = (1 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Approximate width in pixels of `text` at the 11 px label size.
fn label_width(text: &str) -> i32 {
    (text.chars().count() as f64 * 6.5).ceil() as i32
}

/// The offset of a label from its point (pixel `(px, py)`): the first of eight spots around
/// the point whose box overlaps no label placed before (above right, below right, above left,
/// below left, then further out), else the first; the box is added to `placed`.
fn place_label(px: i32, py: i32, text: &str, placed: &mut Vec<(i32, i32, i32, i32)>) -> (i32, i32) {
    let (w, h) = (label_width(text), 12);
    let spots = [
        (6, -14),
        (6, 3),
        (-6 - w, -14),
        (-6 - w, 3),
        (6, -28),
        (6, 17),
        (-6 - w, -28),
        (-6 - w, 17),
    ];
    let boxed = |(dx, dy): (i32, i32)| (px + dx, py + dy, px + dx + w, py + dy + h);
    let overlaps = |a: (i32, i32, i32, i32), b: &(i32, i32, i32, i32)| {
        a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3
    };
    let chosen = spots
        .iter()
        .copied()
        .find(|&o| !placed.iter().any(|b| overlaps(boxed(o), b)))
        .unwrap_or(spots[0]);
    placed.push(boxed(chosen));
    chosen
}

fn draw<DB: DrawingBackend>(chart: &Chart, root: DrawingArea<DB, Shift>) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("drawing the chart: {e:?}");
    root.fill(&WHITE).map_err(err)?;
    let xs = range(
        chart
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.0)),
        chart.log.0,
    );
    let ys = range(
        chart
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1)),
        chart.log.1,
    );
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(&chart.title, ("sans-serif", 18))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(72);
    // The four axis combinations are different coordinate types in plotters.
    macro_rules! plot {
        ($x:expr, $y:expr) => {{
            let mut c = builder.build_cartesian_2d($x, $y).map_err(err)?;
            c.configure_mesh()
                .max_light_lines(2)
                .x_label_formatter(&|v| short(*v))
                .y_label_formatter(&|v| short(*v))
                .x_desc(chart.x_label.as_str())
                .y_desc(chart.y_label.as_str())
                .label_style(("sans-serif", 14))
                .axis_desc_style(("sans-serif", 16))
                .draw()
                .map_err(err)?;
            // Labels already placed, as pixel boxes: a new one takes the first free spot
            // around its point.
            let mut placed: Vec<(i32, i32, i32, i32)> = Vec::new();
            // One front is black; several (one per object) take their series' colours.
            let fronts = chart
                .series
                .iter()
                .filter(|s| s.style == Style::Front)
                .count();
            for s in &chart.series {
                let color = if s.style == Style::Front && fronts == 1 {
                    BLACK.to_rgba()
                } else {
                    Palette99::pick(s.color).to_rgba()
                };
                let width = if matches!(s.style, Style::Fit | Style::Front) {
                    1
                } else {
                    2
                };
                let mut points = s.points.clone();
                if s.style == Style::Front {
                    // A front is a staircase in x: drawn in any other order its line crosses
                    // itself.
                    points.sort_by(|a, b| a.0.total_cmp(&b.0));
                }
                if s.style != Style::Markers {
                    let drawn = c
                        .draw_series(LineSeries::new(
                            points.iter().copied(),
                            color.stroke_width(width),
                        ))
                        .map_err(err)?;
                    if !s.name.is_empty() {
                        drawn.label(s.name.as_str()).legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                        });
                    }
                }
                match s.style {
                    Style::Fit => {}
                    Style::Front => {
                        c.draw_series(
                            s.points
                                .iter()
                                .map(|p| Circle::new(*p, 7, color.stroke_width(1))),
                        )
                        .map_err(err)?;
                    }
                    Style::Line | Style::Markers => {
                        let drawn = c
                            .draw_series(
                                s.points.iter().map(|p| Circle::new(*p, 3, color.filled())),
                            )
                            .map_err(err)?;
                        if s.style == Style::Markers && !s.name.is_empty() {
                            drawn
                                .label(s.name.as_str())
                                .legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
                        }
                    }
                }
                if !s.labels.is_empty() {
                    let mut texts = Vec::new();
                    for (p, t) in s.points.iter().zip(&s.labels) {
                        let (px, py) = c.backend_coord(p);
                        let offset = place_label(px, py, t, &mut placed);
                        texts.push((*p, t.clone(), offset));
                    }
                    c.draw_series(texts.into_iter().map(|(p, t, offset)| {
                        EmptyElement::at(p)
                            + Text::new(t, offset, ("sans-serif", 11).into_font().color(&color))
                    }))
                    .map_err(err)?;
                }
            }
            c.configure_series_labels()
                .label_font(("sans-serif", 14))
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .position(match chart.legend {
                    Legend::UpperLeft => SeriesLabelPosition::UpperLeft,
                    Legend::UpperRight => SeriesLabelPosition::UpperRight,
                    Legend::LowerRight => SeriesLabelPosition::LowerRight,
                    Legend::LowerLeft => SeriesLabelPosition::LowerLeft,
                })
                .draw()
                .map_err(err)?;
        }};
    }
    let (kx, ky) = (log_ticks(&xs), log_ticks(&ys));
    match chart.log {
        (true, true) => plot!(
            xs.log_scale().with_key_points(kx),
            ys.log_scale().with_key_points(ky)
        ),
        (true, false) => plot!(xs.log_scale().with_key_points(kx), ys),
        (false, true) => plot!(xs, ys.log_scale().with_key_points(ky)),
        (false, false) => plot!(xs, ys),
    }
    root.present().map_err(err)?;
    Ok(())
}
