//! Min-max scaling of the per-particle features (x, y, vx, vy, m), fitted on the training split
//! only.
//!
//! Physical values in: x, y in domain units, vx, vy in domain units per time unit, m the
//! material id as f32 (0 liquid, 1 jelly, 2 snow, 3 rope). Scaled values out:
//! `(v - min) / (max - min)` per feature, so training data lies in [0, 1] (other splits may
//! leave it). Arithmetic is done in f64 and rounded once, so `unscale(scale(v))` returns `v`
//! to within one rounding of the scaled value. A feature that is constant over the training
//! data gets `max = min + 1` (a range of 1), so scaling never divides by zero. [`ScalerFit`]
//! accumulates the extremes trajectory by trajectory (for datasets that are streamed);
//! [`Scaler::fit`] is the one-call form. The scaler is saved with the checkpoint (serde).
//! Used by `minflow train` (fit, scale inputs and targets) and `minflow eval` (scale for the
//! metrics, unscale predictions).

use serde::{Deserialize, Serialize};

use super::Trajectory;

/// Features per particle: x, y, vx, vy, m.
pub const FEATURES: usize = 5;
/// Feature names, in order.
pub const FEATURE_NAMES: [&str; FEATURES] = ["x", "y", "vx", "vy", "m"];

/// Per-feature min-max scaling; feature order as in [`FEATURE_NAMES`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Scaler {
    /// Smallest value of each feature over every frame and particle of the training
    /// trajectories: x, y (domain units), vx, vy (domain units per time unit), m (material id).
    pub min: [f32; FEATURES],
    /// Largest value of each feature, same units; `min + 1` for a feature that is constant
    /// over the training data (and 0 / 1 for both when there was no data at all).
    pub max: [f32; FEATURES],
}

impl Default for Scaler {
    /// The identity: min 0, max 1 for every feature.
    fn default() -> Self {
        Self {
            min: [0.0; FEATURES],
            max: [1.0; FEATURES],
        }
    }
}

/// Running per-feature extremes; [`ScalerFit::finish`] turns them into a [`Scaler`].
#[derive(Debug, Clone, PartialEq)]
pub struct ScalerFit {
    min: [f32; FEATURES],
    max: [f32; FEATURES],
    frames: u64,
}

impl Default for ScalerFit {
    fn default() -> Self {
        Self {
            min: [f32::INFINITY; FEATURES],
            max: [f32::NEG_INFINITY; FEATURES],
            frames: 0,
        }
    }
}

impl ScalerFit {
    /// Nothing seen yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes every frame and particle of `traj` into account.
    pub fn add(&mut self, traj: &Trajectory) {
        if traj.frames == 0 || traj.n == 0 {
            return;
        }
        for row in traj.states.chunks_exact(4) {
            for (f, &v) in row.iter().enumerate() {
                self.min[f] = self.min[f].min(v);
                self.max[f] = self.max[f].max(v);
            }
        }
        for &m in &traj.material {
            self.min[4] = self.min[4].min(f32::from(m));
            self.max[4] = self.max[4].max(f32::from(m));
        }
        self.frames += traj.frames as u64;
    }

    /// The scaler; constant features get a range of 1, and with no data at all every feature
    /// is left unscaled (min 0, max 1) with a warning.
    pub fn finish(self) -> Scaler {
        if self.frames == 0 {
            tracing::warn!("fitting the scaler on no data: features are left unscaled");
            return Scaler::default();
        }
        let mut scaler = Scaler {
            min: self.min,
            max: self.max,
        };
        for (f, name) in FEATURE_NAMES.iter().enumerate() {
            if scaler.max[f] <= scaler.min[f] {
                tracing::info!(
                    "feature {name} is constant ({}) in the training data: range set to 1",
                    scaler.min[f]
                );
                scaler.max[f] = scaler.min[f] + 1.0;
            }
        }
        scaler
    }
}

impl Scaler {
    /// Fits on `trajs`, which must be the training split only (see the module doc).
    pub fn fit(trajs: &[&Trajectory]) -> Scaler {
        let mut fit = ScalerFit::new();
        for t in trajs {
            fit.add(t);
        }
        fit.finish()
    }

