//! Shape matching of solid bodies (Müller, Heidelberger, Teschner & Gross 2005, "Meshless
//! Deformations Based on Shape Matching", sections 3-4): a body's particles are pulled
//! towards goal positions `g_i = G q_i + c`, with `c` their centre of mass, `q_i` their rest
//! offsets from the rest centre, and `G` the rotation `R` of the polar decomposition of
//! `A_pq = sum_i (x_i - c) q_i^T`, blended with the volume-preserving linear fit
//! `A = A_pq A_qq^-1 / sqrt(det)` by `linear` (the paper's beta). Each particle moves
//! `stiffness` of the way (alpha). The centre of mass is kept, so momentum is too. With
//! `plastic` > 0 the rest offsets take on that share of the remaining deformation each frame
//! (`q_i += plastic (R^T (x_i - c) - q_i)`): a rest shape that yields, as the solver's snow
//! does (its singular values clamped, docs/mpm.md).
//!
//! A body is a connected piece of one material in the scene's rest frame: particles closer
//! than [`LINK`] spacings are joined (union-find, [`Components`]).

use super::ShapeParams;
use crate::geometry::centre_of_mass;
use crate::neighbours::Components;

/// Particles of one material closer than this many spacings in the rest frame belong to one
/// body.
const LINK: f32 = 2.5;

/// One body: its particles and their rest shape.
#[derive(Clone, Debug)]
pub(super) struct Body {
    /// Material id.
    pub(super) material: u8,
    ids: Vec<u32>,
    /// `[len]`: rest offsets from the rest centre of mass (domain units).
    rest: Vec<[f32; 2]>,
    /// `A_qq^-1`, row-major.
    aqq_inv: [f32; 4],
}

/// The bodies of material `m` in `rest` (`[N, stride]` rows) whose spacing is `spacing`:
/// [`pieces`] turned into shape-matching bodies.
pub(super) fn bodies(
    rest: &[f32],
    stride: usize,
    material: &[u8],
    m: u8,
    spacing: f32,
) -> Vec<Body> {
    pieces(rest, stride, material, m, spacing)
        .into_iter()
        .map(|p| Body::new(rest, stride, m, p))
        .collect()
}

/// The connected pieces of material `m` in `rest` (`[N, stride]` rows) whose spacing is
/// `spacing`: particles closer than [`LINK`] spacings are joined
/// ([`Components::join_within`]); pieces of 3 particles or more, each its particle indices in increasing
/// order, the pieces in order of their lowest index.
pub(super) fn pieces(
    rest: &[f32],
    stride: usize,
    material: &[u8],
    m: u8,
    spacing: f32,
) -> Vec<Vec<u32>> {
    let ids: Vec<u32> = (0..material.len() as u32)
        .filter(|&i| material[i as usize] == m)
        .collect();
    if ids.len() < 3 || spacing <= 0.0 {
        return Vec::new();
    }
    let mut sets = Components::new(material.len());
    sets.join_within(rest, stride, &ids, LINK * spacing);
    let mut pieces = sets.groups(&ids);
    pieces.retain(|p| p.len() >= 3);
    pieces
}

impl Body {
    /// The body's particles, in increasing order.
    pub(super) fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// The body's rest offsets from its rest centre (domain units, `[len]`) and `A_qq^-1`
    /// (row-major).
    pub(super) fn rest_shape(&self) -> (&[[f32; 2]], [f32; 4]) {
        (&self.rest, self.aqq_inv)
    }

    fn new(rest: &[f32], stride: usize, material: u8, ids: Vec<u32>) -> Self {
        let at = |i: u32| [rest[stride * i as usize], rest[stride * i as usize + 1]];
        let c = centre_of_mass(rest, stride, &ids).map(|c| c as f32);
        let rest: Vec<[f32; 2]> = ids
            .iter()
            .map(|&i| {
                let p = at(i);
                [p[0] - c[0], p[1] - c[1]]
            })
            .collect();
        let mut body = Self {
            material,
            ids,
            rest,
            aqq_inv: [0.0; 4],
        };
        body.aqq_inv = body.aqq_inverse();
        body
    }

    /// `(sum_i q_i q_i^T)^-1`, row-major (0 when singular: a body in a line).
    fn aqq_inverse(&self) -> [f32; 4] {
        let mut a = [0.0f64; 3];
        for q in &self.rest {
            let (x, y) = (f64::from(q[0]), f64::from(q[1]));
            a[0] += x * x;
            a[1] += x * y;
            a[2] += y * y;
        }
        let det = a[0] * a[2] - a[1] * a[1];
        if det.abs() < 1e-18 {
            return [0.0; 4];
        }
        [a[2] / det, -a[1] / det, -a[1] / det, a[0] / det].map(|v| v as f32)
    }

