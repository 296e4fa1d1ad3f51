//! The projection's data laid out for a device: [`liquid_plan`], the liquid's pressure part,
//! the walls, the velocity update and the energy given back for every scene of a call, as
//! flat arrays a GPU's kernels read (`crate::ops::LiquidPlan`). The kernels there are the device
//! form of [`SceneShape::project`] for scenes whose only parts are those (every scene of the
//! `fluid` family, the liquid-only scenes of `multi`): the same steps in the same order, the
//! same arithmetic per node and particle, with the grid's sums in fixed point (the order the
//! atomics land in changes no bit) where the host sums in particle order.
//!
//! A scene with rope, bodies, contact, the density part or the momentum part has no plan:
//! its call projects on the host (`model::store`'s `finish_here`).

use super::{Constraints, SceneShape};
use crate::material::Material;
use crate::ops::{LiquidPlan, MATERIALS, SCENE_VALUES};

const _: () = assert!(MATERIALS == crate::material::COUNT);

/// The plan for a call of the scenes `shapes` (each `[N]` particles with materials
/// `material[s N..(s + 1) N]` and time step `dt[s]`) and K frames a scene, or None when
/// `c` has a part the device does not project (rope, jelly, snow, the density part,
/// contact, momentum, rebound) that acts on one of the scenes.
pub fn liquid_plan(
    c: &Constraints,
    shapes: &[&SceneShape],
    material: &[u8],
    dt: &[f32],
    k: usize,
) -> Option<LiquidPlan> {
    let known = material.iter().all(|&m| usize::from(m) < MATERIALS);
    if c.momentum.is_some() || shapes.is_empty() || shapes.len() != dt.len() || !known {
        return None;
    }
    let b = shapes.len();
    let n = material.len() / b;
    let liquid = Material::Liquid.id();
    let mut plan = LiquidPlan {
        b,
        n,
        k,
        volume: material.iter().map(|&m| -(1.0 + f32::from(m))).collect(),
        liquid,
        counts: [0; MATERIALS],
        scenes: vec![0.0; b * SCENE_VALUES],
        nodes: 1,
        stiffness: 0.0,
        full: 0.0,
        omega: 1.0,
        iterations: 0,
        velocity: false,
        restore: 0.0,
        walls: c.walls.is_some(),
    };
    if let Some(p) = &c.pressure {
        (plan.stiffness, plan.full, plan.omega) = (p.stiffness, p.full, p.omega);
        (plan.iterations, plan.velocity) = (p.iterations, p.velocity);
        plan.restore = p.restore.min(1.0);
    }
    for (s, shape) in shapes.iter().enumerate() {
        let on_host_only = !shape.chains.is_empty()
            || !shape.bodies.is_empty()
            || shape.contact.is_some()
            || shape.liquid.is_some()
            || shape.rebound.is_some()
            || shape.n != n;
        if on_host_only {
            return None;
        }
        let (lo, hi) = c.walls.map_or((0.0, 1.0), |w| w.bounds(shape.grid));
        let row = &mut plan.scenes[s * SCENE_VALUES..(s + 1) * SCENE_VALUES];
        row[5..8].copy_from_slice(&[lo, hi, dt[s]]);
        for (m, v) in row[10..].iter_mut().enumerate() {
            *v = shape.spacing(m as u8);
        }
        let (Some(_), Some(d)) = (&c.pressure, &shape.pressure) else {
            continue;
        };
        row[..5].copy_from_slice(&[d.h, d.side as f32, d.rest, d.band.0, d.band.1]);
        row[8] = d.solid_volume();
        plan.nodes = plan.nodes.max(d.side * d.side);
        let volume = &mut plan.volume[s * n..(s + 1) * n];
        for (&i, &v) in d.ids.iter().zip(&d.volume) {
            volume[i as usize] = v;
        }
        debug_assert!(d
            .ids
            .iter()
            .all(|&i| material[s * n + i as usize] == liquid));
    }
    for &m in material {
        plan.counts[usize::from(m)] += 1;
    }
    Some(plan)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w x h` block of `material` at spacing 1/128 from `(x0, y0)` (`[N, 4]` rows).
    fn block(x0: f32, y0: f32, (w, h): (usize, usize), material: Material) -> (Vec<f32>, Vec<u8>) {
        let mut f = Vec::new();
        for i in 0..w {
            for j in 0..h {
                f.extend([x0 + i as f32 / 128.0, y0 + j as f32 / 128.0, 0.0, 0.0]);
            }
        }
        (f, vec![material.id(); w * h])
    }

    #[test]
    fn a_liquid_scene_is_laid_out_and_a_rope_keeps_its_call_on_the_host() {
        // The default parts but momentum and rebound (which the device does not project).
        let mut c = Constraints::defaults();
        (c.momentum, c.rebound) = (None, None);
        let (rest, ids) = block(0.3, 0.1, (20, 10), Material::Liquid);
        let shape = SceneShape::on_grid(&rest, 4, &ids, &c, Some(64));
        let material = [ids.clone(), ids.clone()].concat();
        let plan = liquid_plan(&c, &[&shape, &shape], &material, &[0.01, 0.02], 1).unwrap();
        assert_eq!((plan.b, plan.n, plan.k), (2, 200, 1));
        assert!(plan.volume.iter().all(|&v| v > 0.0 && v.is_finite()));
        assert_eq!(plan.counts[usize::from(Material::Liquid.id())], 400);
        let row = &plan.scenes[SCENE_VALUES..];
        let side = row[1] as usize;
        assert!(
            side > 2 && plan.nodes == side * side,
            "{side} {}",
            plan.nodes
        );
        let (lo, hi) = c.walls.unwrap().bounds(Some(64));
        assert_eq!(&row[5..8], &[lo, hi, 0.02]);
        assert!((plan.iterations, plan.walls) == (40, true));
        // Half the block a rope: the call keeps its host projection.
        let (mut rest2, mut ids2) = (rest.clone(), ids.clone());
        let (rope, rope_ids) = block(0.6, 0.5, (20, 1), Material::Rope);
        rest2[..80].copy_from_slice(&rope);
        ids2[..20].copy_from_slice(&rope_ids);
        let roped = SceneShape::on_grid(&rest2, 4, &ids2, &c, Some(64));
        let material = [ids.clone(), ids2].concat();
        assert!(liquid_plan(&c, &[&shape, &roped], &material, &[0.01, 0.01], 1).is_none());
        // The momentum part (not on the device) keeps every call on the host.
        let mut with_momentum = c.clone();
        with_momentum.momentum = Some(crate::model::constraints::MomentumParams::DEFAULT);
        let material = [ids.clone(), ids].concat();
        let plan = liquid_plan(&with_momentum, &[&shape, &shape], &material, &[0.01; 2], 1);
        assert!(plan.is_none());
    }
}
