//! Per-frame error metrics of a predicted frame against its ground truth (docs/design.md,
//! "Metrics"; the paper's Tables 2 and 3), and their averages.
//!
//! Inputs: two physical `[N, 4]` states (x, y in domain units, vx, vy in domain units per
//! time unit), the scene's N material ids and the [`Scaler`] that defines the scaled
//! features. Outputs: one [`FrameMetrics`] per frame:
//!
//! - `mse`: mean over particles and the four scaled features (x, y, vx, vy) of the squared
//!   error, the paper's metric; the scaled values are exactly what the training batches use
//!   ([`Scaler::scale`]), the squares are summed in f64;
//! - the same split by channel (`mse_pos`: x, y; `mse_vel`: vx, vy) and by material
//!   (liquid, jelly, snow, rope; `None` for a material the scene does not have);
//! - in physical units: `phys_pos` (domain units squared) and `phys_vel` ((domain units per
//!   time unit) squared), mean over particles and the two components;
//! - physics diagnostics: `ke_err` = |KE(pred) - KE(truth)| with KE = 1/2 mean |v|^2 (the
//!   kinetic energy per unit mass, every particle of equal mass), `com_err` = distance between
//!   the centres of mass (domain units), `density_err` = MSE between density maps on a G x G
//!   grid (the training loss's tent splat, normalised to mean 1, see [`density_map`]), and
//!   `outside` = predicted particles outside the unit square.
//!
//! Used by `minflow eval` and `minflow report` through [`super::rollout`] and
//! [`super::replay`].

use crate::data::Scaler;
use crate::geometry::position_sum;

/// Material count ([`crate::material::COUNT`]): the per-material slots of [`FrameMetrics`].
pub const MATERIALS: usize = crate::material::COUNT;

/// The metric columns before the per-material ones (see [`metric_names`]).
const HEAD: [&str; 3] = ["mse", "mse_pos", "mse_vel"];
/// The metric columns after the per-material ones.
const TAIL: [&str; 7] = [
    "phys_pos",
    "phys_vel",
    "ke_err",
    "com_err",
    "density_err",
    "outside",
    "outside_truth",
];
/// Metrics per frame: the columns of [`metric_names`] and [`FrameMetrics::values`].
pub const METRIC_COUNT: usize = HEAD.len() + MATERIALS + TAIL.len();

/// The metric names in the order of [`FrameMetrics::values`], as CSV column names: `mse`,
/// `mse_pos`, `mse_vel`, `mse_<material>` per material in id order (`mse_liquid`, ...),
/// `phys_pos`, `phys_vel`, `ke_err`, `com_err`, `density_err`, `outside`, `outside_truth`.
pub fn metric_names() -> Vec<String> {
    let materials = crate::material::names().map(|m| format!("mse_{m}"));
    HEAD.iter()
        .map(|&h| h.to_owned())
        .chain(materials)
        .chain(TAIL.iter().map(|&t| t.to_owned()))
        .collect()
}

/// Errors of one predicted frame against the truth (see the module doc for each field's
/// definition and units). Averages over several frames are [`FrameMetrics::mean`]s.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FrameMetrics {
    /// MSE over the scaled (x, y, vx, vy): the paper's metric.
    pub mse: f64,
    /// MSE over the scaled positions (x, y).
    pub mse_pos: f64,
    /// MSE over the scaled velocities (vx, vy).
    pub mse_vel: f64,
    /// MSE over the scaled (x, y, vx, vy) of the particles of each material; `None` where
    /// the scene has no particle of that material.
    pub mse_material: [Option<f64>; MATERIALS],
    /// MSE of positions, domain units squared.
    pub phys_pos: f64,
    /// MSE of velocities, (domain units per time unit) squared.
    pub phys_vel: f64,
    /// |KE(pred) - KE(truth)|, KE = 1/2 mean |v|^2, (domain units per time unit) squared.
    pub ke_err: f64,
    /// Distance between the predicted and the true centre of mass, domain units.
    pub com_err: f64,
    /// MSE between the density maps (mean-1 normalised, dimensionless).
    pub density_err: f64,
    /// Predicted particles outside the unit square (a mean over frames after averaging).
    pub outside: f64,
    /// True particles outside the unit square (0 for valid ground truth).
    pub outside_truth: f64,
}

