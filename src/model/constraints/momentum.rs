//! Momentum of free clusters: the one law of the solver a frame-to-frame projection can keep
//! exactly. MLS-MPM with APIC transfers conserves the total linear momentum of particles that
//! share grid nodes with no other particles and no wall (Jiang et al. 2015, "The affine
//! particle-in-cell method", section 5): the stress forces of a body on the grid sum to zero,
//! and only gravity changes its momentum. Over a frame of `S` substeps of `h = dt / S`
//! (symplectic Euler: the velocity first, then `x += h v`, docs/mpm.md check 3) a cluster of
//! equal-mass particles that stays clear of the walls and of every other particle then has
//!
//! ```text
//! v_mean' = v_mean + g dt
//! x_mean' = x_mean + v_mean dt + g dt^2 (1 + 1/S) / 2
//! ```
//!
//! along each axis, whatever its material does inside. [`conserve`] finds the clusters of a
//! frame transition (particles linked where they are within [`MomentumParams::reach`] in the
//! frame before or the predicted one, union-find over [`crate::neighbours::Bins`]) and moves
//! each free cluster rigidly so that its centre of mass and mean velocity are these: a
//! translation of its positions and a uniform change of its velocities, leaving its shape,
//! strain and spin as the network and the other parts made them.

use super::MomentumParams;
use crate::geometry::centre_of_mass;
use crate::neighbours::Components;

/// Moves each free cluster of the transition `prev -> frame` (both `[N, 4]` physical x, y,
/// vx, vy) onto the free-flight law of the module doc, in place; `before` (`[N, 4]`) is the
/// network's frame before this projection, whose position moves the caller turns into
/// velocity (`v += (x - x_before) / dt` after the projection): the velocity set here is the
/// one the frame ends with. An axis of a cluster is free where every particle of the cluster
/// keeps [`MomentumParams::clearance`] from both walls of that axis in both frames.
pub(super) fn conserve(
    p: &MomentumParams,
    prev: &[f32],
    before: &[f32],
    frame: &mut [f32],
    dt: f32,
) {
    let n = frame.len() / 4;
    if n == 0 || prev.len() != frame.len() || before.len() != frame.len() || dt <= 0.0 {
        return;
    }
    let (lo, hi) = (p.clearance, 1.0 - p.clearance);
    let lag = 0.5 * (1.0 + 1.0 / p.substeps.max(1) as f64);
    let dt64 = f64::from(dt);
    for ids in clusters(prev, frame, p.reach) {
        let (x_prev, x_now) = (
            centre_of_mass(prev, 4, &ids),
            centre_of_mass(frame, 4, &ids),
        );
        for a in 0..2 {
            let free = ids.iter().all(|&i| {
                let i = i as usize;
                (lo..=hi).contains(&prev[4 * i + a]) && (lo..=hi).contains(&frame[4 * i + a])
            });
            if !free {
                continue;
            }
            // Means in f64: the cluster's x (its centre of mass) and v before, and the
            // frame's as it would end (its velocity plus the position moves so far over dt).
            // Moving axis 0 leaves axis 1's centre as it was, so both are taken once above.
            let (mut vp, mut vc) = (0.0f64, 0.0f64);
            for &i in &ids {
                let i = i as usize;
                vp += f64::from(prev[4 * i + 2 + a]);
                vc += f64::from(frame[4 * i + 2 + a])
                    + f64::from(frame[4 * i + a] - before[4 * i + a]) / dt64;
            }
            let m = ids.len() as f64;
            let (xp, vp, xc, vc) = (x_prev[a], vp / m, x_now[a], vc / m);
            let g = f64::from(p.gravity[a]);
            let shift = xp + vp * dt64 + lag * g * dt64 * dt64 - xc;
            // The velocity to add beyond the shift's own `shift / dt`, which the caller adds.
            let kick = vp + g * dt64 - vc - shift / dt64;
            let (shift, kick) = (shift as f32, kick as f32);
            for &i in &ids {
                let i = i as usize;
                frame[4 * i + a] += shift;
                frame[4 * i + 2 + a] += kick;
            }
        }
    }
}

/// The clusters of the transition `prev -> frame` (`[N, 4]` each): particles joined where
/// they are within `reach` of each other in either frame. Each cluster its particle indices
/// in increasing order, the clusters by their lowest index.
fn clusters(prev: &[f32], frame: &[f32], reach: f32) -> Vec<Vec<u32>> {
    let n = frame.len() / 4;
    let ids: Vec<u32> = (0..n as u32).collect();
    let mut sets = Components::new(n);
    for state in [prev, frame] {
        sets.join_within(state, 4, &ids, reach);
    }
    sets.groups(&ids)
}

