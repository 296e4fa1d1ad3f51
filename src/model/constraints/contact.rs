//! Contact between shape-matched bodies: two bodies never overlap. Each pair of bodies
//! whose particles come closer than `distance` particle spacings is pushed apart along the
//! contact normal by their overlap along it (separating-axis depth), the two bodies
//! sharing the move in inverse proportion to their particle counts (equal particle masses,
//! so momentum is kept), as a rigid translation of each body. Applied before shape matching,
//! which then keeps each body's shape. This is position-based dynamics' rigid-body contact
//! resolved at the body level (Müller et al. 2007, section 3.5 "Collisions"; Macklin et al.
//! 2014, "Unified Particle Physics for Real-Time Applications", section 5: rigid bodies as
//! shape-matched particle sets with particle-particle contacts), not per particle: a per-
//! particle push on a few boundary particles would move a body by a fraction of its overlap.

use super::index::BodyIndex;
use super::shape::Body;
use super::ContactParams;
use crate::geometry::centre_of_mass;
use crate::neighbours::Bins;

/// Closing speeds below this (domain units per time unit; about three frames of gravity at
/// 0.016 time units a frame) are resting contact: stopped, not bounced.
pub const RESTING: f32 = 0.5;
/// The close pairs' mean direction is the contact normal when its length (1 when every pair
/// points the same way) is at least this.
const AGREE: f32 = 0.3;

/// A scene's bodies for contact: which body each particle belongs to.
#[derive(Debug, Clone, Default)]
pub(super) struct Contact {
    /// The shape-matched bodies' particles.
    bodies: BodyIndex,
    /// The contact distance: the largest spacing among the bodies' materials (domain units).
    spacing: f32,
}

impl Contact {
    /// The contact data of `bodies` in a scene of `n` particles, with `spacing` the particle
    /// spacing of each material id; None with fewer than two bodies.
    pub(super) fn new(bodies: &[Body], n: usize, spacing: &[f32]) -> Option<Self> {
        if bodies.len() < 2 {
            return None;
        }
        let widest = bodies
            .iter()
            .map(|body| spacing[usize::from(body.material)])
            .fold(0.0f32, f32::max);
        (widest > 0.0).then(|| Self {
            bodies: BodyIndex::new(bodies.iter().map(Body::ids), n),
            spacing: widest,
        })
    }

    /// Pushes overlapping bodies of `frame` (`[N, 4]` rows, `dt` time units after the last)
    /// apart (module doc) and sets their velocities by an impulse along each contact normal:
    /// a pair closing faster than [`RESTING`] leaves at `restitution` times that speed, a
    /// slower one stops closing. The push itself does not count as velocity (the velocity
    /// the projection gives every move, `dx / dt`, is taken back from it here).
    pub(super) fn separate(&self, p: &ContactParams, frame: &mut [f32], dt: f32) {
        let d = p.distance * self.spacing;
        let mut total = vec![[0.0f32; 2]; self.bodies.len()];
        let mut normals = std::collections::BTreeMap::new();
        for _ in 0..p.iterations.max(1) {
            let pushes = self.overlaps(frame, d);
            if pushes.is_empty() {
                break;
            }
            let mut shift = vec![[0.0f32; 2]; self.bodies.len()];
            for ((a, b), (normal, depth)) in pushes {
                normals.entry((a, b)).or_insert(normal);
                let (na, nb) = (self.size(a), self.size(b));
                let (wa, wb) = (nb / (na + nb), na / (na + nb));
                for k in 0..2 {
                    shift[a][k] += normal[k] * depth * wa;
                    shift[b][k] -= normal[k] * depth * wb;
                }
            }
            for (t, s) in total.iter_mut().zip(&shift) {
                t[0] += s[0];
                t[1] += s[1];
            }
            self.bodies.add(frame, &shift, 0);
        }
        if normals.is_empty() || dt <= 0.0 {
            return;
        }
        let mut dv: Vec<[f32; 2]> = total.iter().map(|s| [-s[0] / dt, -s[1] / dt]).collect();
        let mean = self.mean_velocities(frame);
        for ((a, b), n) in normals {
            let (ma, mb) = (self.size(a), self.size(b));
            let rel = (mean[a][0] - mean[b][0]) * n[0] + (mean[a][1] - mean[b][1]) * n[1];
            if rel >= 0.0 {
                continue;
            }
            let target = if -rel > RESTING {
                -p.restitution * rel
            } else {
                0.0
            };
            let j = (target - rel) / (1.0 / ma + 1.0 / mb);
            for k in 0..2 {
                dv[a][k] += j / ma * n[k];
                dv[b][k] -= j / mb * n[k];
            }
        }
        self.bodies.add(frame, &dv, 2);
    }

