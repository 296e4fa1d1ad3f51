//! Range checks of numeric flags as clap value parsers, so a flag out of range is a usage
//! error (exit 2, clap's message naming the flag) before any data is read, as ripgrep checks
//! its low-level arguments before building its high-level ones. The grid model's ranges are
//! its config's own ([`grid::BUNDLE`] and the rest), which `GridConfig::validate` checks too.

use crate::model::grid;

/// A count of at least 1.
pub fn at_least_one(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(v) => Ok(v),
        Err(e) => Err(e.to_string()),
    }
}

/// A rollout length: a number of steps (at least 1), or `full`, to each scene's end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Horizon {
    /// This many predicted steps.
    Steps(usize),
    /// From the seed frames to the scene's last frame.
    Full,
}

impl std::fmt::Display for Horizon {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Horizon::Steps(k) => write!(f, "{k}"),
            Horizon::Full => f.write_str("full"),
        }
    }
}

/// `--horizon`: a step count of at least 1, or `full`.
pub fn horizon(s: &str) -> Result<Horizon, String> {
    match s {
        "full" => Ok(Horizon::Full),
        _ => at_least_one(s)
            .map(Horizon::Steps)
            .map_err(|e| format!("{e} (a number of steps, or full)")),
    }
}

/// An integer in `range`.
fn integer_in(s: &str, range: std::ops::RangeInclusive<usize>) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(v) if range.contains(&v) => Ok(v),
        Ok(_) => Err(format!("must be in {}..={}", range.start(), range.end())),
        Err(e) => Err(e.to_string()),
    }
}

/// A bundle size K (`--bundle`): an integer in [`grid::BUNDLE`] (1..=16).
pub fn bundle(s: &str) -> Result<usize, String> {
    integer_in(s, grid::BUNDLE)
}

/// `--substeps`: network substeps per frame, in [`grid::SUBSTEPS`] (1..=8).
pub fn substeps(s: &str) -> Result<usize, String> {
    integer_in(s, grid::SUBSTEPS)
}

/// `--interaction`: rounds of message passing, in [`grid::INTERACTION_ROUNDS`] (0..=8).
pub fn rounds(s: &str) -> Result<usize, String> {
    integer_in(s, grid::INTERACTION_ROUNDS)
}

/// `--interaction-neighbours`: neighbours per particle, in [`grid::INTERACTION_NEIGHBOURS`]
/// (1..=64).
pub fn neighbours(s: &str) -> Result<usize, String> {
    integer_in(s, grid::INTERACTION_NEIGHBOURS)
}

/// `--box-grid`: 0 (the network's grid) or a grid side in [`grid::BOX_GRID`] (8..=4096).
pub fn box_grid(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Ok(0),
        _ => integer_in(s, grid::BOX_GRID),
    }
}

/// `--interaction-radius`: a radius in (0, [`grid::INTERACTION_RADIUS_MAX`]] (0.25) of the
/// unit box.
pub fn radius(s: &str) -> Result<f64, String> {
    let max = grid::INTERACTION_RADIUS_MAX;
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && v <= max => Ok(v),
        Ok(v) => Err(format!("{v} is not in (0, {max}]")),
        Err(e) => Err(e.to_string()),
    }
}

/// A finite number above 0.
pub fn positive(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite number above 0")),
        Err(e) => Err(e.to_string()),
    }
}

/// A finite number of at least 0.
pub fn non_negative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a finite number >= 0")),
        Err(e) => Err(e.to_string()),
    }
}

/// [`non_negative`] as f32.
pub fn non_negative_f32(s: &str) -> Result<f32, String> {
    non_negative(s).map(|v| v as f32)
}

/// The longest wait or duration a flag may ask for, in seconds (about 31 years): longer ones
/// overflow the clock arithmetic (`Duration::from_secs_f64` panics past ~5.8e11 years).
pub const MAX_SECONDS: f64 = 1e9;

/// Seconds of a wait or a duration: a finite number in `[0, MAX_SECONDS]`.
pub fn seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && (0.0..=MAX_SECONDS).contains(&v) => Ok(v),
        Ok(v) => Err(format!(
            "{v} is not a number of seconds in [0, {MAX_SECONDS:e}]"
        )),
        Err(e) => Err(e.to_string()),
    }
}

/// A repeating interval in seconds: a finite number in `[0.001, MAX_SECONDS]` (0 would log or
/// split in a busy loop).
pub fn interval(s: &str) -> Result<f64, String> {
    match seconds(s) {
        Ok(v) if v >= 1e-3 => Ok(v),
        Ok(v) => Err(format!("{v} is shorter than 0.001 s")),
        Err(e) => Err(e),
    }
}

/// A pacing factor (1 = real time): 0 (as fast as possible) or a finite number of at least
/// 1e-6 (slower ones turn frame gaps into waits that overflow the clock arithmetic).
pub fn rate(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v == 0.0 || (v.is_finite() && v >= 1e-6) => Ok(v),
        Ok(v) => Err(format!("{v} is neither 0 nor a finite number >= 1e-6")),
        Err(e) => Err(e.to_string()),
    }
}

