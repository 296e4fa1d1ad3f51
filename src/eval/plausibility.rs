//! Physical plausibility of a predicted frame, independent of particle order (docs/design.md,
//! "Metrics"): how much the predicted material still looks like the true one, where the
//! per-particle MSE only says how far each particle is from its twin.
//!
//! - [`sinkhorn_divergence`]: the debiased Sinkhorn divergence between two point clouds with
//!   uniform weights and the squared Euclidean cost, `S(a, b) = OT(a, b) - OT(a, a) / 2 - OT(b,
//!   b) / 2` (Feydy et al. 2019, "Interpolating between optimal transport and MMD using
//!   Sinkhorn divergences", eq. 3), computed per material on the positions in domain units
//!   (domain units squared; as LagrangeBench, Toshev et al. 2023, section 4.2, reports it).
//!   `OT` is entropic optimal transport at blur `sqrt(eps)`, by symmetric Sinkhorn iterations
//!   in the log domain (Feydy's geomloss `sinkhorn_loop`, the averaged update). Clouds above
//!   [`SINKHORN_POINTS`] points are subsampled evenly by particle index (the same particles in
//!   both clouds).
//! - [`Neighbours::strain_error`] ([`Neighbours`] lives in [`super::structure`], re-exported
//!   here): for the solids (jelly, snow, rope), each particle's k nearest neighbours of the
//!   same material in the rollout's first frame, and the mean over particles and neighbours of
//!   `|d_pred / d_0 - d_true / d_0|`, `d` the current distance to the neighbour: zero when the
//!   prediction is a rigid motion of the truth, positive when it stretches, tears or crumples
//!   the body (dimensionless).
//! - [`kinetic_energy`]: per material `sum 1/2 |v|^2` (equal particle masses), summed over the
//!   rollout and taken prediction over truth.
//! - Structure ([`super::structure`]): the volume ratio (area covered, prediction over truth),
//!   the intact fraction of the solids' rest-neighbour pairs and the rope's connected share,
//!   prediction beside truth.
//! - Conservation ([`super::conservation`]): each body's centre-of-mass error and the momentum
//!   drift, prediction beside truth.
//!
//! [`Plausibility`] holds all of them per material for one frame. Used by [`super::rollout`]
//! (`minflow eval`) at the steps [`probe_steps`] picks.

use super::metrics::MATERIALS;
use super::structure::covered_area;
pub use super::structure::Neighbours;

/// At most this many points per cloud enter [`sinkhorn_divergence`] in [`Plausibility::of`].
pub const SINKHORN_POINTS: usize = 256;
/// The entropic regularisation `eps` (domain units squared): blur `sqrt(eps)` = 0.02, about
/// one grid cell of the 64 x 64 MPM grid.
pub const SINKHORN_EPS: f64 = 4e-4;
/// Sinkhorn iterations.
pub const SINKHORN_ITERS: usize = 40;

/// Plausibility of one predicted frame, per material (0 liquid, 1 jelly, 2 snow, 3 rope);
/// `None` where the scene has no particle of that material (and, for `strain`, for liquid).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Plausibility {
    /// Sinkhorn divergence of the position clouds, domain units squared.
    pub sinkhorn: [Option<f64>; MATERIALS],
    /// Strain error (solids only), dimensionless.
    pub strain: [Option<f64>; MATERIALS],
    /// Area covered, prediction over truth ([`super::structure::covered_area`]).
    pub volume: [Option<f64>; MATERIALS],
    /// Intact fraction of the rest-neighbour pairs (solids only), prediction.
    pub intact: [Option<f64>; MATERIALS],
    /// The same of the truth.
    pub intact_truth: [Option<f64>; MATERIALS],
    /// Share of the particles in the largest intact piece (solids only), prediction.
    pub connected: [Option<f64>; MATERIALS],
    /// The same of the truth.
    pub connected_truth: [Option<f64>; MATERIALS],
    /// Kinetic energy `sum 1/2 |v|^2` summed over the rollout's frames up to this one,
    /// prediction over truth (equal particle masses; [`kinetic_energy`]): 1 when the rollout
    /// keeps the truth's motion, below 1 when it loses energy.
    pub energy: [Option<f64>; MATERIALS],
    /// The same over every particle.
    pub energy_all: Option<f64>,
    /// Centre-of-mass error: per material, the mean over its bodies of the distance between
    /// the predicted and the true centre of mass, domain units
    /// ([`super::conservation::Bodies::com_error`]).
    pub com: [Option<f64>; MATERIALS],
    /// Momentum drift of the prediction up to this step, domain units per time unit per
    /// frame ([`super::conservation::MomentumDrift`]); `None` when no transition was free of
    /// the walls.
    pub momentum: Option<f64>,
    /// The same of the truth (about 1e-6: MPM conserves momentum).
    pub momentum_truth: Option<f64>,
}

