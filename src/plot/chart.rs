//! One line chart drawn on one drawing area: title, axes with tick labels and descriptions,
//! one coloured line per series (a dot for a single point) and a legend of the named series
//! in the corner with the fewest points.
//! Shared by [`line_chart`](super::line_chart) (the whole image) and
//! [`panels`](super::panels) (one grid cell each), so both look alike; used by `minflow
//! train` (loss curve) and `minflow eval` (per-scene MSE). Input: a [`ChartSpec`] and an area
//! in pixels; output: pixels on that area, or the plotters error as text. Font sizes and
//! label areas scale with the area's smaller side.

use std::ops::Range;

use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::prelude::*;

use super::range::{bounds, drawable, Bounds};
use super::ticks::{label, log_ticks};
use super::{series_colour, Series, FONT_FAMILY};

/// What one chart shows.
pub(super) struct ChartSpec<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub series: &'a [Series],
    pub log_y: bool,
}

/// Pixel sizes of one chart's text and spacing, from the area's smaller side.
struct Layout {
    title: f64,
    label: f64,
    tick: f64,
    margin: u32,
    line_width: u32,
    /// Most tick labels on the x and the y axis.
    x_labels: usize,
    y_labels: usize,
}

impl Layout {
    fn for_area(width: u32, height: u32) -> Self {
        let side = f64::from(width.min(height));
        let mut layout = Layout {
            title: (side / 20.0).clamp(11.0, 28.0),
            label: (side / 28.0).clamp(10.0, 20.0),
            tick: (side / 34.0).clamp(9.0, 16.0),
            margin: (side / 40.0).clamp(4.0, 16.0) as u32,
            line_width: if side >= 300.0 { 2 } else { 1 },
            x_labels: 0,
            y_labels: 0,
        };
        layout.x_labels = layout.max_x_labels(width);
        layout.y_labels = layout.max_y_labels(height);
        layout
    }

    /// Height of the x label area: tick labels, the axis description, gaps.
    fn x_area(&self) -> u32 {
        (self.tick + self.label + 14.0) as u32
    }

    /// Width of the y label area: about seven tick-label characters and the description.
    fn y_area(&self) -> u32 {
        (self.tick * 4.2 + self.label + 14.0) as u32
    }

    /// How many y tick labels fit on an area `height` px high, about 2.5 lines apart.
    fn max_y_labels(&self, height: u32) -> usize {
        let plot =
            f64::from(height) - f64::from(self.x_area() + 2 * self.margin) - self.title * 1.5;
        (plot / (self.tick * 2.5)).clamp(2.0, 12.0) as usize
    }

    /// How many x tick labels fit on an area `width` px wide, about six characters apart.
    fn max_x_labels(&self, width: u32) -> usize {
        let plot = f64::from(width) - f64::from(self.y_area() + 2 * self.margin);
        (plot / (self.tick * 3.5)).clamp(2.0, 12.0) as usize
    }
}

/// Draws `spec` on `area`; a plotters failure comes back as its message.
pub(super) fn draw<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    spec: &ChartSpec<'_>,
) -> Result<(), String> {
    let lines: Vec<Vec<(f64, f64)>> = spec
        .series
        .iter()
        .map(|s| drawable(&s.points, spec.log_y))
        .collect();
    let b = bounds(lines.iter().flatten(), spec.log_y);
    let (width, height) = area.dim_in_pixel();
    let layout = Layout::for_area(width, height);
    let x_res = (b.x.end - b.x.start) / 100.0;
    let x_format = move |v: &f64| label(*v, x_res);
    let corner = legend_corner(&lines, &b, spec.log_y);
    let drawn = if spec.log_y {
        let ticks = log_ticks(b.y.start, b.y.end, layout.y_labels);
        let y_format = move |v: &f64| label(*v, ticks.step.unwrap_or(v.abs() / 100.0));
        let y =
            b.y.log_scale()
                .with_key_points(ticks.bold)
                .with_light_points(ticks.light);
        draw_on(
            area,
            spec,
            (&layout, corner),
            &lines,
            (b.x, &x_format),
            (y, &y_format),
        )
    } else {
        let y_res = (b.y.end - b.y.start) / 100.0;
        let y_format = move |v: &f64| label(*v, y_res);
        draw_on(
            area,
            spec,
            (&layout, corner),
            &lines,
            (b.x, &x_format),
            (b.y, &y_format),
        )
    };
    drawn.map_err(|e| e.to_string())
}