    /// The distance within which two bodies' particles touch (domain units).
    pub(super) fn reach(&self, p: &ContactParams) -> f32 {
        p.distance * self.spacing
    }

    /// The particle count of body `b`.
    fn size(&self, b: usize) -> f32 {
        self.bodies.of(b).len() as f32
    }

    /// Each body's mean velocity in `frame`.
    fn mean_velocities(&self, frame: &[f32]) -> Vec<[f32; 2]> {
        let mut v = vec![[0.0f32; 2]; self.bodies.len()];
        for &i in &self.bodies.ids {
            let b = self.bodies.body_of[i as usize] as usize;
            v[b][0] += frame[4 * i as usize + 2];
            v[b][1] += frame[4 * i as usize + 3];
        }
        for (b, v) in v.iter_mut().enumerate() {
            v[0] /= self.size(b);
            v[1] /= self.size(b);
        }
        v
    }

    /// Per pair of bodies `(a, b)`, `a < b`, with particles closer than `d`: the unit normal
    /// `n` from `b` towards `a` and the overlap along it, `d + max_b(x . n) - min_a(x . n)`
    /// (the separating-axis depth, right for convex bodies however deep they overlap: a
    /// body closing at a few domain units per time unit moves several particle spacings
    /// into another in one frame). `n` is the mean direction of the close particle pairs,
    /// or, where those disagree (a deep overlap), the line between the centres of mass.
    fn overlaps(&self, frame: &[f32], d: f32) -> Vec<((usize, usize), ([f32; 2], f32))> {
        let list = Bins::for_radius(frame, 4, &self.bodies.ids, d);
        let mut acc: std::collections::BTreeMap<(usize, usize), ([f32; 2], usize)> =
            Default::default();
        for &i in &self.bodies.ids {
            let bi = self.bodies.body_of[i as usize] as usize;
            let (x, y) = (frame[4 * i as usize], frame[4 * i as usize + 1]);
            list.around(x, y, |j| {
                let bj = self.bodies.body_of[j] as usize;
                if bj <= bi {
                    return;
                }
                let (dx, dy) = (x - frame[4 * j], y - frame[4 * j + 1]);
                let r = dx.hypot(dy);
                if r < d && r > 0.0 {
                    let e = acc.entry((bi, bj)).or_insert(([0.0; 2], 0));
                    e.0[0] += dx / r;
                    e.0[1] += dy / r;
                    e.1 += 1;
                }
            });
        }
        acc.into_iter()
            .filter_map(|((a, b), (sum, count))| {
                let mean = [sum[0] / count as f32, sum[1] / count as f32];
                let n = match mean[0].hypot(mean[1]) {
                    len if len >= AGREE => [mean[0] / len, mean[1] / len],
                    _ => {
                        let (ca, cb) = (self.centre(frame, a), self.centre(frame, b));
                        let (dx, dy) = (ca[0] - cb[0], ca[1] - cb[1]);
                        let len = dx.hypot(dy);
                        if len <= 0.0 {
                            return None;
                        }
                        [dx / len, dy / len]
                    }
                };
                let along =
                    |i: &u32| frame[4 * *i as usize] * n[0] + frame[4 * *i as usize + 1] * n[1];
                let low_a = self
                    .bodies
                    .of(a)
                    .iter()
                    .map(along)
                    .fold(f32::INFINITY, f32::min);
                let high_b = self
                    .bodies
                    .of(b)
                    .iter()
                    .map(along)
                    .fold(f32::NEG_INFINITY, f32::max);
                let depth = d + high_b - low_a;
                (depth > 0.0).then_some(((a, b), (n, depth)))
            })
            .collect()
    }

