//! The projection's data laid out for a device: [`projection_plan`], the ropes, the bodies' shape
//! matching and contact, the liquid's pressure part, the walls, the velocity update and the
//! energy given back for every scene of a call, as flat arrays a GPU's kernels read
//! (`crate::ops::ProjectionPlan`). The kernels there are the device form of
//! [`SceneShape::project`] for scenes whose only parts are those (every scene under the
//! shipped models but the `-mixed` ones): the same steps in the same order, the same
//! arithmetic per node and particle, with the grid's sums in fixed point (the order the
//! atomics land in changes no bit) where the host sums in particle order, and the bodies'
//! sums in f64 over the cube's threads.
//!
//! The momentum and rebound parts are laid out too (their values in the head of
//! `solids`, a scene's rebound bodies in its row; the contacts in progress cross per call,
//! `ProjectionPlan::events`, set by the caller). A scene with the density part, a plastic
//! body, more than [`MAX_BODIES`] bodies, rebound bodies that are not its first shape-matched
//! ones, or a momentum reach below [`MIN_REACH`] has no plan: its call projects on the host
//! (`model::store`'s `finish_here`).

use std::sync::Arc;

use super::{Constraints, SceneShape};
use crate::material::Material;
use crate::ops::{
    ProjectionPlan, BODY_VALUES, MATERIALS, MAX_BODIES, MOMENTUM_AT, REBOUND_AT, SCENE_SOLIDS,
    SCENE_VALUES, SOLIDS_HEAD,
};

const _: () = assert!(MATERIALS == crate::material::COUNT);

/// The smallest momentum reach the device takes (domain units): its cells of side
/// `reach / sqrt(2)` over 1.5 domain widths fit the kernel's 48 x 48 (`cuda/projection/momentum.rs`).
pub const MIN_REACH: f32 = 0.045;

/// The plan for a call of the scenes `shapes` (each `[N]` particles with materials
/// `material[s N..(s + 1) N]` and time step `dt[s]`) and K frames a scene, or None when
/// `c` has a part the device does not project (the density part, a plastic body, more than
/// [`MAX_BODIES`] bodies, the module doc's rebound and momentum limits) that acts on one of
/// the scenes. With the rebound part, the caller sets the plan's `events` before a call.
pub fn projection_plan(
    c: &Constraints,
    shapes: &[&SceneShape],
    material: &[u8],
    dt: &[f32],
    k: usize,
) -> Option<ProjectionPlan> {
    let known = material.iter().all(|&m| usize::from(m) < MATERIALS);
    let reach_ok = c.momentum.is_none_or(|p| p.reach >= MIN_REACH);
    if !reach_ok || shapes.is_empty() || shapes.len() != dt.len() || !known {
        return None;
    }
    let b = shapes.len();
    let n = material.len() / b;
    let solids = solids(c, shapes)?;
    let liquid = Material::Liquid.id();
    let mut plan = ProjectionPlan {
        b,
        n,
        k,
        volume: Arc::from([]),
        liquid,
        counts: [0; MATERIALS],
        scenes: Arc::from([]),
        nodes: 1,
        stiffness: 0.0,
        full: 0.0,
        omega: 1.0,
        iterations: 0,
        velocity: false,
        restore: 0.0,
        walls: c.walls.is_some(),
        solids: solids.into(),
        events: Default::default(),
        rebound: shapes.iter().map(|s| s.rebound_bodies()).max().unwrap_or(0),
        device: Default::default(),
    };
    let mut volume: Vec<f32> = material.iter().map(|&m| -(1.0 + f32::from(m))).collect();
    let mut scenes = vec![0.0f32; b * SCENE_VALUES];
    if let Some(p) = &c.pressure {
        (plan.stiffness, plan.full, plan.omega) = (p.stiffness, p.full, p.omega);
        (plan.iterations, plan.velocity) = (p.iterations, p.velocity);
        plan.restore = p.restore.min(1.0);
    }
    for (s, shape) in shapes.iter().enumerate() {
        let on_host_only = shape.liquid.is_some() || shape.n != n;
        if on_host_only {
            return None;
        }
        let (lo, hi) = c.walls.map_or((0.0, 1.0), |w| w.bounds(shape.grid));
        let row = &mut scenes[s * SCENE_VALUES..(s + 1) * SCENE_VALUES];
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
        let own = &mut volume[s * n..(s + 1) * n];
        for (&i, &v) in d.ids.iter().zip(&d.volume) {
            own[i as usize] = v;
        }
        debug_assert!(d
            .ids
            .iter()
            .all(|&i| material[s * n + i as usize] == liquid));
    }
    for &m in material {
        plan.counts[usize::from(m)] += 1;
    }
    (plan.volume, plan.scenes) = (volume.into(), scenes.into());
    Some(plan)
}