/// A loss discount, in `(0, 1]`.
pub fn discount(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v > 0.0 && v <= 1.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not in (0, 1]")),
        Err(e) => Err(e.to_string()),
    }
}

/// A share, in `[0, 1]`.
pub fn share(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        Ok(v) => Err(format!("{v} is not in [0, 1]")),
        Err(e) => Err(e.to_string()),
    }
}

/// A probability of dropping, in `[0, 1)`.
pub fn dropout(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..1.0).contains(&v) => Ok(v),
        Ok(v) => Err(format!("{v} is not in [0, 1)")),
        Err(e) => Err(e.to_string()),
    }
}

/// A U-Net convolution kernel: auto | burn | gather | shift.
pub fn conv_kernel(s: &str) -> Result<crate::model::grid::ConvKernel, String> {
    crate::model::grid::ConvKernel::parse(s)
        .ok_or_else(|| format!("{s:?} is not one of auto | burn | gather | shift"))
}

/// A subcommand's flag values with its own defaults for every flag but `required` (values
/// the caller sets itself next, each parsed as `-`), so `report` and `demo` run what `train`
/// and `eval` would.
///
/// # Errors
/// A flag of `T` without a default that `required` does not name.
pub fn defaults<T: clap::Args>(required: &[&str]) -> anyhow::Result<T> {
    let argv: Vec<&str> = required.iter().flat_map(|f| [*f, "-"]).collect();
    parse(&argv)
}

/// A subcommand's flag values from `argv` (its flags and values, no program name), so
/// `demo` runs what `simulate` would with those flags.
///
/// # Errors
/// `argv` is not a valid command line of `T` (clap's error).
pub fn parse<T: clap::Args>(argv: &[&str]) -> anyhow::Result<T> {
    #[derive(clap::Parser)]
    struct Wrap<T: clap::Args> {
        #[command(flatten)]
        inner: T,
    }
    let argv = std::iter::once("minflow").chain(argv.iter().copied());
    Ok(<Wrap<T> as clap::Parser>::try_parse_from(argv)?.inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges() {
        assert!(at_least_one("0").is_err() && at_least_one("3") == Ok(3));
        assert!(positive("-1").is_err() && positive("inf").is_err() && positive("0").is_err());
        assert!(non_negative("0").is_ok() && non_negative("-0.5").is_err());
        assert!(dropout("2").is_err() && dropout("-0.5").is_err() && dropout("0.1").is_ok());
        assert!(conv_kernel("shift").is_ok() && conv_kernel("winograd").is_err());
        assert!(seconds("0") == Ok(0.0) && seconds("2.5") == Ok(2.5));
        assert!(["-1", "inf", "NaN", "1e10", "x"]
            .iter()
            .all(|s| seconds(s).is_err()));
        assert!(interval("0").is_err() && interval("0.5") == Ok(0.5) && interval("-1").is_err());
        assert!(rate("0") == Ok(0.0) && rate("2") == Ok(2.0));
        assert!(share("0") == Ok(0.0) && share("1") == Ok(1.0) && share("0.5") == Ok(0.5));
        assert!(["-0.1", "1.5", "NaN", "x"]
            .iter()
            .all(|s| share(s).is_err()));
        assert!(["-1", "1e-300", "inf", "NaN"]
            .iter()
            .all(|s| rate(s).is_err()));
    }

    /// The grid model's flags and `GridConfig::validate` accept the same values: each edge of
    /// each range, and one past it.
    #[test]
    fn grid_flags_agree_with_the_config() {
        use grid::{GridConfig, MemoryKind};
        let config = || GridConfig::new(MemoryKind::MinGru);
        for v in 0..=70 {
            let text = v.to_string();
            let valid = |c: GridConfig| c.validate().is_ok();
            assert_eq!(
                bundle(&text).is_ok(),
                valid(config().with_bundle(v)),
                "bundle {v}"
            );
            assert_eq!(
                substeps(&text).is_ok(),
                valid(config().with_substeps(v)),
                "{v}"
            );
            assert_eq!(
                rounds(&text).is_ok(),
                valid(config().with_interaction(v)),
                "{v}"
            );
            let k = config().with_interaction_neighbours(v);
            assert_eq!(neighbours(&text).is_ok(), valid(k), "neighbours {v}");
        }
        for v in [0, 1, 7, 8, 32, 256, 4096, 4097] {
            let c = config().with_box_grid(v);
            assert_eq!(
                box_grid(&v.to_string()).is_ok(),
                c.validate().is_ok(),
                "box {v}"
            );
        }
        for r in [-0.1, 0.0, 1e-6, 0.02, 0.25, 0.2500001, 1.0] {
            let c = config().with_interaction_radius(r);
            assert_eq!(
                radius(&r.to_string()).is_ok(),
                c.validate().is_ok(),
                "radius {r}"
            );
        }
        let message = config().with_bundle(0).validate().unwrap_err().to_string();
        assert_eq!(message, "--bundle must be in 1..=16");
    }
}