impl Plausibility {
    /// The plausibility of `pred` against `truth` (both `[N, 4]` physical), with `material`
    /// ids `[N]` and the neighbours of the rollout's first frame.
    pub fn of(pred: &[f32], truth: &[f32], material: &[u8], neighbours: &Neighbours) -> Self {
        let mut out = Self::default();
        for m in 0..MATERIALS {
            let ids: Vec<usize> = (0..material.len())
                .filter(|&i| usize::from(material[i]).min(MATERIALS - 1) == m)
                .collect();
            if ids.is_empty() {
                continue;
            }
            let stride = ids.len().div_ceil(SINKHORN_POINTS);
            let cloud = |state: &[f32]| -> Vec<[f64; 2]> {
                ids.iter()
                    .step_by(stride)
                    .map(|&i| [f64::from(state[4 * i]), f64::from(state[4 * i + 1])])
                    .collect()
            };
            out.sinkhorn[m] = Some(sinkhorn_divergence(
                &cloud(pred),
                &cloud(truth),
                SINKHORN_EPS,
                SINKHORN_ITERS,
            ));
            out.strain[m] = neighbours.strain_error(pred, truth, m);
            let of_m = |i: usize| usize::from(material[i]).min(MATERIALS - 1) == m;
            let area = |state: &[f32]| covered_area(state, of_m);
            let true_area = area(truth);
            out.volume[m] = (true_area > 0).then(|| area(pred) as f64 / true_area as f64);
            out.intact[m] = neighbours.intact_fraction(pred, m);
            out.intact_truth[m] = neighbours.intact_fraction(truth, m);
            out.connected[m] = neighbours.connected_share(pred, m);
            out.connected_truth[m] = neighbours.connected_share(truth, m);
        }
        out
    }

    /// Field-wise mean of `all` (a material's mean over the frames that have it).
    pub fn mean(all: &[Plausibility]) -> Option<Plausibility> {
        if all.is_empty() {
            return None;
        }
        let mean = |f: &dyn Fn(&Plausibility) -> Option<f64>| {
            let v: Vec<f64> = all.iter().filter_map(f).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        Some(Plausibility {
            sinkhorn: std::array::from_fn(|m| mean(&|p| p.sinkhorn[m])),
            strain: std::array::from_fn(|m| mean(&|p| p.strain[m])),
            volume: std::array::from_fn(|m| mean(&|p| p.volume[m])),
            intact: std::array::from_fn(|m| mean(&|p| p.intact[m])),
            intact_truth: std::array::from_fn(|m| mean(&|p| p.intact_truth[m])),
            connected: std::array::from_fn(|m| mean(&|p| p.connected[m])),
            connected_truth: std::array::from_fn(|m| mean(&|p| p.connected_truth[m])),
            energy: std::array::from_fn(|m| mean(&|p| p.energy[m])),
            energy_all: mean(&|p| p.energy_all),
            com: std::array::from_fn(|m| mean(&|p| p.com[m])),
            momentum: mean(&|p| p.momentum),
            momentum_truth: mean(&|p| p.momentum_truth),
        })
    }
}

/// The kinetic energy `sum_i 1/2 |v_i|^2` of `state` (`[N, 4]` physical) per material id
/// (ids past the last in the last entry) and over all particles, with unit particle mass
/// (MPM gives every particle of a scene the same mass).
pub fn kinetic_energy(state: &[f32], material: &[u8]) -> ([f64; MATERIALS], f64) {
    let mut per = [0.0f64; MATERIALS];
    for (row, &m) in state.chunks_exact(4).zip(material) {
        let (vx, vy) = (f64::from(row[2]), f64::from(row[3]));
        per[usize::from(m).min(MATERIALS - 1)] += 0.5 * (vx * vx + vy * vy);
    }
    (per, per.iter().sum())
}

/// A rollout's kinetic energy ([`kinetic_energy`]) summed over its first k frames,
/// prediction and truth, per material and over all particles.
pub struct EnergySums {
    /// `[steps]`: cumulative (per material, all) of the prediction.
    pred: Vec<([f64; MATERIALS], f64)>,
    /// The same of the truth.
    truth: Vec<([f64; MATERIALS], f64)>,
}

impl EnergySums {
    /// The sums of `pairs`, `(prediction, truth)` frames (`[N, 4]` physical) in step order
    /// from step 1, with material ids `material`.
    pub fn of<'a>(pairs: impl Iterator<Item = (&'a [f32], &'a [f32])>, material: &[u8]) -> Self {
        let (mut pred, mut truth) = (Vec::new(), Vec::new());
        let (mut acc_p, mut acc_t) = (([0.0; MATERIALS], 0.0), ([0.0; MATERIALS], 0.0));
        for (p, t) in pairs {
            for (acc, sums, frame) in [(&mut acc_p, &mut pred, p), (&mut acc_t, &mut truth, t)] {
                let (per, all) = kinetic_energy(frame, material);
                (0..MATERIALS).for_each(|m| acc.0[m] += per[m]);
                acc.1 += all;
                sums.push(*acc);
            }
        }
        Self { pred, truth }
    }

