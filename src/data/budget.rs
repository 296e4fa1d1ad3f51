//! How many frames training may hold in memory ([`ResidentBudget`], `train
//! --max-resident-frames`): a number, or `auto`, a share of the memory the machine has
//! available (`MemAvailable` in `/proc/meminfo`) divided by a frame's size at the dataset's
//! particle count. A dataset larger than the budget is streamed from its bags
//! ([`super::StreamingLoader`]).

use std::str::FromStr;

/// The share of the available memory `auto` gives the training frames: the rest is for the
/// batches, the model and the backend's buffers (on a GPU machine, for the host's pinned
/// staging too).
pub const AUTO_SHARE: f64 = 0.4;

/// The largest particle count `minflow simulate` makes (`--grid 256`): what `auto` assumes
/// of a dataset before its scenes are indexed.
pub const LARGEST_SCENE: usize = 40_000;

/// Bytes a frame of `n` particles takes in memory: x, y, vx, vy as f32.
pub fn frame_bytes(n: usize) -> usize {
    16 * n.max(1)
}

/// `--max-resident-frames`: a frame count, or `auto`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResidentBudget {
    /// [`AUTO_SHARE`] of the available memory.
    Auto,
    /// At most this many frames (at least 1).
    Frames(usize),
}

impl FromStr for ResidentBudget {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "auto" => Ok(Self::Auto),
            _ => match s.parse::<usize>() {
                Ok(0) => Err("must be at least 1 (or auto)".into()),
                Ok(n) => Ok(Self::Frames(n)),
                Err(_) => Err(format!("{s:?} is neither a frame count nor auto")),
            },
        }
    }
}

impl std::fmt::Display for ResidentBudget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Frames(n) => write!(f, "{n}"),
        }
    }
}

impl ResidentBudget {
    /// The budget in frames of `n` particles: the count given, or for `auto`
    /// [`AUTO_SHARE`] of [`available_memory`] over [`frame_bytes`] (at least 1; 50,000 frames
    /// when the available memory cannot be read).
    pub fn frames(&self, n: usize) -> usize {
        match self {
            Self::Frames(frames) => *frames,
            Self::Auto => match available_memory() {
                Some(bytes) => ((bytes as f64 * AUTO_SHARE) as usize / frame_bytes(n)).max(1),
                None => 50_000,
            },
        }
    }

    /// What the budget is, for a log line: the `frames` that [`Self::frames`] gave for `n`
    /// particles and, for `auto`, where they came from.
    pub fn describe(&self, n: usize, frames: usize) -> String {
        match (self, available_memory()) {
            (Self::Auto, Some(bytes)) => format!(
                "{frames} frames of {n} particles ({:.0} % of the {:.1} GiB available)",
                AUTO_SHARE * 100.0,
                bytes as f64 / f64::from(1u32 << 30)
            ),
            _ => format!("{frames} frames"),
        }
    }
}

/// The memory the machine has available for new work, bytes (`MemAvailable` of
/// `/proc/meminfo`); None where that cannot be read.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::{frame_bytes, ResidentBudget};

    #[test]
    fn parses_counts_and_auto() {
        assert_eq!("auto".parse(), Ok(ResidentBudget::Auto));
        assert_eq!("1200".parse(), Ok(ResidentBudget::Frames(1200)));
        assert!("0".parse::<ResidentBudget>().is_err());
        assert!("lots".parse::<ResidentBudget>().is_err());
        assert_eq!(ResidentBudget::Frames(7).frames(2500), 7);
        assert_eq!(frame_bytes(2500), 40_000);
    }

    #[test]
    fn auto_takes_a_share_of_the_available_memory() {
        let Some(bytes) = super::available_memory() else {
            panic!("/proc/meminfo has no MemAvailable on this machine");
        };
        let frames = ResidentBudget::Auto.frames(2500);
        let expected = (bytes as f64 * super::AUTO_SHARE) as usize / 40_000;
        // The memory may change between the two reads: within 5 %.
        assert!(
            frames.abs_diff(expected) <= expected / 20 + 1,
            "{frames} vs {expected}"
        );
        assert!(ResidentBudget::Auto.frames(40_000) < frames);
    }
}