impl FrameMetrics {
    /// The fields as one row, in [`metric_names`] order (`NaN` for an absent material).
    pub fn values(&self) -> Vec<f64> {
        let mut row = Vec::with_capacity(METRIC_COUNT);
        row.extend([self.mse, self.mse_pos, self.mse_vel]);
        row.extend(self.mse_material.map(|m| m.unwrap_or(f64::NAN)));
        row.extend([
            self.phys_pos,
            self.phys_vel,
            self.ke_err,
            self.com_err,
            self.density_err,
            self.outside,
            self.outside_truth,
        ]);
        row
    }

    /// Every field `NaN` and no material: the row of a predictor with nothing scored.
    pub fn absent() -> FrameMetrics {
        let nan = f64::NAN;
        FrameMetrics {
            mse: nan,
            mse_pos: nan,
            mse_vel: nan,
            mse_material: [None; MATERIALS],
            phys_pos: nan,
            phys_vel: nan,
            ke_err: nan,
            com_err: nan,
            density_err: nan,
            outside: nan,
            outside_truth: nan,
        }
    }

    /// Field-wise mean of `all` (a material's mean over the frames that have it); `None` for
    /// an empty slice.
    pub fn mean(all: &[FrameMetrics]) -> Option<FrameMetrics> {
        if all.is_empty() {
            return None;
        }
        let k = all.len() as f64;
        let avg = |f: &dyn Fn(&FrameMetrics) -> f64| all.iter().map(f).sum::<f64>() / k;
        let mut mse_material = [None; MATERIALS];
        for (m, slot) in mse_material.iter_mut().enumerate() {
            let present: Vec<f64> = all.iter().filter_map(|x| x.mse_material[m]).collect();
            if !present.is_empty() {
                *slot = Some(present.iter().sum::<f64>() / present.len() as f64);
            }
        }
        Some(FrameMetrics {
            mse: avg(&|x| x.mse),
            mse_pos: avg(&|x| x.mse_pos),
            mse_vel: avg(&|x| x.mse_vel),
            mse_material,
            phys_pos: avg(&|x| x.phys_pos),
            phys_vel: avg(&|x| x.phys_vel),
            ke_err: avg(&|x| x.ke_err),
            com_err: avg(&|x| x.com_err),
            density_err: avg(&|x| x.density_err),
            outside: avg(&|x| x.outside),
            outside_truth: avg(&|x| x.outside_truth),
        })
    }
}