    /// The steps summed.
    pub fn steps(&self) -> usize {
        self.pred.len()
    }

    /// Prediction over truth of the sums up to step `k` (1-based), per material and over all;
    /// None where the truth's is 0, the scene has no such particle, or `k` is not a step.
    pub fn ratio_at(&self, k: usize) -> ([Option<f64>; MATERIALS], Option<f64>) {
        let ratio = |p: f64, t: f64| (t > 0.0).then(|| p / t);
        let at =
            |v: &Vec<([f64; MATERIALS], f64)>| k.checked_sub(1).and_then(|i| v.get(i).copied());
        match (at(&self.pred), at(&self.truth)) {
            (Some(p), Some(t)) => (
                std::array::from_fn(|m| ratio(p.0[m], t.0[m])),
                ratio(p.1, t.1),
            ),
            _ => ([None; MATERIALS], None),
        }
    }
}

/// The steps at which a rollout of `steps` steps is probed: 20, 50, 100, 200, 400, ... up to
/// `steps`, and `steps` itself.
pub fn probe_steps(steps: usize) -> Vec<usize> {
    let mut out: Vec<usize> = [20, 50, 100]
        .into_iter()
        .chain((0..).map(|i| 200 << i))
        .take_while(|&k| k < steps)
        .collect();
    if steps > 0 {
        out.push(steps);
    }
    out
}

/// Entropic OT cost `OT_eps(a, b)` between uniform clouds `a` and `b` (domain units squared),
/// by `iters` symmetric log-domain Sinkhorn iterations (dual potentials `f` on `a`, `g` on
/// `b`; each iteration averages the old and the new potential, as geomloss does), then
/// `mean f + mean g`.
fn entropic_ot(a: &[[f64; 2]], b: &[[f64; 2]], eps: f64, iters: usize) -> f64 {
    let cost = |p: &[f64; 2], q: &[f64; 2]| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2);
    let (log_a, log_b) = (-(a.len() as f64).ln(), -(b.len() as f64).ln());
    // softmin_eps over the other cloud: -eps log sum_j exp(log w_j + (h_j - C_ij) / eps).
    let softmin = |x: &[f64; 2], ys: &[[f64; 2]], h: &[f64], log_w: f64| {
        let terms = ys.iter().zip(h).map(|(y, hj)| (hj - cost(x, y)) / eps);
        let top = terms.clone().fold(f64::NEG_INFINITY, f64::max);
        let sum: f64 = terms.map(|t| (t - top).exp()).sum();
        -eps * (log_w + top + sum.ln())
    };
    let (mut f, mut g) = (vec![0.0; a.len()], vec![0.0; b.len()]);
    for _ in 0..iters {
        let f_new: Vec<f64> = a.iter().map(|x| softmin(x, b, &g, log_b)).collect();
        let g_new: Vec<f64> = b.iter().map(|y| softmin(y, a, &f, log_a)).collect();
        for (old, new) in f.iter_mut().zip(f_new) {
            *old = 0.5 * (*old + new);
        }
        for (old, new) in g.iter_mut().zip(g_new) {
            *old = 0.5 * (*old + new);
        }
    }
    // A last, undamped update of each potential at the converged other.
    let f_last: Vec<f64> = a.iter().map(|x| softmin(x, b, &g, log_b)).collect();
    let g_last: Vec<f64> = b.iter().map(|y| softmin(y, a, &f, log_a)).collect();
    f_last.iter().sum::<f64>() / a.len() as f64 + g_last.iter().sum::<f64>() / b.len() as f64
}

