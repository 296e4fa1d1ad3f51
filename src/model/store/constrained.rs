//! A state's constraint data ([`ConstraintState`]): per trajectory its [`SceneShape`],
//! built from its rest frame on the first projected step, and the projection of predicted
//! frames onto the model's [`Constraints`] with it. Part of every [`super::State`], of
//! either architecture; it stacks and splits per trajectory like the network's state.
//!
//! A trajectory's data sits in a [`Slot`] that the states carrying it share: the surrogate
//! node projects a call's predictions only after it has recorded the next call
//! (`Surrogate::submit_scenes`), whose states were split off before that projection, so the
//! projection must reach the states that moved on (the first projection builds the data
//! into the slot they share, and the next call's projection finds it there).

use std::sync::{Arc, Mutex};

use crate::model::constraints::{projection_plan, Constraints, Correction, SceneShape};
use crate::ops::{ProjectionPlan, MATERIALS};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

pub(super) use super::events::Slot;

/// The last device plan a surrogate laid out, with what it was laid out for: the scenes'
/// slots (by address), their time steps, materials and solver grids. A node's calls serve the
/// same streams call after call, so the same plan, and its copy on the device, serves them
/// (`ConstraintState::device_plan`).
#[derive(Default)]
pub(super) struct PlanCache {
    key: Option<PlanKey>,
    plan: Option<ProjectionPlan>,
}

/// What a cached plan was laid out for (the slots held, so no other can take their
/// address).
struct PlanKey {
    slots: Vec<Slot>,
    dt: Vec<u32>,
    material: Vec<u8>,
    grids: Vec<Option<u32>>,
}

impl PlanKey {
    /// Whether this is the key of a call of `slots` with time steps `dt`, materials
    /// `material` and solver grids `grids` (compared in place: a node's every call checks it).
    fn fits(&self, slots: &[Slot], dt: &[f32], material: &[u8], grids: &[Option<u32>]) -> bool {
        self.slots.len() == slots.len()
            && (self.slots.iter().zip(slots)).all(|(a, b)| Arc::ptr_eq(a, b))
            && (self.dt.iter().copied()).eq(dt.iter().map(|t| t.to_bits()))
            && self.grids == grids
            && self.material == material
    }
}

/// How far the calls projected on the device moved each material: the sums on the device
/// (`[MATERIALS]`, particle spacings), added there call after call and read back only when
/// taken, and the particle-frames counted on the host.
pub(super) struct DeviceMoves<B: Backend> {
    sums: Option<Tensor<B, 1>>,
    count: [u64; MATERIALS],
}

impl<B: Backend> Default for DeviceMoves<B> {
    fn default() -> Self {
        Self {
            sums: None,
            count: [0; MATERIALS],
        }
    }
}

impl<B: Backend> DeviceMoves<B> {
    /// Adds one call's sums (`[MATERIALS]`) of the plan's K frames.
    pub(super) fn add(&mut self, sums: Tensor<B, 1>, plan: &ProjectionPlan) {
        self.sums = Some(match self.sums.take() {
            Some(held) => held + sums,
            None => sums,
        });
        for (c, &n) in self.count.iter_mut().zip(&plan.counts) {
            *c += n * plan.k as u64;
        }
    }

    /// The sums read back as a [`Correction`] (zero where nothing was projected; a failed
    /// read counts nothing).
    pub(super) fn read(self) -> Correction {
        let mut out = Correction::default();
        let Some(sums) = self.sums else {
            return out;
        };
        if let Ok(values) = sums.into_data().to_vec::<f32>() {
            for (m, v) in values.into_iter().enumerate().take(MATERIALS) {
                out.sum[m] = f64::from(v);
                out.count[m] = self.count[m];
            }
        }
        out
    }
}

/// Per trajectory (batch row): its constraint data, and the rest frames it is built from.
#[derive(Clone, Default)]
pub(super) struct ConstraintState {
    /// Per trajectory: its constraint data's slot, filled from its rest frame on the first
    /// projected step (no slots before the state's first stack or projection; see
    /// `Surrogate::with_constraints`).
    pub(super) shapes: Vec<Slot>,
    /// The rest frames (`[B, N, 4]`) set by `Surrogate::init_state_at` that the first
    /// projected step builds `shapes` from; without them it takes its input frame.
    pub(super) rest_frames: Option<Vec<f32>>,
    /// The solver grid of each trajectory, when known (`Surrogate::with_solver_grid`,
    /// `Surrogate::rollout_on`, `Surrogate::init_state_for`): the liquid's pressure part picks
    /// its threshold by it. One entry per trajectory once stacked; a state that was never
    /// stacked may hold one entry for all its rows.
    pub(super) solver_grids: Vec<Option<u32>>,
    /// Whether the call that left this state projected its predictions on the device
    /// ([`ConstraintState::device_plan`]), so the host has nothing left to project.
    pub(super) on_device: bool,
}

