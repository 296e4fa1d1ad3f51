//! Range checks of numeric flags as clap value parsers, so a flag out of range is a usage
//! error (exit 2, clap's message naming the flag) before any data is read, as ripgrep checks
//! its low-level arguments before building its high-level ones.

/// A count of at least 1.
pub fn at_least_one(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(v) => Ok(v),
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
    }
}