    /// The centre of mass of body `b` in `frame` (`[N, 4]`; [`centre_of_mass`]).
    fn centre(&self, frame: &[f32], b: usize) -> [f32; 2] {
        centre_of_mass(frame, 4, self.bodies.of(b)).map(|c| c as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::super::shape;
    use super::*;

    /// Two 6 x 6 lattices of jelly (spacing 0.01), the second `gap` to the right of the first.
    fn two_blocks(gap: f32) -> (Vec<f32>, Vec<u8>) {
        let mut frame = Vec::new();
        for x0 in [0.3f32, 0.3 + 0.05 + gap] {
            for i in 0..6 {
                for j in 0..6 {
                    frame.extend([x0 + 0.01 * i as f32, 0.5 + 0.01 * j as f32, 0.0, 0.0]);
                }
            }
        }
        let material = vec![1u8; frame.len() / 4];
        (frame, material)
    }

    #[test]
    fn overlapping_bodies_are_pushed_apart_and_their_centre_stays() {
        let (rest, material) = two_blocks(0.04);
        let bodies = shape::bodies(&rest, 4, &material, 1, 0.01);
        assert_eq!(bodies.len(), 2);
        let contact = Contact::new(&bodies, material.len(), &[0.0, 0.01, 0.0, 0.0]).unwrap();
        // The second block moved 0.035 left: its first column 0.005 from the first's last.
        let mut frame = rest.clone();
        for row in frame.chunks_exact_mut(4).skip(36) {
            row[0] -= 0.035;
        }
        let before: f32 = frame.chunks_exact(4).map(|r| r[0]).sum();
        let p = ContactParams {
            distance: 1.0,
            iterations: 4,
            restitution: 0.8,
        };
        contact.separate(&p, &mut frame, 0.016);
        let gap = frame
            .chunks_exact(4)
            .skip(36)
            .map(|r| r[0])
            .fold(1.0, f32::min)
            - frame
                .chunks_exact(4)
                .take(36)
                .map(|r| r[0])
                .fold(0.0, f32::max);
        assert!(gap >= 0.01 - 1e-5, "gap {gap}");
        let after: f32 = frame.chunks_exact(4).map(|r| r[0]).sum();
        assert!((after - before).abs() < 1e-3, "{before} -> {after}");
        // Bodies apart are left alone.
        let mut apart = rest.clone();
        contact.separate(&p, &mut apart, 0.016);
        assert_eq!(apart, rest);
    }

    #[test]
    fn closing_bodies_bounce_with_the_restitution_and_resting_ones_stop() {
        let (rest, material) = two_blocks(0.04);
        let bodies = shape::bodies(&rest, 4, &material, 1, 0.01);
        let contact = Contact::new(&bodies, material.len(), &[0.0, 0.01, 0.0, 0.0]).unwrap();
        let p = ContactParams {
            distance: 1.0,
            iterations: 3,
            restitution: 0.8,
        };
        // The velocity each block leaves with once the projection's `v += dx / dt` pass
        // (SceneShape::project) has run.
        let close = |speed: f32| {
            let mut frame = rest.clone();
            for (k, row) in frame.chunks_exact_mut(4).enumerate() {
                if k >= 36 {
                    row[0] -= 0.035;
                }
                row[2] = if k < 36 { speed } else { -speed };
            }
            let before = frame.clone();
            contact.separate(&p, &mut frame, 0.016);
            let leave = |range: std::ops::Range<usize>| {
                range
                    .map(|k| frame[4 * k + 2] + (frame[4 * k] - before[4 * k]) / 0.016)
                    .sum::<f32>()
                    / 36.0
            };
            (leave(0..36), leave(36..72))
        };
        // Closing at 2 (1 each): they leave at 1.6; the push took no velocity.
        let (a, b) = close(1.0);
        assert!((a + 0.8).abs() < 1e-3 && (b - 0.8).abs() < 1e-3, "{a} {b}");
        // Closing at 0.2: resting contact, stopped.
        let (a, b) = close(0.1);
        assert!(a.abs() < 1e-3 && b.abs() < 1e-3, "{a} {b}");
    }
}
