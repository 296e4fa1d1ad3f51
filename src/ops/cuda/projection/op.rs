//! [`NetOps::project_constraints`](crate::ops::NetOps::project_constraints) on burn's CUDA
//! backend (feature `cuda`): the projection of a call's predictions recorded as one custom
//! operation of burn's fusion layer (how one joins the fusion stream: see `cublas.rs`),
//! right behind the network's call, so the frames are projected before they are read back
//! and no host pass sits between the call and the next. One kernel projects every frame of
//! the call (`cuda/projection/call.rs`), behind a copy of the frames and the zeroing of the
//! sums, and before the moves are turned out of fixed point.

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::{FloatTensor, FloatTensorOps};
use burn::tensor::{Tensor, TensorData, TensorMetadata};
use burn_cubecl::cubecl;
use burn_cubecl::tensor::CubeTensor;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::prelude::*;
use cubecl::server::Handle;

use super::buffers::BuffersLaunch;
use super::call::call_kernel;
use super::liquid::{copy_kernel, zero_kernel};
use super::liquid_solve::{moves_kernel, THREADS};
use super::momentum_sums::SUMS;
use crate::ops::cuda::net::conv::{contiguous, elementwise, Cuda, Inner, Runtime};
use std::sync::{Arc, Mutex, OnceLock};

use crate::ops::{
    event_table_len, ProjectionPlan, TablesLater, MATERIALS, MOMENTUM_AT, SCENE_VALUES,
};

/// The largest factor the energy step scales a frame's velocities by (`energy::MAX_SCALE`).
const MAX_SCALE: f32 = 2.0;

/// The recorded projection: inputs `[out, volume, scenes, solids, input, events]`, outputs
/// the projected frames, the moves (`[B, MATERIALS]`, particle spacings summed over the
/// call's frames) and the rebound part's contacts after the call (`events`' layout).
#[derive(Debug)]
struct ProjectionOp {
    desc: CustomOpIr,
    /// The plan (its arrays shared; on the device they are the inputs).
    s: ProjectionPlan,
    /// Whether the input frames came (the momentum and rebound parts act).
    laws: bool,
}

/// Scratch of one call: `[B nodes]` node slots of each array.
struct Scratch {
    before: Handle,
    acc: Handle,
    grid: Handle,
    kind: Handle,
    q: Handle,
    rhs: Handle,
    faces: Handle,
    moves: Handle,
    list: Handle,
    prev: Handle,
    parent: Handle,
    sorted: Handle,
    cellof: Handle,
    sums: Handle,
    free: Handle,
}

/// A launch argument over `len` elements of `h`.
fn arr(h: &Handle, len: usize) -> ArrayArg<CudaRuntime> {
    // SAFETY: every scratch handle is allocated with `len` elements of the kernel's type
    // (`ProjectionOp::execute`).
    unsafe { ArrayArg::from_raw_parts(h.clone(), len) }
}

/// `t`'s launch argument as a flat array.
fn flat(t: &CubeTensor<CudaRuntime>) -> ArrayArg<CudaRuntime> {
    t.clone().into_array_arg()
}

impl Operation<Runtime> for ProjectionOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let inputs = &self.desc.inputs;
        let out = contiguous(handles.get_float_tensor::<Inner>(&inputs[0]));
        let volume = contiguous(handles.get_float_tensor::<Inner>(&inputs[1]));
        let scenes = contiguous(handles.get_float_tensor::<Inner>(&inputs[2]));
        let solids = contiguous(handles.get_float_tensor::<Inner>(&inputs[3]));
        let input = contiguous(handles.get_float_tensor::<Inner>(&inputs[4]));
        let events_in = contiguous(handles.get_float_tensor::<Inner>(&inputs[5]));
        let client = out.client.clone();
        let s = &self.s;
        let (frames, events) = (copied(&out), copied(&events_in));
        let laws = self.law_scratch();
        let slots = s.b * s.nodes;
        let scratch = Scratch {
            before: client.empty(s.b * s.n * 16),
            acc: client.empty(slots * 6 * 8),
            grid: client.empty(slots * 5 * 4),
            kind: client.empty(slots * 4),
            q: client.empty(slots * 4),
            rhs: client.empty(slots * 4),
            faces: client.empty(slots * 2 * 4),
            moves: client.empty(s.b * MATERIALS * 8),
            list: client.empty(slots * 4),
            prev: client.empty(laws * 16),
            parent: client.empty(laws * 4),
            sorted: client.empty(laws * 4),
            cellof: client.empty(laws * 4),
            sums: client.empty(laws * SUMS * 8),
            free: client.empty(laws * 4),
        };
        let (count, dim) = elementwise(&client, slots * 6);
        zero_kernel::launch(&client, count, dim, arr(&scratch.acc, slots * 6));
        let words = s.b * MATERIALS;
        let (count, dim) = elementwise(&client, words);
        zero_kernel::launch(&client, count, dim, arr(&scratch.moves, words));
        let args = Args {
            client: &client,
            frames: &frames,
            net: &out,
            volume: &volume,
            scenes: &scenes,
            solids: &solids,
            input: &input,
            events: &events,
            scratch: &scratch,
        };
        self.run(&args);
        let moves = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            out.device.clone(),
            burn::tensor::Shape::new([s.b, MATERIALS]),
            out.dtype,
        );
        let (count, dim) = elementwise(&client, words);
        moves_kernel::launch(
            &client,
            count,
            dim,
            arr(&scratch.moves, words),
            flat(&moves),
        );
        handles.register_float_tensor::<Inner>(&self.desc.outputs[0].id, frames);
        handles.register_float_tensor::<Inner>(&self.desc.outputs[1].id, moves);
        handles.register_float_tensor::<Inner>(&self.desc.outputs[2].id, events);
    }
}

