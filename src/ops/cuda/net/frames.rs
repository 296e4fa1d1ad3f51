//! A grid model's per-particle frames ([`crate::ops::ParticleFrames`]) on burn's CUDA backend
//! (feature `cuda`) as one cubecl kernel, recorded as a custom operation of burn's fusion
//! layer (how one joins the fusion stream: `cublas.rs`).
//!
//! Why: as tensor operations, each of a call's K frames is a stencil, a gather, the inputs'
//! concatenation, three dense layers with their SiLUs and the integration, each a pass over
//! all `B N` particles' rows through the GPU's memory: the roofline's largest network part,
//! 24 ms of a 90 ms call of the scale model at 256 scenes of 10,000 particles (docs/speed.md,
//! "Roofline by part"). Here one thread carries one particle through all K frames: its
//! velocity window, position and the head's activations stay in registers, the weights sit in
//! shared memory (every thread of a warp reads the same one), and only the latent
//! fields, the particle's own inputs and the K output frames cross the GPU's memory. The CPU's
//! counterpart is the host pass (`model::grid::host_pass`); training keeps the tensor form.
//! The kernel: `frames_kernels.rs`.

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{DType, Shape, TensorMetadata};
use burn_cubecl::cubecl;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::prelude::*;

use super::conv::{contiguous, Cuda, Inner, Runtime};
use super::frames_kernels::{frames_kernel, Widths, FRAMES_CUBE, SHARED_VALUES};
use crate::ops::{OpsError, ParticleFrames};

/// The recorded frames: inputs `[fields, memory?, vel, material, pos, dt, wa, ba, wb, bb,
/// wo, bo]`, output `[K B N, 4]`.
#[derive(Debug)]
struct FramesOp {
    desc: CustomOpIr,
    widths: Widths,
    sizes: [usize; 3],
    /// The velocity normalisation, the velocity change's scale and mean, per axis.
    scales: [[f32; 2]; 3],
    /// The integration's box `(lo, hi)`, domain units.
    bounds: (f32, f32),
}

impl Operation<Runtime> for FramesOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let mut t: Vec<_> = (self.desc.inputs.iter())
            .map(|ir| contiguous(handles.get_float_tensor::<Inner>(ir)))
            .collect();
        if self.widths.h == 0 {
            // No memory: any tensor stands in for it (its loop runs no iteration).
            t.insert(1, t[1].clone());
        }
        let [n, bundle, channels] = self.sizes;
        let [b, particles] = [t[4].meta.shape()[0], t[4].meta.shape()[1]];
        let rows = b * particles;
        let client = t[0].client.clone();
        let out = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            t[0].device.clone(),
            Shape::new([bundle * b, particles, 4]),
            DType::F32,
        );
        let int = |what: &'static str, v: usize| {
            OpsError::fit_u32(what, v).unwrap_or_else(|e| e.raise("particle frames kernel"))
        };
        let [vs, ds, dm] = self.scales;
        // A thread holds ~170 values in registers: small cubes let several share an SM.
        let dim = CubeDim::new_1d(FRAMES_CUBE);
        let count = CubeCount::Static(int("cubes", rows.div_ceil(FRAMES_CUBE as usize)), 1, 1);
        let arg = |i: usize| t[i].clone().into_tensor_arg();
        // SAFETY: every index is in bounds: `particle_frames` checked the shapes against the
        // widths the kernel is compiled for, and the output holds K rows a particle.
        unsafe {
            frames_kernel::launch_unchecked::<CudaRuntime>(
                &client,
                count,
                dim,
                arg(0),
                arg(1),
                arg(2),
                arg(3),
                arg(4),
                arg(5),
                arg(6),
                arg(7),
                arg(8),
                arg(9),
                arg(10),
                arg(11),
                out.clone().into_tensor_arg(),
                int("particles", particles),
                int("grid side", n),
                int("field channels", channels),
                int("frames", bundle),
                (vs[0], vs[1]),
                (ds[0], ds[1]),
                (dm[0], dm[1]),
                self.bounds,
                self.widths,
            )
        };
        handles.register_float_tensor::<Inner>(&self.desc.outputs[0].id, out);
    }
}

/// [`NetOps::particle_frames`](crate::ops::NetOps::particle_frames) on the GPU: the call's K
/// frames `[K B, N, 4]` in one kernel; `None` for a head whose weights do not fit in a cube's
/// [`SHARED_VALUES`].
///
/// # Panics
/// Shapes that disagree (the model's own tensors: a bug, not an input error).
pub(crate) fn particle_frames(f: ParticleFrames<Cuda>) -> Option<FloatTensor<Cuda>> {
    let [b, particles, w2] = f.vel.shape().dims::<3>();
    let [fb, cells, channels] = f.fields.shape().dims::<3>();
    assert!(fb == b && cells == f.n * f.n && channels >= f.bundle * f.latent);
    assert!(w2 >= 2 && f.material.shape().dims::<3>()[..2] == [b, particles]);
    let [a_in, a] = f.layers[0].0.shape().dims::<2>();
    let a2 = f.layers[1].0.shape().dims::<2>()[1];
    let m = f.material.shape().dims::<3>()[2];
    let h = f.memory.as_ref().map_or(0, |t| t.shape().dims::<2>()[1]);
    assert_eq!(
        a_in,
        f.latent + w2 + m + 2 + h,
        "the head's first layer's inputs"
    );
    let widths = Widths {
        l: f.latent,
        w2,
        m,
        h,
        a,
        a2,
    };
    if widths.offsets()[5] > SHARED_VALUES {
        return None;
    }
    let client = f.pos.client.clone();
    let out = TensorIr::uninit(
        client.create_empty_handle(),
        Shape::new([f.bundle * b, particles, 4]),
        DType::F32,
    );
    let [(wa, ba), (wb, bb), (wo, bo)] = f.layers;
    let inputs: Vec<FloatTensor<Cuda>> = std::iter::once(f.fields)
        .chain(f.memory)
        .chain([f.vel, f.material, f.pos, f.dt, wa, ba, wb, bb, wo, bo])
        .collect();
    let streams = OperationStreams::with_inputs(&inputs);
    let irs: Vec<TensorIr> = inputs.into_iter().map(|t| t.into_ir()).collect();
    let desc = CustomOpIr::new("minflow_particle_frames", &irs, &[out]);
    let op = FramesOp {
        desc: desc.clone(),
        widths,
        sizes: [f.n, f.bundle, channels],
        scales: [f.vel_scale, f.dv_scale, f.dv_mean],
        bounds: f.bounds,
    };
    Some(
        client
            .register(streams, OperationIr::Custom(desc), op)
            .remove(0),
    )
}