/// The `solids` array of a call of `shapes` (`ProjectionPlan::solids`' layout), or None where a
/// scene has a body the device does not project (plastic, or more than [`MAX_BODIES`]).
fn solids(c: &Constraints, shapes: &[&SceneShape]) -> Option<Vec<f32>> {
    let mut chains: Vec<&super::rope::Chain> = Vec::new();
    let mut bodies: Vec<&super::shape::Body> = Vec::new();
    let mut out = vec![0.0f32; SOLIDS_HEAD + SCENE_SOLIDS * shapes.len()];
    for (s, shape) in shapes.iter().enumerate() {
        let plastic = shape
            .bodies
            .iter()
            .any(|body| c.shape_of(body.material).is_none_or(|p| p.plastic > 0.0));
        if plastic || shape.bodies.len() > MAX_BODIES || !rebound_leads(shape) {
            return None;
        }
        let reach = match (&c.contact, &shape.contact) {
            (Some(p), Some(contact)) => contact.reach(p),
            _ => 0.0,
        };
        let row = &mut out[SOLIDS_HEAD + SCENE_SOLIDS * s..][..SCENE_SOLIDS];
        let (c0, b0) = (chains.len(), bodies.len());
        if c.rope.is_some() {
            chains.extend(&shape.chains);
        }
        bodies.extend(&shape.bodies);
        let index = |v: usize| v as f32;
        row.copy_from_slice(&[
            index(c0),
            index(chains.len()),
            index(b0),
            index(bodies.len()),
            reach,
            index(shape.rebound_bodies()),
        ]);
    }
    let chains_at = out.len();
    let bodies_at = chains_at + 2 * chains.len();
    let mut elements = bodies_at + BODY_VALUES * bodies.len();
    out.resize(elements, 0.0);
    for (i, chain) in chains.iter().enumerate() {
        let (ids, along) = chain.parts();
        out[chains_at + 2 * i..][..2].copy_from_slice(&[elements as f32, ids.len() as f32]);
        out.extend(ids.iter().zip(along).flat_map(|(&id, &a)| [id as f32, a]));
        elements = out.len();
    }
    for (i, body) in bodies.iter().enumerate() {
        let p = c.shape_of(body.material)?;
        let (rest, aqq) = body.rest_shape();
        let row = &mut out[bodies_at + BODY_VALUES * i..][..BODY_VALUES];
        row[..4].copy_from_slice(&[elements as f32, rest.len() as f32, p.stiffness, p.linear]);
        row[4..].copy_from_slice(&aqq);
        let ids = body.ids();
        out.extend(
            ids.iter()
                .zip(rest)
                .flat_map(|(&id, q)| [id as f32, q[0], q[1]]),
        );
        elements = out.len();
    }
    out[..SOLIDS_HEAD].copy_from_slice(&head(c, chains_at, bodies_at));
    // Indices are held as f32: exact below 2^24.
    (out.len() < 1 << 24).then_some(out)
}

/// The head of `solids` ([`SOLIDS_HEAD`] values, `ProjectionPlan::solids`' layout) for the
/// parts of `c`, the chain table at `chains_at` and the body table at `bodies_at`.
fn head(c: &Constraints, chains_at: usize, bodies_at: usize) -> [f32; SOLIDS_HEAD] {
    let mut out = [0.0f32; SOLIDS_HEAD];
    let (stretch, sweeps, long) = c
        .rope
        .map_or((0.0, 0, false), |p| (p.stretch, p.iterations, p.long_range));
    let (iterations, restitution) = c
        .contact
        .map_or((0, 0.0), |p| (p.iterations, p.restitution));
    out[..MOMENTUM_AT].copy_from_slice(&[
        chains_at as f32,
        bodies_at as f32,
        stretch,
        sweeps as f32,
        f32::from(u8::from(long)),
        iterations as f32,
        restitution,
        super::contact::RESTING,
    ]);
    if let Some(p) = &c.momentum {
        let lag = 0.5 * (1.0 + 1.0 / p.substeps.max(1) as f32);
        let [gx, gy] = p.gravity;
        out[MOMENTUM_AT..REBOUND_AT].copy_from_slice(&[p.reach, p.clearance, lag, gx, gy]);
    }
    if let Some(p) = &c.rebound {
        let [gx, gy] = p.gravity;
        let values = [
            p.restitution,
            p.reach,
            p.clearance,
            p.release,
            p.resting,
            gx,
            gy,
        ];
        out[REBOUND_AT..SOLIDS_HEAD].copy_from_slice(&values);
    }
    out
}

/// Whether `shape`'s rebound bodies (if any) are its first shape-matched bodies, in order:
/// the device reads their particles from the body table.
fn rebound_leads(shape: &SceneShape) -> bool {
    let Some(rebound) = &shape.rebound else {
        return true;
    };
    let r = rebound.body_count();
    r <= shape.bodies.len()
        && (0..r).all(|b| {
            shape.bodies[b].material == crate::material::Material::Jelly.id()
                && shape.bodies[b].ids() == rebound.body(b)
        })
}