/// The debiased Sinkhorn divergence `S(a, b) = OT(a, b) - OT(a, a) / 2 - OT(b, b) / 2`
/// between uniform point clouds (see the module doc), domain units squared; 0 for two empty
/// clouds, NaN when only one is empty. Non-negative and 0 for equal clouds; for a cloud and
/// its translate by `h` it tends to `|h|^2` as `eps` goes to 0.
pub fn sinkhorn_divergence(a: &[[f64; 2]], b: &[[f64; 2]], eps: f64, iters: usize) -> f64 {
    match (a.is_empty(), b.is_empty()) {
        (true, true) => return 0.0,
        (true, false) | (false, true) => return f64::NAN,
        _ => {}
    }
    let ab = entropic_ot(a, b, eps, iters);
    let aa = entropic_ot(a, a, eps, iters);
    let bb = entropic_ot(b, b, eps, iters);
    (ab - 0.5 * (aa + bb)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One point against one point: the only plan moves all mass, OT(a, b) = |a - b|^2 and
    /// OT(a, a) = 0 whatever eps, so S = |a - b|^2 = 0.3^2 + 0.4^2 = 0.25.
    #[test]
    fn single_points_give_the_squared_distance() {
        let s = sinkhorn_divergence(&[[0.1, 0.2]], &[[0.4, 0.6]], 1e-3, 20);
        assert!((s - 0.25).abs() < 1e-9, "{s}");
    }

    /// Two points 0.5 apart against their translate by h = (0, 0.01): with eps far below the
    /// spacing squared each point is matched to its own translate, S -> h^2 = 1e-4. Equal
    /// clouds give 0.
    #[test]
    fn a_translated_cloud_gives_its_squared_shift() {
        let a = [[0.2, 0.5], [0.7, 0.5]];
        let b = [[0.2, 0.51], [0.7, 0.51]];
        let s = sinkhorn_divergence(&a, &b, 1e-5, 50);
        assert!((s - 1e-4).abs() < 2e-6, "{s}");
        assert!(sinkhorn_divergence(&a, &a, 1e-5, 50).abs() < 1e-12);
    }

    /// The order of the particles does not matter.
    #[test]
    fn particle_order_does_not_matter() {
        let a: Vec<[f64; 2]> = (0..30)
            .map(|i| [0.1 + 0.02 * i as f64, 0.3 + 0.01 * (i % 7) as f64])
            .collect();
        let b: Vec<[f64; 2]> = a.iter().map(|p| [p[0] + 0.03, p[1]]).collect();
        let mut rev = b.clone();
        rev.reverse();
        let (s, r) = (
            sinkhorn_divergence(&a, &b, 4e-4, 40),
            sinkhorn_divergence(&a, &rev, 4e-4, 40),
        );
        assert!((s - r).abs() < 1e-12 && s > 0.0, "{s} {r}");
    }

    /// A jelly square of 5 x 5 particles: rotating and translating the prediction leaves the
    /// strain error at 0; stretching it by 10 % along x gives a positive error, at most 0.1
    /// (no neighbour distance changes by more than 10 %).
    #[test]
    fn strain_is_zero_for_rigid_motion_and_positive_for_a_stretch() {
        let frame: Vec<f32> = (0..25)
            .flat_map(|i| {
                [
                    0.4 + 0.01 * (i % 5) as f32,
                    0.4 + 0.01 * (i / 5) as f32,
                    0.,
                    0.,
                ]
            })
            .collect();
        let material = vec![1u8; 25];
        let nb = Neighbours::new(&frame, &material);
        let (c, s) = (0.3f32.cos(), 0.3f32.sin());
        let rigid: Vec<f32> = frame
            .chunks_exact(4)
            .flat_map(|r| {
                [
                    c * r[0] - s * r[1] + 0.1,
                    s * r[0] + c * r[1] - 0.05,
                    0.,
                    0.,
                ]
            })
            .collect();
        let stretched: Vec<f32> = frame
            .chunks_exact(4)
            .flat_map(|r| [0.4 + 1.1 * (r[0] - 0.4), r[1], 0., 0.])
            .collect();
        let rigid_err = nb.strain_error(&rigid, &frame, 1).unwrap();
        let stretch_err = nb.strain_error(&stretched, &frame, 1).unwrap();
        assert!(rigid_err < 1e-5, "{rigid_err}");
        assert!(
            stretch_err > 0.02 && stretch_err <= 0.1 + 1e-5,
            "{stretch_err}"
        );
        assert_eq!(
            nb.strain_error(&frame, &frame, 0),
            None,
            "liquid has no strain"
        );
    }

    #[test]
    fn probe_steps_cover_the_horizon() {
        assert_eq!(probe_steps(20), vec![20]);
        assert_eq!(probe_steps(5), vec![5]);
        assert_eq!(probe_steps(100), vec![20, 50, 100]);
        assert_eq!(probe_steps(623), vec![20, 50, 100, 200, 400, 623]);
    }
}
