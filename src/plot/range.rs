//! Which points a chart can draw and the axis ranges that show them, for
//! [`line_chart`](super::line_chart) and [`panels`](super::panels) (`minflow train`, `minflow
//! eval`). Input: (x, y) pairs in the caller's units; output: the drawable pairs and an x and
//! a y range in the same units, never empty, never infinite.
//!
//! A point is drawable when both values are finite and within ±[`LIMIT`] (so a range's width
//! stays finite) and, on a log y axis, y is at least [`MIN_LOG_Y`]. The y range gets a 5 %
//! margin on each side (in log10 space on a log axis); the x range none. A range of one value
//! is widened (by 10 % of the value, 1 when it is 0, or half a decade on a log axis); with no
//! drawable point at all the ranges are x 0..1, y 0..1 (linear) or 1..10 (log).

use std::ops::Range;

/// Largest |x| or |y| drawn.
pub(super) const LIMIT: f64 = 1e300;
/// Smallest y drawn on a log axis (keeps 10^(log10 y - margin) a normal float).
pub(super) const MIN_LOG_Y: f64 = 1e-300;
/// Margin on each side of the y range, as a fraction of its width.
const Y_MARGIN: f64 = 0.05;

/// The x and y ranges of one chart.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Bounds {
    pub x: Range<f64>,
    pub y: Range<f64>,
}

/// The drawable points of `points`, in order.
pub(super) fn drawable(points: &[(f64, f64)], log_y: bool) -> Vec<(f64, f64)> {
    let in_limit = |v: f64| v.is_finite() && v.abs() <= LIMIT;
    points
        .iter()
        .copied()
        .filter(|&(x, y)| in_limit(x) && in_limit(y) && (!log_y || y >= MIN_LOG_Y))
        .collect()
}

/// Ranges covering `points`, which must all be [`drawable`] for `log_y`.
pub(super) fn bounds<'a>(
    points: impl Iterator<Item = &'a (f64, f64)> + Clone,
    log_y: bool,
) -> Bounds {
    let x = widen(
        min_max(points.clone().map(|p| p.0)),
        0.0,
        linear_pad,
        0.0..1.0,
    );
    let y = if log_y {
        let decades = widen(
            min_max(points.map(|p| p.1.log10())),
            Y_MARGIN,
            |_| 0.5,
            0.0..1.0,
        );
        10f64.powf(decades.start)..10f64.powf(decades.end)
    } else {
        widen(min_max(points.map(|p| p.1)), Y_MARGIN, linear_pad, 0.0..1.0)
    };
    Bounds { x, y }
}

/// Smallest and largest of `values`, `None` when there are none.
fn min_max(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    values.fold(None, |acc, v| match acc {
        None => Some((v, v)),
        Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
    })
}

/// `lo..hi` grown by `margin` of its width on each side; a single value `v` grown by
/// `single(v)` on each side; `default` when there is nothing.
fn widen(
    span: Option<(f64, f64)>,
    margin: f64,
    single: impl Fn(f64) -> f64,
    default: Range<f64>,
) -> Range<f64> {
    match span {
        None => default,
        Some((lo, hi)) if hi > lo => {
            let pad = (hi - lo) * margin;
            lo - pad..hi + pad
        }
        Some((v, _)) => v - single(v)..v + single(v),
    }
}

/// How far a single linear value is widened on each side.
fn linear_pad(v: f64) -> f64 {
    if v == 0.0 {
        1.0
    } else {
        v.abs() * 0.1
    }
}