#[cfg(test)]
mod tests {
    use super::super::{MomentumParams, ShapeParams};
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
    fn a_call_is_laid_out_with_its_ropes_and_a_plastic_body_keeps_it_on_the_host() {
        // The default parts but momentum and rebound (which the device does not project).
        let mut c = Constraints::defaults();
        (c.momentum, c.rebound) = (None, None);
        let (rest, ids) = block(0.3, 0.1, (20, 10), Material::Liquid);
        let shape = SceneShape::on_grid(&rest, 4, &ids, &c, Some(64));
        let material = [ids.clone(), ids.clone()].concat();
        let plan = projection_plan(&c, &[&shape, &shape], &material, &[0.01, 0.02], 1).unwrap();
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
        // Half the block a rope: its chain is laid out after the head and the scenes' rows.
        let (mut rest2, mut ids2) = (rest.clone(), ids.clone());
        let (rope, rope_ids) = block(0.6, 0.5, (20, 1), Material::Rope);
        rest2[..80].copy_from_slice(&rope);
        ids2[..20].copy_from_slice(&rope_ids);
        let roped = SceneShape::on_grid(&rest2, 4, &ids2, &c, Some(64));
        let material = [ids.clone(), ids2.clone()].concat();
        let plan = projection_plan(&c, &[&shape, &roped], &material, &[0.01, 0.01], 1).unwrap();
        let head = SOLIDS_HEAD + 2 * SCENE_SOLIDS;
        assert_eq!(plan.solids[0], head as f32);
        let row = &plan.solids[SOLIDS_HEAD + SCENE_SOLIDS..][..SCENE_SOLIDS];
        assert_eq!(
            row,
            &[0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
            "scene 1 holds chain 0"
        );
        let chain = &plan.solids[head..head + 2];
        assert_eq!(chain, &[(head + 2) as f32, 20.0]);
        let along = plan.solids[head + 2 + 2 * 19 + 1];
        assert!((along - 19.0 / 128.0).abs() < 1e-6, "{along}");
        // A plastic body keeps its call on the host.
        let mut plastic = c.clone();
        plastic.jelly = plastic.jelly.map(|p| ShapeParams { plastic: 0.1, ..p });
        let (jelly, jelly_ids) = block(0.2, 0.6, (6, 6), Material::Jelly);
        let (mut rest3, mut ids3) = (rest.clone(), ids.clone());
        rest3[..144].copy_from_slice(&jelly);
        ids3[..36].copy_from_slice(&jelly_ids);
        let body = SceneShape::on_grid(&rest3, 4, &ids3, &plastic, Some(64));
        let material = [ids.clone(), ids3].concat();
        assert!(projection_plan(&plastic, &[&shape, &body], &material, &[0.01; 2], 1).is_none());
        // The momentum part's values in the head; a reach below the cells' keeps the call
        // on the host.
        let mut with_momentum = c.clone();
        let p = crate::model::constraints::MomentumParams::DEFAULT;
        with_momentum.momentum = Some(p);
        let material = [ids.clone(), ids].concat();
        let plan = projection_plan(&with_momentum, &[&shape, &shape], &material, &[0.01; 2], 1);
        let head = &plan.unwrap().solids[MOMENTUM_AT..REBOUND_AT];
        let lag = 0.5 * (1.0 + 1.0 / p.substeps as f32);
        assert_eq!(head[..3], [p.reach, p.clearance, lag]);
        with_momentum.momentum = Some(MomentumParams { reach: 0.03, ..p });
        let plan = projection_plan(&with_momentum, &[&shape, &shape], &material, &[0.01; 2], 1);
        assert!(plan.is_none());
    }

    #[test]
    fn rebound_bodies_are_the_first_bodies_and_their_count_is_laid_out() {
        let c = Constraints::defaults();
        assert!(c.rebound.is_some() && c.jelly.is_some());
        // Two jelly blocks apart and a liquid pool.
        let (mut rest, mut ids) = block(0.3, 0.1, (20, 10), Material::Liquid);
        for x0 in [0.2, 0.6] {
            let (jelly, jelly_ids) = block(x0, 0.6, (6, 6), Material::Jelly);
            rest.extend(jelly);
            ids.extend(jelly_ids);
        }
        let shape = SceneShape::on_grid(&rest, 4, &ids, &c, Some(64));
        assert_eq!(shape.rebound_bodies(), 2);
        let plan = projection_plan(&c, &[&shape], &ids, &[0.01], 1).unwrap();
        assert_eq!(plan.rebound, 2);
        assert_eq!(plan.solids[SOLIDS_HEAD + 5], 2.0);
        let p = c.rebound.unwrap();
        assert_eq!(
            plan.solids[REBOUND_AT..REBOUND_AT + 2],
            [p.restitution, p.reach]
        );
    }
}