#[cfg(test)]
mod tests {
    use super::super::block;
    use super::*;

    fn params() -> MomentumParams {
        MomentumParams {
            reach: 0.07,
            clearance: 0.08,
            substeps: 20,
            gravity: [0.0, -9.8],
        }
    }

    #[test]
    fn clusters_join_particles_near_in_either_frame() {
        // Two blocks 0.2 apart before, touching in the predicted frame: one cluster; a third
        // far in both: its own.
        let prev = [
            block(0.2, 0.5, [0.0; 2]),
            block(0.44, 0.5, [0.0; 2]),
            block(0.2, 0.2, [0.0; 2]),
        ]
        .concat();
        let mut frame = prev.clone();
        for row in frame.chunks_exact_mut(4).skip(25).take(25) {
            row[0] -= 0.18;
        }
        let found = clusters(&prev, &frame, 0.07);
        assert_eq!(found.iter().map(Vec::len).collect::<Vec<_>>(), vec![50, 25]);
        assert_eq!(&found[0][..3], &[0, 1, 2]);
        assert_eq!(found[1][0], 50);
        assert_eq!(clusters(&prev, &prev, 0.07).len(), 3);
    }

    #[test]
    fn a_free_cluster_follows_free_flight_and_keeps_its_shape() {
        let dt = 0.016f32;
        let prev = block(0.4, 0.5, [1.0, 0.5]);
        // The network lost momentum and squashed the block: its x a bit short, each
        // particle's own offset kept.
        let mut frame = prev.clone();
        for (k, row) in frame.chunks_exact_mut(4).enumerate() {
            row[0] += 0.8 * dt + 1e-4 * k as f32;
            row[1] += 0.2 * dt;
            row[2] = 0.8;
            row[3] = 0.2;
        }
        let before = frame.clone();
        let net = frame.clone();
        conserve(&params(), &prev, &before, &mut frame, dt);
        let mean =
            |f: &[f32], c: usize| f.chunks_exact(4).map(|r| f64::from(r[c])).sum::<f64>() / 25.0;
        let lag = 0.5 * (1.0 + 1.0 / 20.0);
        let dt64 = f64::from(dt);
        let want_x = mean(&prev, 0) + 1.0 * dt64;
        let want_y = mean(&prev, 1) + 0.5 * dt64 - lag * 9.8 * dt64 * dt64;
        assert!((mean(&frame, 0) - want_x).abs() < 1e-6);
        assert!((mean(&frame, 1) - want_y).abs() < 1e-6);
        // The caller adds (x - before) / dt to the velocities: then v' = v + g dt.
        let end_v = |c: usize| {
            frame
                .chunks_exact(4)
                .zip(before.chunks_exact(4))
                .map(|(r, b)| f64::from(r[2 + c]) + f64::from(r[c] - b[c]) / dt64)
                .sum::<f64>()
                / 25.0
        };
        assert!((end_v(0) - 1.0).abs() < 1e-4, "{}", end_v(0));
        assert!((end_v(1) - (0.5 - 9.8 * dt64)).abs() < 1e-4, "{}", end_v(1));
        // A translation: the particles' offsets from each other are the network's.
        for (r, o) in frame.chunks_exact(4).zip(net.chunks_exact(4)) {
            let d = (r[0] - o[0]) - (frame[0] - net[0]);
            assert!(d.abs() < 1e-6);
        }
    }

    #[test]
    fn an_axis_near_a_wall_is_left_alone() {
        let dt = 0.016f32;
        // On the floor: y within the clearance, x free.
        let prev = block(0.4, 0.02, [1.0, 0.0]);
        let mut frame = prev.clone();
        for row in frame.chunks_exact_mut(4) {
            row[0] += 0.5 * dt;
            row[2] = 0.5;
        }
        let before = frame.clone();
        let net = frame.clone();
        conserve(&params(), &prev, &before, &mut frame, dt);
        for (r, o) in frame.chunks_exact(4).zip(net.chunks_exact(4)) {
            assert_eq!((r[1], r[3]), (o[1], o[3]));
            assert!((r[0] - (o[0] + 0.5 * dt)).abs() < 1e-6);
        }
    }
}
