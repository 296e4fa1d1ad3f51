//! Tick values for a log10 y axis and tick label text for every axis, for
//! [`chart`](super::chart) (`minflow train` loss curve, `minflow eval` MSE panels). Input: an
//! axis range in the caller's units and how many labels fit; output: labelled ("bold") and
//! grid-only ("light") values, and short label strings.
//!
//! plotters' own log ticks crowd when a range spans less than a couple of decades, so log
//! axes pick the first of powers of ten, 1-2-5 and 1..9 mantissas that gives 3 to
//! `max_labels` ticks (powers of ten thinned on very wide ranges), then to two powers of ten,
//! and on ranges narrower than that to evenly spaced 1-2-5 steps.

/// Ticks of one axis.
pub(super) struct Ticks {
    /// Labelled values, with a grid line each.
    pub bold: Vec<f64>,
    /// Values with a faint grid line only.
    pub light: Vec<f64>,
    /// Spacing of evenly spaced ticks (labels need that resolution); `None` for ticks on
    /// mantissas, labelled to three significant digits.
    pub step: Option<f64>,
}

const POWERS: &[f64] = &[1.0];
const ONE_TWO_FIVE: &[f64] = &[1.0, 2.0, 5.0];
const ALL_DIGITS: &[f64] = &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0];
/// Widest range, in decades, that still gets light grid lines at 2..9 mantissas.
const MAX_LIGHT_DECADES: i32 = 10;

/// Ticks for a log10 axis over `lo..hi` (0 < lo < hi, both finite), at most `max_labels`
/// (at least 2) labelled.
pub(super) fn log_ticks(lo: f64, hi: f64, max_labels: usize) -> Ticks {
    let max_labels = max_labels.max(2);
    let (k0, k1) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    let on = |mantissas: &[f64]| -> Vec<f64> {
        (k0..=k1)
            .flat_map(|k| mantissas.iter().map(move |m| m * 10f64.powi(k)))
            .filter(|v| (lo..=hi).contains(v))
            .collect()
    };
    let light = if k1 - k0 <= MAX_LIGHT_DECADES {
        on(ALL_DIGITS)
    } else {
        Vec::new()
    };
    let powers = on(POWERS);
    if powers.len() > max_labels {
        let every = powers.len().div_ceil(max_labels);
        let bold = powers.into_iter().step_by(every).collect();
        return Ticks {
            bold,
            light,
            step: None,
        };
    }
    for mantissas in [POWERS, ONE_TWO_FIVE, ALL_DIGITS] {
        let bold = on(mantissas);
        if (3.min(max_labels)..=max_labels).contains(&bold.len()) {
            return Ticks {
                bold,
                light,
                step: None,
            };
        }
    }
    if powers.len() >= 2 {
        return Ticks {
            bold: powers,
            light,
            step: None,
        };
    }
    linear_ticks(lo, hi, max_labels)
}

/// Evenly spaced ticks on multiples of a 1-2-5 step, at most `max_labels` of them (and at
/// least one step per `lo..hi` range).
fn linear_ticks(lo: f64, hi: f64, max_labels: usize) -> Ticks {
    let raw = (hi - lo) / max_labels as f64;
    let magnitude = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * magnitude)
        .find(|&s| s >= raw)
        .unwrap_or(10.0 * magnitude);
    if !(step.is_finite() && step > 0.0) {
        return Ticks {
            bold: vec![lo, hi],
            light: Vec::new(),
            step: None,
        };
    }
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    if last.saturating_sub(first) > 2 * max_labels as i64 {
        // Only when lo / step is beyond f64 precision; the ends are the best we can do.
        return Ticks {
            bold: vec![lo, hi],
            light: Vec::new(),
            step: None,
        };
    }
    let bold = (first..=last).map(|i| i as f64 * step).collect();
    Ticks {
        bold,
        light: Vec::new(),
        step: Some(step),
    }
}

/// Label for tick `v` showing differences down to `resolution`: "0", "0.25", "150", "1e-5",
/// "2.5e6"; exponent form from 1e5 up and below 1e-3.
pub(super) fn label(v: f64, resolution: f64) -> String {
    let a = v.abs();
    if a == 0.0 || !a.is_finite() || !(resolution.is_finite() && resolution > 0.0) {
        return format!("{v}");
    }
    let res_exp = resolution.log10().floor() as i32;
    if (1e-3..1e5).contains(&a) {
        let decimals = (-res_exp).clamp(0, 12) as usize;
        return trim_zeros(&format!("{v:.decimals$}")).to_string();
    }
    let digits = (a.log10().floor() as i32 - res_exp).clamp(0, 12) as usize;
    let text = format!("{v:.digits$e}");
    match text.split_once('e') {
        Some((mantissa, exponent)) => format!("{}e{exponent}", trim_zeros(mantissa)),
        None => text,
    }
}

/// "2.500" -> "2.5", "3.000" -> "3", "120" -> "120".
fn trim_zeros(number: &str) -> &str {
    if number.contains('.') {
        number.trim_end_matches('0').trim_end_matches('.')
    } else {
        number
    }
}