impl ConstraintState {
    /// Several states' constraint data as one, per trajectory in order: a state that has
    /// none yet counts as one trajectory (a node's scene), given an empty slot of its own.
    /// The stacked data keeps no rest frames (a node's states have none).
    pub(super) fn stack(parts: Vec<ConstraintState>) -> ConstraintState {
        let mut shapes = Vec::new();
        let mut solver_grids = Vec::new();
        for part in parts {
            let rows = part.shapes.len().max(1);
            solver_grids.extend((0..rows).map(|i| part.grid_of(i)));
            match part.shapes.is_empty() {
                true => shapes.push(Slot::default()),
                false => shapes.extend(part.shapes),
            }
        }
        ConstraintState {
            shapes,
            rest_frames: None,
            solver_grids,
            on_device: false,
        }
    }

    /// The solver grid of trajectory `i` (the one entry of a state never stacked).
    fn grid_of(&self, i: usize) -> Option<u32> {
        match self.solver_grids.len() {
            1 => self.solver_grids[0],
            _ => self.solver_grids.get(i).copied().flatten(),
        }
    }

    /// A copy whose trajectories' data is its own (each slot's content copied), so that
    /// projecting the copy leaves this state's data as it was: a padded call's copies of its
    /// last scene (a projection keeps state between steps: snow's yield, contacts under way).
    pub(super) fn detached(&self) -> ConstraintState {
        let copy = |slot: &Slot| {
            let shape = slot.lock().unwrap_or_else(|e| e.into_inner()).clone();
            Arc::new(Mutex::new(shape))
        };
        ConstraintState {
            shapes: self.shapes.iter().map(copy).collect(),
            rest_frames: self.rest_frames.clone(),
            solver_grids: self.solver_grids.clone(),
            on_device: false,
        }
    }

    /// Stacked data back per scene, scene i of `sizes[i]` trajectories: the inverse of
    /// [`ConstraintState::stack`] (every scene empty when the data is not one per
    /// trajectory).
    pub(super) fn split(self, sizes: &[usize]) -> Vec<ConstraintState> {
        let total: usize = sizes.iter().sum();
        let has_shapes = self.shapes.len() == total;
        let mut grids = (0..total)
            .map(|i| self.grid_of(i))
            .collect::<Vec<_>>()
            .into_iter();
        let mut shapes = self.shapes.into_iter();
        sizes
            .iter()
            .map(|&size| ConstraintState {
                shapes: match has_shapes {
                    true => shapes.by_ref().take(size).collect(),
                    false => Vec::new(),
                },
                rest_frames: None,
                solver_grids: grids.by_ref().take(size).collect(),
                on_device: false,
            })
            .collect()
    }

    /// The device's plan for projecting this call's predictions onto `c` (the call's input
    /// `frames` `[B, N, 4]`, materials `[B N]`, time steps `[B]`; its K set by the caller),
    /// where every scene's parts are ones the device projects
    /// ([`crate::model::constraints::projection_plan`]); each scene's constraint data is built
    /// first where it has none, as [`ConstraintState::project`] builds it. Its wall time
    /// counts as projection time (`stages::take_projection`).
    pub(super) fn device_plan(
        &mut self,
        c: &Constraints,
        (frames, material, dt): (&[f32], &[u8], &[f32]),
        cache: &Mutex<PlanCache>,
    ) -> Option<ProjectionPlan> {
        use rayon::prelude::*;
        let started = std::time::Instant::now();
        let b = dt.len();
        let n = material.len() / b.max(1);
        if self.shapes.len() != b {
            self.shapes = (0..b).map(|_| Slot::default()).collect();
        }
        let rest = self.rest_frames.as_deref();
        let rest = rest.filter(|r| r.len() == b * n * 4).unwrap_or(frames);
        let grids: Vec<Option<u32>> = (0..b).map(|i| self.grid_of(i)).collect();
        let mut cache = cache.lock().unwrap_or_else(|e| e.into_inner());
        let hit = (cache.key.as_ref()).is_some_and(|k| k.fits(&self.shapes, dt, material, &grids));
        let plan = match hit {
            // The cached plan's scenes are built already.
            true => cache.plan.clone(),
            false => {
                // In parallel, as the host's projection builds them: 2-3 ms a scene of 2,500.
                self.shapes.par_iter().enumerate().for_each(|(i, slot)| {
                    let mut shape = slot.lock().unwrap_or_else(|e| e.into_inner());
                    let rows = &rest[i * n * 4..(i + 1) * n * 4];
                    let ids = &material[i * n..(i + 1) * n];
                    built(&mut shape, (rows, ids), c, grids[i]);
                });
                let guards: Vec<_> = (self.shapes.iter())
                    .map(|slot| slot.lock().unwrap_or_else(|e| e.into_inner()))
                    .collect();
                let shapes: Vec<&SceneShape> = guards.iter().filter_map(|g| g.as_ref()).collect();
                let mut plan = projection_plan(c, &shapes, material, dt, 1);
                if let Some(plan) = plan.as_mut() {
                    plan.events = super::events::SlotEvents::events(&self.shapes, plan.rebound);
                }
                let key = PlanKey {
                    slots: self.shapes.clone(),
                    dt: dt.iter().map(|t| t.to_bits()).collect(),
                    material: material.to_vec(),
                    grids,
                };
                (cache.key, cache.plan) = (Some(key), plan.clone());
                plan
            }
        };
        // The host's share of a device projection (its kernel runs in the call).
        if plan.is_some() {
            super::stages::count_projection(started.elapsed());
        }
        plan
    }

