//! Conservation diagnostics of a rollout (docs/design.md, "Metrics"): does the prediction
//! move the bodies where the truth moves them, and does it keep the momentum that MPM keeps?
//!
//! - [`Bodies`]: the bodies of the rollout's first frame (connected pieces of each material,
//!   [`crate::model::constraints::pieces`]) and [`Bodies::com_error`], per material the mean
//!   over its bodies of the distance between the predicted and the true centre of mass
//!   (domain units). Particle order is the body's identity, so a body that tears or merges
//!   still has a centre of mass.
//! - [`MomentumDrift`]: MLS-MPM with APIC transfers conserves the total linear momentum
//!   `sum_p m v_p` exactly in the interior: only gravity and the walls change it (Jiang et
//!   al. 2015, "The affine particle-in-cell method", section 5; the walls zero the outward
//!   grid velocity, `docs/mpm.md`). With equal particle masses the mean velocity then changes
//!   by `g dt` per frame along any axis on which no particle is within [`WALL_CLEARANCE`] of
//!   a wall. The drift is the mean over such frame-to-frame transitions of `|dv_mean - g dt|`
//!   (Euclidean over the free axes; domain units per time unit, per frame): about 1e-6 for
//!   the solver's own frames, larger where a prediction creates or destroys momentum.
//!
//! Used by [`super::rollout`] at the probe steps, beside [`super::plausibility`].

use super::metrics::MATERIALS;
use crate::geometry::centre_of_mass;

/// A wall touches the grid nodes within 3 cells of it (`docs/mpm.md`); a particle farther than
/// this from it (5 cells of the 64 x 64 grid, plus the B-spline's reach) cannot be pushed by it.
pub const WALL_CLEARANCE: f32 = 0.08;
/// Gravity of the generated scenes and the default of scene files (domain units per time
/// unit squared).
pub const GRAVITY: [f64; 2] = [0.0, -9.8];

/// The bodies of a rollout's first frame.
#[derive(Debug, Clone, Default)]
pub struct Bodies {
    /// `(material id clamped to MATERIALS - 1, particle indices)` per body.
    pieces: Vec<(usize, Vec<u32>)>,
}

impl Bodies {
    /// The bodies of `frame` (`[N, 4]` physical) with material ids `material` (`[N]`).
    pub fn new(frame: &[f32], material: &[u8]) -> Self {
        let pieces = crate::model::constraints::pieces(frame, 4, material)
            .into_iter()
            .map(|(m, ids)| (usize::from(m).min(MATERIALS - 1), ids))
            .collect();
        Self { pieces }
    }

    /// Number of bodies.
    pub fn len(&self) -> usize {
        self.pieces.len()
    }

    /// Whether there is no body.
    pub fn is_empty(&self) -> bool {
        self.pieces.is_empty()
    }

    /// Per material, the mean over its bodies of `|com(pred) - com(truth)|` (both `[N, 4]`
    /// physical; domain units); `None` for a material without a body.
    pub fn com_error(&self, pred: &[f32], truth: &[f32]) -> [Option<f64>; MATERIALS] {
        let mut sum = [0.0f64; MATERIALS];
        let mut count = [0usize; MATERIALS];
        for (m, ids) in &self.pieces {
            let (p, t) = (centre_of_mass(pred, 4, ids), centre_of_mass(truth, 4, ids));
            sum[*m] += (p[0] - t[0]).hypot(p[1] - t[1]);
            count[*m] += 1;
        }
        std::array::from_fn(|m| (count[m] > 0).then(|| sum[m] / count[m] as f64))
    }
}

/// The momentum drift of one rollout (module doc), transition by transition.
#[derive(Debug, Clone, Default)]
pub struct MomentumDrift {
    /// Per transition `k - 1 -> k` (k = 1, 2, ...): the drift, `None` where every axis had a
    /// particle near a wall.
    per_step: Vec<Option<f64>>,
}