    /// Moves the body's particles in `frame` (`[N, 4]` rows) towards their goal positions
    /// (module doc); with `p.plastic` > 0 the rest shape yields.
    pub(super) fn project(&mut self, p: &ShapeParams, frame: &mut [f32]) {
        let at = |frame: &[f32], i: u32| [frame[4 * i as usize], frame[4 * i as usize + 1]];
        let c = centre_of_mass(frame, 4, &self.ids).map(|c| c as f32);
        let mut apq = [0.0f64; 4];
        for (&i, q) in self.ids.iter().zip(&self.rest) {
            let x = at(frame, i);
            let d = [f64::from(x[0] - c[0]), f64::from(x[1] - c[1])];
            apq[0] += d[0] * f64::from(q[0]);
            apq[1] += d[0] * f64::from(q[1]);
            apq[2] += d[1] * f64::from(q[0]);
            apq[3] += d[1] * f64::from(q[1]);
        }
        // The rotation of the polar decomposition of a 2 x 2 matrix.
        let theta = (apq[2] - apq[1]).atan2(apq[0] + apq[3]);
        let (s, co) = (theta.sin() as f32, theta.cos() as f32);
        let rot = [co, -s, s, co];
        let goal = if p.linear > 0.0 {
            let q = self.aqq_inv;
            let a = [
                apq[0] as f32 * q[0] + apq[1] as f32 * q[2],
                apq[0] as f32 * q[1] + apq[1] as f32 * q[3],
                apq[2] as f32 * q[0] + apq[3] as f32 * q[2],
                apq[2] as f32 * q[1] + apq[3] as f32 * q[3],
            ];
            let det = a[0] * a[3] - a[1] * a[2];
            match det > 1e-12 {
                true => {
                    let k = 1.0 / det.sqrt();
                    std::array::from_fn(|r| p.linear * a[r] * k + (1.0 - p.linear) * rot[r])
                }
                false => rot,
            }
        } else {
            rot
        };
        for (&i, q) in self.ids.iter().zip(self.rest.iter_mut()) {
            let i = 4 * i as usize;
            let g = [
                goal[0] * q[0] + goal[1] * q[1] + c[0],
                goal[2] * q[0] + goal[3] * q[1] + c[1],
            ];
            frame[i] += p.stiffness * (g[0] - frame[i]);
            frame[i + 1] += p.stiffness * (g[1] - frame[i + 1]);
            if p.plastic > 0.0 {
                // R^T (x - c): the particle's offset in the body's rest orientation.
                let d = [frame[i] - c[0], frame[i + 1] - c[1]];
                let back = [co * d[0] + s * d[1], -s * d[0] + co * d[1]];
                q[0] += p.plastic * (back[0] - q[0]);
                q[1] += p.plastic * (back[1] - q[1]);
            }
        }
        if p.plastic > 0.0 && p.linear > 0.0 {
            self.aqq_inv = self.aqq_inverse();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::model::constraints::spacing::lattice as block;

    #[test]
    fn two_apart_blocks_are_two_bodies() {
        let mut rest = block();
        rest.extend(block().chunks(4).flat_map(|r| [r[0] + 0.3, r[1], 0.0, 0.0]));
        let material = vec![1u8; 200];
        let found = bodies(&rest, 4, &material, 1, 0.01);
        assert_eq!(found.len(), 2);
        assert_eq!(found[0].ids.len(), 100);
    }

    #[test]
    fn a_rigidly_moved_body_stays_and_a_squashed_one_is_restored_to_a_rotation() {
        let rest = block();
        let material = vec![1u8; 100];
        let mut body = bodies(&rest, 4, &material, 1, 0.01).remove(0);
        let rigid = ShapeParams {
            stiffness: 1.0,
            linear: 0.0,
            plastic: 0.0,
        };
        // Rotated by 30 degrees about (0.5, 0.5) and moved: unchanged by the projection.
        let (s, c) = (0.5f32, 0.75f32.sqrt());
        let mut moved: Vec<f32> = rest
            .chunks(4)
            .flat_map(|r| {
                let (x, y) = (r[0] - 0.5, r[1] - 0.5);
                [c * x - s * y + 0.6, s * x + c * y + 0.4, 0.0, 0.0]
            })
            .collect();
        let want = moved.clone();
        body.project(&rigid, &mut moved);
        let err = moved
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-5, "{err}");
        // Squashed to half its height about its centre: back to the rest shape, same centre.
        let mut squashed: Vec<f32> = rest
            .chunks(4)
            .flat_map(|r| [r[0], 0.345 + 0.5 * (r[1] - 0.345), 0.0, 0.0])
            .collect();
        body.project(&rigid, &mut squashed);
        let err = squashed
            .iter()
            .zip(&rest)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-5, "{err}");
    }

    #[test]
    fn a_plastic_rest_shape_takes_on_the_deformation() {
        let rest = block();
        let material = vec![2u8; 100];
        let mut body = bodies(&rest, 4, &material, 2, 0.01).remove(0);
        let plastic = ShapeParams {
            stiffness: 0.5,
            linear: 0.0,
            plastic: 1.0,
        };
        let squash = |r: &[f32]| [r[0], 0.345 + 0.5 * (r[1] - 0.345), 0.0, 0.0];
        let mut frame: Vec<f32> = rest.chunks(4).flat_map(squash).collect();
        body.project(&plastic, &mut frame);
        // The rest shape is now the half-way shape: projecting it again moves nothing.
        let again = frame.clone();
        body.project(&plastic, &mut frame);
        let err = frame
            .iter()
            .zip(&again)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-5, "{err}");
    }
}