/// `tables` read back behind the work recorded so far, waited for on the first call of the
/// result (empty where the read failed).
fn read_later(tables: FloatTensor<Cuda>) -> TablesLater {
    let ahead = Mutex::new(Some(crate::ops::cuda::read::read_ahead(tables)));
    let landed = OnceLock::<Arc<[f32]>>::new();
    Arc::new(move || {
        let read = || {
            let ahead = ahead.lock().unwrap_or_else(|e| e.into_inner()).take();
            let values = ahead.map(|a| a.wait().unwrap_or_default());
            values.unwrap_or_default().into()
        };
        landed.get_or_init(read).clone()
    })
}

/// A copy of `t` on its device (the kernel writes the copy).
fn copied(t: &CubeTensor<CudaRuntime>) -> CubeTensor<CudaRuntime> {
    let client = t.client.clone();
    let copy = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
        client.clone(),
        t.device.clone(),
        t.meta.shape().clone(),
        t.dtype,
    );
    let (count, dim) = elementwise(&client, t.meta.shape().num_elements());
    copy_kernel::launch(&client, count, dim, flat(t), flat(&copy));
    copy
}

/// What every launch of a call reads.
struct Args<'a> {
    client: &'a ComputeClient<CudaRuntime>,
    frames: &'a CubeTensor<CudaRuntime>,
    net: &'a CubeTensor<CudaRuntime>,
    volume: &'a CubeTensor<CudaRuntime>,
    scenes: &'a CubeTensor<CudaRuntime>,
    solids: &'a CubeTensor<CudaRuntime>,
    input: &'a CubeTensor<CudaRuntime>,
    events: &'a CubeTensor<CudaRuntime>,
    scratch: &'a Scratch,
}

impl ProjectionOp {
    /// Elements of each momentum and rebound scratch array: a particle each where the parts
    /// act, else one.
    fn law_scratch(&self) -> usize {
        match self.laws {
            true => self.s.b * self.s.n,
            false => 1,
        }
    }

    /// The call's kernel: a cube a scene, every frame in order.
    fn run(&self, a: &Args<'_>) {
        let s = &self.s;
        let (client, sc) = (a.client, a.scratch);
        let (bn, slots) = (s.b * s.n, s.b * s.nodes);
        let laws = self.law_scratch();
        let buffers = BuffersLaunch::new(
            flat(a.frames),
            flat(a.net),
            arr(&sc.before, bn * 4),
            flat(a.volume),
            flat(a.scenes),
            arr(&sc.acc, slots * 6),
            arr(&sc.grid, slots * 5),
            arr(&sc.kind, slots),
            arr(&sc.q, slots),
            arr(&sc.rhs, slots),
            arr(&sc.faces, slots * 2),
            arr(&sc.moves, s.b * MATERIALS),
            arr(&sc.list, slots),
            flat(a.solids),
            flat(a.input),
            arr(&sc.prev, laws * 4),
            arr(&sc.parent, laws),
            arr(&sc.sorted, laws),
            arr(&sc.cellof, laws),
            arr(&sc.sums, laws * SUMS),
            arr(&sc.free, laws),
            flat(a.events),
        );
        let int = |v: usize| u32::try_from(v).expect("liquid projection: sizes fit u32");
        call_kernel::launch(
            client,
            CubeCount::Static(int(s.b), 1, 1),
            CubeDim::new_1d(THREADS),
            buffers,
            u32::from(self.laws),
            int(s.rebound),
            int(s.n),
            int(s.nodes),
            int(s.k),
            int(s.iterations),
            u32::from(s.walls) + 2 * u32::from(s.liquid),
            u32::from(s.velocity),
            s.full,
            s.stiffness,
            s.omega,
            s.restore,
            MAX_SCALE,
        );
    }
}