    fn range64(&self, f: usize) -> f64 {
        let r = f64::from(self.max[f]) - f64::from(self.min[f]);
        if r > 0.0 {
            r
        } else {
            1.0
        }
    }

    /// `max - min` of feature `f` (1 where that would be zero). Panics when `f >= 5`.
    pub fn range(&self, f: usize) -> f32 {
        self.range64(f) as f32
    }

    /// Scales one value of feature `f`: `(v - min) / (max - min)`.
    pub fn scale(&self, f: usize, v: f32) -> f32 {
        ((f64::from(v) - f64::from(self.min[f])) / self.range64(f)) as f32
    }

    /// Inverse of [`Scaler::scale`]: `s * (max - min) + min`.
    pub fn unscale(&self, f: usize, s: f32) -> f32 {
        (f64::from(s) * self.range64(f) + f64::from(self.min[f])) as f32
    }

    /// Appends the scaled `[N, 5]` features of a physical `[N, 4]` state (x, y, vx, vy) and
    /// its N material ids to `out`.
    pub fn scale_into(&self, state: &[f32], material: &[u8], out: &mut Vec<f32>) {
        debug_assert_eq!(state.len(), 4 * material.len());
        out.reserve(5 * material.len());
        for (row, &m) in state.chunks_exact(4).zip(material) {
            for (f, &v) in row.iter().enumerate() {
                out.push(self.scale(f, v));
            }
            out.push(self.scale(4, f32::from(m)));
        }
    }

    /// [`Scaler::scale_into`] into `out`, `[N, 5]`, instead of appending (the same values).
    /// Panics when `out` is not `5 N` long.
    pub fn scale_to(&self, state: &[f32], material: &[u8], out: &mut [f32]) {
        debug_assert_eq!(state.len(), 4 * material.len());
        assert_eq!(
            out.len(),
            5 * material.len(),
            "rows of 5 features for every particle"
        );
        let rows = state.chunks_exact(4).zip(material);
        for ((row, &m), to) in rows.zip(out.chunks_exact_mut(5)) {
            for (f, &v) in row.iter().enumerate() {
                to[f] = self.scale(f, v);
            }
            to[4] = self.scale(4, f32::from(m));
        }
    }

    /// [`Scaler::scale_state_into`] into `out`, `[N, 4]`, instead of appending. Panics when
    /// `out` is not as long as `state`.
    pub fn scale_state_to(&self, state: &[f32], out: &mut [f32]) {
        assert_eq!(out.len(), state.len(), "a scaled row for every particle");
        for (row, to) in state.chunks_exact(4).zip(out.chunks_exact_mut(4)) {
            for (f, &v) in row.iter().enumerate() {
                to[f] = self.scale(f, v);
            }
        }
    }

    /// Appends the scaled `[N, 4]` (x, y, vx, vy) of a physical `[N, 4]` state to `out`.
    pub fn scale_state_into(&self, state: &[f32], out: &mut Vec<f32>) {
        out.reserve(state.len());
        for row in state.chunks_exact(4) {
            for (f, &v) in row.iter().enumerate() {
                out.push(self.scale(f, v));
            }
        }
    }

    /// Scales rows of `width` features in place: `[.., 4]` (x, y, vx, vy) or `[.., 5]` (with
    /// m). Panics on another width.
    pub fn scale_rows(&self, rows: &mut [f32], width: usize) {
        assert!(
            width == 4 || width == 5,
            "rows have 4 or 5 features, not {width}"
        );
        for row in rows.chunks_exact_mut(width) {
            for (f, v) in row.iter_mut().enumerate() {
                *v = self.scale(f, *v);
            }
        }
    }

    /// Unscales rows of `width` features in place (the inverse of [`Scaler::scale_rows`]).
    /// Panics on a width other than 4 or 5.
    pub fn unscale_rows(&self, rows: &mut [f32], width: usize) {
        assert!(
            width == 4 || width == 5,
            "rows have 4 or 5 features, not {width}"
        );
        for row in rows.chunks_exact_mut(width) {
            for (f, v) in row.iter_mut().enumerate() {
                *v = self.unscale(f, *v);
            }
        }
    }
}