impl MomentumDrift {
    /// The drift of the frames `frame(0), frame(1), ..., frame(steps)` (each `[N, 4]`
    /// physical), `dt` apart (time units).
    pub fn of<'a>(frame: impl Fn(usize) -> &'a [f32], steps: usize, dt: f32) -> Self {
        let dt = f64::from(dt);
        let mut per_step = Vec::with_capacity(steps);
        let (mut before, mut clear_before) = mean_velocity(frame(0));
        for k in 1..=steps {
            let (now, clear_now) = mean_velocity(frame(k));
            let mut sq = 0.0;
            let mut free = false;
            for a in 0..2 {
                if clear_before[a] && clear_now[a] {
                    free = true;
                    sq += (now[a] - before[a] - GRAVITY[a] * dt).powi(2);
                }
            }
            per_step.push(free.then(|| sq.sqrt()));
            (before, clear_before) = (now, clear_now);
        }
        Self { per_step }
    }

    /// The mean drift over the free transitions among the first `k`; `None` without one.
    pub fn mean_to(&self, k: usize) -> Option<f64> {
        let free: Vec<f64> = self.per_step.iter().take(k).flatten().copied().collect();
        (!free.is_empty()).then(|| free.iter().sum::<f64>() / free.len() as f64)
    }
}

/// The mean velocity of `state` (`[N, 4]`), and per axis whether every particle keeps
/// [`WALL_CLEARANCE`] from both walls of that axis.
fn mean_velocity(state: &[f32]) -> ([f64; 2], [bool; 2]) {
    let mut v = [0.0f64; 2];
    let mut clear = [true; 2];
    let (lo, hi) = (WALL_CLEARANCE, 1.0 - WALL_CLEARANCE);
    for row in state.chunks_exact(4) {
        for a in 0..2 {
            v[a] += f64::from(row[2 + a]);
            clear[a] &= (lo..=hi).contains(&row[a]);
        }
    }
    let n = (state.len() / 4).max(1) as f64;
    ([v[0] / n, v[1] / n], clear)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two 5 x 5 blocks of particles 0.01 apart, one jelly and one liquid.
    fn two_blocks() -> (Vec<f32>, Vec<u8>) {
        let mut state = Vec::new();
        let mut material = Vec::new();
        for (m, x0) in [(1u8, 0.3f32), (0, 0.6)] {
            for i in 0..5 {
                for j in 0..5 {
                    state.extend([x0 + 0.01 * i as f32, 0.5 + 0.01 * j as f32, 0.0, 0.0]);
                    material.push(m);
                }
            }
        }
        (state, material)
    }

    #[test]
    fn a_shifted_body_has_its_shift_as_centre_of_mass_error() {
        let (state, material) = two_blocks();
        let bodies = Bodies::new(&state, &material);
        assert_eq!(bodies.len(), 2);
        let mut pred = state.clone();
        for row in pred.chunks_exact_mut(4).take(25) {
            row[0] += 0.03;
            row[1] -= 0.04;
        }
        let e = bodies.com_error(&pred, &state);
        assert!((e[1].unwrap() - 0.05).abs() < 1e-6, "{e:?}");
        assert!(e[0].unwrap() < 1e-9);
        assert_eq!(e[2], None);
    }

    #[test]
    fn free_fall_has_no_drift_and_a_push_has_its_size() {
        let (start, _) = two_blocks();
        let dt = 0.016f32;
        let frames: Vec<Vec<f32>> = (0..4)
            .map(|k| {
                let mut f = start.clone();
                for row in f.chunks_exact_mut(4) {
                    row[3] = -9.8 * dt * k as f32;
                }
                f
            })
            .collect();
        let d = MomentumDrift::of(|k| &frames[k], 3, dt);
        assert!(d.mean_to(3).unwrap() < 1e-6);
        let mut pushed = frames.clone();
        for row in pushed[3].chunks_exact_mut(4) {
            row[2] += 0.3;
        }
        let d = MomentumDrift::of(|k| &pushed[k], 3, dt);
        assert!(
            (d.mean_to(3).unwrap() - 0.1).abs() < 1e-6,
            "{:?}",
            d.mean_to(3)
        );
        // Near the floor the vertical axis is not free; the horizontal one still is.
        let mut low = frames.clone();
        for f in &mut low {
            f[1] = 0.01;
        }
        let d = MomentumDrift::of(|k| &low[k], 3, dt);
        assert!(d.mean_to(3).unwrap() < 1e-6);
    }
}