/// Tick label text for one axis.
type Format<'f> = &'f dyn Fn(&f64) -> String;

/// The chart of [`draw`], with the y axis given as a plotters coordinate spec (linear or
/// log) and each axis with its tick label format.
fn draw_on<DB, Y>(
    area: &DrawingArea<DB, Shift>,
    spec: &ChartSpec<'_>,
    (layout, corner): (&Layout, SeriesLabelPosition),
    lines: &[Vec<(f64, f64)>],
    (x, x_format): (Range<f64>, Format<'_>),
    (y, y_format): (Y, Format<'_>),
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB: DrawingBackend,
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let mut builder = ChartBuilder::on(area);
    builder
        .margin(layout.margin)
        .x_label_area_size(layout.x_area())
        .y_label_area_size(layout.y_area());
    if !spec.title.is_empty() {
        builder.caption(spec.title, (FONT_FAMILY, layout.title));
    }
    let mut chart = builder.build_cartesian_2d(x, y)?;

    chart
        .configure_mesh()
        .x_desc(spec.x_label)
        .y_desc(spec.y_label)
        .axis_desc_style((FONT_FAMILY, layout.label))
        .label_style((FONT_FAMILY, layout.tick))
        .light_line_style(RGBColor(235, 235, 235))
        .bold_line_style(RGBColor(205, 205, 205))
        .max_light_lines(4)
        .x_labels(layout.x_labels)
        .y_labels(layout.y_labels)
        .x_label_formatter(x_format)
        .y_label_formatter(y_format)
        .draw()?;

    let mut any_named = false;
    for (index, (series, points)) in spec.series.iter().zip(lines).enumerate() {
        let (r, g, b) = series_colour(index);
        let style = RGBColor(r, g, b).stroke_width(layout.line_width);
        let annotation = if let [single] = points.as_slice() {
            let radius = layout.line_width as i32 + 2;
            chart.draw_series(std::iter::once(Circle::new(
                *single,
                radius,
                style.filled(),
            )))?
        } else {
            chart.draw_series(LineSeries::new(points.iter().copied(), style))?
        };
        if !series.name.is_empty() {
            any_named = true;
            annotation
                .label(series.name.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
        }
    }
    if any_named {
        chart
            .configure_series_labels()
            .position(corner)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(160, 160, 160))
            .label_font((FONT_FAMILY, layout.tick))
            .draw()?;
    }
    Ok(())
}

/// The corner of the plot with the fewest points where the legend would go (the left or
/// right 40 %, the top or bottom 35 %), upper right on ties.
fn legend_corner(lines: &[Vec<(f64, f64)>], b: &Bounds, log_y: bool) -> SeriesLabelPosition {
    let scale = |y: f64| if log_y { y.log10() } else { y };
    let (y0, y1) = (scale(b.y.start), scale(b.y.end));
    let unit = |&(x, y): &(f64, f64)| {
        (
            (x - b.x.start) / (b.x.end - b.x.start),
            (scale(y) - y0) / (y1 - y0),
        )
    };
    let in_corner = |(u, v): (f64, f64), right: bool, top: bool| {
        (if right { u > 0.6 } else { u < 0.4 }) && (if top { v > 0.65 } else { v < 0.35 })
    };
    let corners = [(true, true), (false, true), (true, false), (false, false)];
    let crowding = |&(right, top): &(bool, bool)| {
        lines
            .iter()
            .flatten()
            .map(unit)
            .filter(|&p| in_corner(p, right, top))
            .count()
    };
    match corners.iter().min_by_key(|c| crowding(c)) {
        Some((false, true)) => SeriesLabelPosition::UpperLeft,
        Some((true, false)) => SeriesLabelPosition::LowerRight,
        Some((false, false)) => SeriesLabelPosition::LowerLeft,
        _ => SeriesLabelPosition::UpperRight,
    }
}