/// The metrics of `pred` against `truth`.
///
/// # Shapes
/// - `pred`, `truth`: `[N, 4]` physical (x, y, vx, vy); `material`: `[N]`
/// - `grid`: density-map side G (the training loss uses 32); 0 skips the density error
///
/// Panics when the lengths disagree (callers check particle counts first).
pub fn frame_metrics(
    pred: &[f32],
    truth: &[f32],
    material: &[u8],
    scaler: &Scaler,
    grid: usize,
) -> FrameMetrics {
    let n = material.len();
    assert!(
        pred.len() == 4 * n && truth.len() == 4 * n,
        "frame_metrics: {} / {} values for {n} particles",
        pred.len(),
        truth.len()
    );
    let mut sq = [0.0f64; 4];
    let mut phys = [0.0f64; 4];
    let mut mat_sum = [0.0f64; MATERIALS];
    let mut mat_count = [0usize; MATERIALS];
    let (mut ke_p, mut ke_t) = (0.0f64, 0.0f64);
    let (mut outside, mut outside_truth) = (0usize, 0usize);
    for ((p, t), &m) in pred
        .chunks_exact(4)
        .zip(truth.chunks_exact(4))
        .zip(material)
    {
        let mut row = 0.0;
        for f in 0..4 {
            let d = f64::from(scaler.scale(f, p[f])) - f64::from(scaler.scale(f, t[f]));
            sq[f] += d * d;
            row += d * d;
            let dp = f64::from(p[f]) - f64::from(t[f]);
            phys[f] += dp * dp;
        }
        let m = usize::from(m).min(MATERIALS - 1);
        mat_sum[m] += row;
        mat_count[m] += 1;
        let speed2 = |r: &[f32]| f64::from(r[2]).powi(2) + f64::from(r[3]).powi(2);
        ke_p += speed2(p);
        ke_t += speed2(t);
        let out = |r: &[f32]| !(0.0..=1.0).contains(&r[0]) || !(0.0..=1.0).contains(&r[1]);
        outside += usize::from(out(p));
        outside_truth += usize::from(out(t));
    }
    let nf = n.max(1) as f64;
    let mut mse_material = [None; MATERIALS];
    for m in 0..MATERIALS {
        if mat_count[m] > 0 {
            mse_material[m] = Some(mat_sum[m] / (4.0 * mat_count[m] as f64));
        }
    }
    // The distance between the centres of mass as the difference of the position sums over
    // N, one division: the same as `centre_of_mass(pred) - centre_of_mass(truth)` up to the
    // last bits, which metrics.csv (every digit) would show.
    let all = || 0..n as u32;
    let (sum_p, sum_t) = (
        position_sum(pred, 4, all()).0,
        position_sum(truth, 4, all()).0,
    );
    let com = ((sum_p[0] - sum_t[0]) / nf).hypot((sum_p[1] - sum_t[1]) / nf);
    let density_err = if grid > 0 {
        let (a, b) = (density_map(pred, grid), density_map(truth, grid));
        a.iter().zip(&b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / (grid * grid) as f64
    } else {
        0.0
    };
    FrameMetrics {
        mse: sq.iter().sum::<f64>() / (4.0 * nf),
        mse_pos: (sq[0] + sq[1]) / (2.0 * nf),
        mse_vel: (sq[2] + sq[3]) / (2.0 * nf),
        mse_material,
        phys_pos: (phys[0] + phys[1]) / (2.0 * nf),
        phys_vel: (phys[2] + phys[3]) / (2.0 * nf),
        ke_err: 0.5 * (ke_p - ke_t).abs() / nf,
        com_err: com,
        density_err,
        outside: outside as f64,
        outside_truth: outside_truth as f64,
    }
}

/// Density map of the positions of a physical `[N, 4]` state on a `g x g` grid over the unit
/// square, `[g, g]` row-major with index `[ix * g + iy]`: each particle is splatted with the
/// tent kernel `w(u) = max(0, 1 - |u g - (i + 1/2)|)` per axis and weight `g^2 / N`, so a
/// uniform distribution has mean 1. The crate's one definition of the map, in f64 on the
/// host; the paper trainer's density loss computes the same map on tensors, differentiably
/// ([`crate::train::paper::loss::density_map`], whose test checks it against this one).
pub fn density_map(state: &[f32], g: usize) -> Vec<f64> {
    let n = state.len() / 4;
    let mut map = vec![0.0f64; g * g];
    if n == 0 || g == 0 {
        return map;
    }
    let w = (g * g) as f64 / n as f64;
    let gf = g as f64;
    // The (at most two) cells whose tent covers coordinate u, with their weights.
    let cells = |u: f64| {
        let s = u * gf - 0.5;
        let i0 = s.floor();
        let frac = s - i0;
        let mut out = [(usize::MAX, 0.0); 2];
        for (slot, (i, wt)) in out.iter_mut().zip([(i0, 1.0 - frac), (i0 + 1.0, frac)]) {
            if i >= 0.0 && i < gf && wt > 0.0 {
                *slot = (i as usize, wt);
            }
        }
        out
    };
    for r in state.chunks_exact(4) {
        let (cx, cy) = (cells(f64::from(r[0])), cells(f64::from(r[1])));
        for &(ix, wx) in &cx {
            if ix == usize::MAX {
                continue;
            }
            for &(iy, wy) in &cy {
                if iy != usize::MAX {
                    map[ix * g + iy] += w * wx * wy;
                }
            }
        }
    }
    map
}