/// Records the projection of `out` (`[K B, N, 4]`), predicted from the call's `input` frames
/// (`[B, N, 4]`; without them the momentum and rebound parts are left out, as the host leaves
/// them), as `plan` lays it out; returns the projected frames (same shape) and how far each
/// scene's materials moved (`[B, MATERIALS]`, particle spacings summed over the call's
/// particles and frames). With the rebound part, the contacts in progress are taken from the
/// plan's store before the call and given back after it as a read queued behind the call
/// (waited for when a scene's contacts are next used).
///
/// # Panics
/// `out` does not hold `plan`'s K B N rows of 4, or the plan's arrays are not its sizes.
pub(crate) fn project(
    out: FloatTensor<Cuda>,
    input: Option<FloatTensor<Cuda>>,
    plan: &ProjectionPlan,
) -> (FloatTensor<Cuda>, FloatTensor<Cuda>) {
    let shape = out.shape();
    assert_eq!(
        shape.num_elements(),
        plan.k * plan.b * plan.n * 4,
        "liquid projection: frames {shape:?} are not [K B, N, 4] of the plan's sizes"
    );
    assert_eq!(
        plan.volume.len(),
        plan.b * plan.n,
        "liquid projection: volumes"
    );
    assert_eq!(
        plan.scenes.len(),
        plan.b * SCENE_VALUES,
        "liquid projection: scenes"
    );
    let device = Cuda::float_device(&out);
    let upload = |v: &[f32]| {
        Tensor::<Cuda, 1>::from_data(TensorData::new(v.to_vec(), [v.len()]), &device)
            .into_primitive()
            .tensor()
    };
    // Uploaded once a plan: a node's calls of the same scenes share one.
    let arrays = || [&plan.volume, &plan.scenes, &plan.solids].map(|a| upload(a));
    let [volume, scenes, solids] = match plan.device.get_or_init(arrays) {
        Some(copy) => copy,
        None => arrays(),
    };
    // The momentum and rebound parts act where the frames before came and one of them is on.
    let on = plan
        .solids
        .get(MOMENTUM_AT)
        .is_some_and(|&reach| reach > 0.0)
        || plan.rebound > 0;
    let laws = input.is_some() && on;
    if let Some(input) = &input {
        assert_eq!(
            input.shape().num_elements(),
            plan.b * plan.n * 4,
            "projection: input frames are not [B, N, 4] of the plan's sizes"
        );
    }
    let store = (plan.events.0.as_ref()).filter(|_| laws && plan.rebound > 0);
    // Without a store the contacts start afresh each call.
    let per = event_table_len(plan.rebound);
    let tables = match store {
        Some(store) => store.take(),
        None => vec![0.0; (plan.b * per).max(1)],
    };
    let events_in = upload(&tables);
    let input = input.unwrap_or_else(|| out.clone());
    let client = out.client.clone();
    let dtype = out.dtype();
    let projected = TensorIr::uninit(client.create_empty_handle(), shape, dtype);
    let shape = burn::tensor::Shape::new([plan.b, MATERIALS]);
    let moves = TensorIr::uninit(client.create_empty_handle(), shape, dtype);
    let shape = burn::tensor::Shape::new([tables.len()]);
    let events = TensorIr::uninit(client.create_empty_handle(), shape, dtype);
    let inputs = [out, volume, scenes, solids, input, events_in];
    let streams = OperationStreams::with_inputs(&inputs);
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new("minflow_projection", &irs, &[projected, moves, events]);
    let op = ProjectionOp {
        desc: desc.clone(),
        s: plan.clone(),
        laws,
    };
    let mut outs = client.register(streams, OperationIr::Custom(desc), op);
    let events = outs.pop().expect("three outputs");
    if let Some(store) = store {
        store.give_back(read_later(events));
    }
    let moves = outs.pop().expect("three outputs");
    (outs.pop().expect("three outputs"), moves)
}