    /// Projects the predicted frames `out` (K frames of `[B, N, 4]`) of the input `frames`
    /// (`[B, N, 4]`, materials `[B N]`, time steps `[B]`) onto `c`, scene by scene in
    /// parallel; each scene's constraint data is built on its first projection from its
    /// row of the rest frames (`[B, N, 4]`) or else of `frames`. Within a bundle, frame
    /// k + 1 is first moved by frame k's correction (the network integrated it from its own
    /// frame k), then projected. Returns how far each scene moved.
    pub(super) fn project(
        &mut self,
        c: &Constraints,
        (frames, material, dt): (&[f32], &[u8], &[f32]),
        out: &mut [Vec<f32>],
    ) -> Vec<Correction> {
        use rayon::prelude::*;
        let started = std::time::Instant::now();
        let b = dt.len();
        let n = material.len() / b;
        let per = n * 4;
        if self.shapes.len() != b {
            self.shapes = (0..b).map(|_| Slot::default()).collect();
        }
        let rest = self.rest_frames.as_deref();
        let rest = rest.filter(|r| r.len() == b * per).unwrap_or(frames);
        let grids: Vec<Option<u32>> = (0..b).map(|i| self.grid_of(i)).collect();
        let mut rows: Vec<Vec<&mut [f32]>> =
            (0..b).map(|_| Vec::with_capacity(out.len())).collect();
        for frame in out.iter_mut() {
            for (row, chunk) in rows.iter_mut().zip(frame.chunks_exact_mut(per)) {
                row.push(chunk);
            }
        }
        let moved = self
            .shapes
            .par_iter()
            .zip(rows.par_iter_mut())
            .enumerate()
            .map(|(i, (slot, row))| {
                let ids = &material[i * n..(i + 1) * n];
                // Each row its own slot (a padded call's copies are detached).
                let mut shape = slot.lock().unwrap_or_else(|e| e.into_inner());
                let shape = built(
                    &mut shape,
                    (&rest[i * per..(i + 1) * per], ids),
                    c,
                    grids[i],
                );
                project_row(c, shape, (&frames[i * per..(i + 1) * per], row), ids, dt[i])
            })
            .collect();
        super::stages::count_projection(started.elapsed());
        moved
    }
}

/// A scene's constraint data `shape`, built from its rest frame `rest` (`[N, 4]`, materials
/// `ids`) on the solver grid `grid` where it has none yet (the setup's thread time counted,
/// `stages::count_setup`).
fn built<'a>(
    shape: &'a mut Option<SceneShape>,
    (rest, ids): (&[f32], &[u8]),
    c: &Constraints,
    grid: Option<u32>,
) -> &'a mut SceneShape {
    shape.get_or_insert_with(|| {
        let started = std::time::Instant::now();
        let made = SceneShape::on_grid(rest, 4, ids, c, grid);
        super::stages::count_setup(started.elapsed());
        made
    })
}

/// One scene's frames of a bundle (`row`, oldest first) projected onto `c` with its data
/// `shape`: frame k + 1 first moved by frame k's position correction. Frame 0 was predicted
/// from `input` (`[N, 4]`), frame k + 1 from frame k as projected. Returns the moves.
fn project_row(
    c: &Constraints,
    shape: &mut SceneShape,
    (input, row): (&[f32], &mut [&mut [f32]]),
    ids: &[u8],
    dt: f32,
) -> Correction {
    let mut total = Correction::default();
    let mut carried: Option<Vec<f32>> = None;
    let last = row.len().saturating_sub(1);
    for k in 0..row.len() {
        let (done, rest) = row.split_at_mut(k);
        let frame = &mut *rest[0];
        let prev: &[f32] = done.last().map_or(input, |f| &**f);
        // The network's own frame, kept where its correction carries into the
        // next frame (not after the bundle's last).
        let own = (k < last).then(|| frame.to_vec());
        if let Some(offset) = &carried {
            for (v, o) in frame.iter_mut().zip(offset) {
                *v += o;
            }
        }
        total.add(&shape.project(c, (Some(prev), frame), ids, dt));
        // The position correction relative to the network's own frame.
        carried = own.map(|own| {
            let mut offset: Vec<f32> = frame.iter().zip(&own).map(|(a, b)| a - b).collect();
            for o in offset.chunks_exact_mut(4) {
                (o[2], o[3]) = (0.0, 0.0);
            }
            offset
        });
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The states split from a stack share its slots (a projection landing after the split
    /// reaches them); a detached copy (a padded call's copy of a scene) shares none, so its
    /// projection leaves the scene's data alone.
    #[test]
    fn split_states_share_slots_and_detached_copies_do_not() {
        let stacked = ConstraintState::stack(vec![ConstraintState::default(); 2]);
        assert_eq!(stacked.shapes.len(), 2);
        let parts = stacked.clone().split(&[1, 1]);
        for (part, slot) in parts.iter().zip(&stacked.shapes) {
            assert!(Arc::ptr_eq(&part.shapes[0], slot));
        }
        let copy = parts[1].detached();
        assert_eq!(copy.shapes.len(), 1);
        assert!(!Arc::ptr_eq(&copy.shapes[0], &parts[1].shapes[0]));
        // Stacking the scene beside its copy keeps them apart.
        let padded = ConstraintState::stack(vec![parts[1].clone(), copy]);
        assert!(!Arc::ptr_eq(&padded.shapes[0], &padded.shapes[1]));
    }

    /// Each scene keeps its own solver grid through a stack and a split: a node's batch mixes
    /// scenes of the 64 x 64 and the 128 x 128 grids, and each must project with its own
    /// threshold (a stack that took one grid for all its rows made the node's results
    /// depend on which scenes shared a call).
    #[test]
    fn each_scene_keeps_its_solver_grid_through_stack_and_split() {
        let scene = |grid| ConstraintState {
            solver_grids: vec![grid],
            ..ConstraintState::default()
        };
        let stacked = ConstraintState::stack(vec![scene(Some(128)), scene(Some(64)), scene(None)]);
        assert_eq!(stacked.solver_grids, vec![Some(128), Some(64), None]);
        let again = ConstraintState::stack(vec![stacked.clone(), scene(Some(64))]);
        assert_eq!(
            again.solver_grids,
            vec![Some(128), Some(64), None, Some(64)]
        );
        let parts = stacked.split(&[2, 1]);
        assert_eq!(parts[0].solver_grids, vec![Some(128), Some(64)]);
        assert_eq!(parts[1].solver_grids, vec![None]);
    }

    /// A node's next call of the same scenes gets the same plan (its arrays, and so its copy
    /// on the device, shared); another time step, or a scene that left, lays out a new one.
    #[test]
    fn the_same_scenes_reuse_their_device_plan() {
        let mut c = Constraints::defaults();
        (c.momentum, c.rebound) = (None, None);
        let (n, b) = (64usize, 2usize);
        let frames: Vec<f32> = (0..b * n)
            .flat_map(|i| {
                [
                    0.3 + 0.01 * (i % 8) as f32,
                    0.1 + 0.01 * (i / 8 % 8) as f32,
                    0.0,
                    0.0,
                ]
            })
            .collect();
        let material = vec![crate::material::Material::Liquid.id(); b * n];
        let cache = Mutex::new(PlanCache::default());
        let mut state = ConstraintState::stack(vec![ConstraintState::default(); b]);
        let first = state.device_plan(&c, (&frames, &material, &[0.01; 2]), &cache);
        let first = first.expect("liquid scenes have a plan");
        // The next call's state: split and stacked again, sharing the slots.
        let mut next = ConstraintState::stack(state.clone().split(&[1, 1]));
        let again = next.device_plan(&c, (&frames, &material, &[0.01; 2]), &cache);
        assert!(Arc::ptr_eq(&first.volume, &again.unwrap().volume));
        let slower = next.device_plan(&c, (&frames, &material, &[0.02; 2]), &cache);
        assert!(!Arc::ptr_eq(&first.volume, &slower.unwrap().volume));
        let mut one = ConstraintState::stack(state.split(&[1, 1]).into_iter().take(1).collect());
        let alone = one.device_plan(&c, (&frames[..n * 4], &material[..n], &[0.02]), &cache);
        assert_eq!(alone.expect("one scene's plan").b, 1);
    }
}
