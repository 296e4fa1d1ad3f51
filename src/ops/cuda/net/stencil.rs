//! The grid model's sparse particle-grid transfers on burn's CUDA backend (feature `cuda`):
//! G2P ([`NetOps::stencil_gather`]) and P2G ([`NetOps::stencil_splat`]) as one cubecl kernel
//! each, recorded as custom operations of burn's fusion layer (as `cuda/net/conv.rs`).
//!
//! Why: the separable dense form (`model::grid::transfer`) turns a transfer into two batched
//! products over `[B, N, n]` weights and a `[B, N, n C]` intermediate. With 256 scenes of
//! 2,500 particles on a 64 x 64 grid that intermediate is ~3 GB, and cubecl's kernel profile
//! of one network call on an H100 put ~45 of its ~104 ms in those passes (docs/scale.md).
//! The sparse form reads 9 nodes a particle: G2P is a gather (one thread per particle and
//! channel, no atomics); P2G a scatter-add with atomic adds, as MPM codes do their P2G on GPUs
//! (Hu et al. 2019, "Taichi", the MLS-MPM example; Wang et al. 2020, "A massively parallel and
//! scalable multi-GPU material point method"). f32 atomics sum in no fixed order, so such a
//! P2G differs from run to run in its last bits, and so would every gradient that flows
//! through it (G2P's backward is a P2G). These add in 64-bit fixed point instead
//! (`cuda/net/stencil_kernels.rs`): integer sums do not depend on the order, so P2G, and training through
//! it, is the same to the bit on every run. Inference and training on CUDA both take these
//! kernels ([`NetOps::dense_stencil`]; `MINFLOW_CUDA_TRANSFERS=dense` takes the dense
//! products back). The stencil itself ([`NetOps::sparse_stencil`]) is one kernel too.
//!
//! Outputs are allocated contiguous ([`contiguous_empty`]; P2G's sums zeroed by a
//! kernel): burn's `zeros_client` pitches each innermost row of CUDA memory to a
//! power of two bytes (12 f32 channels -> a row stride of 16), while the kernels write flat
//! `row * c + j`. `minflow bench transfer --device cuda` checks every form against the CPU
//! backend, and P2G's bits against the same values in reverse particle order.
//!
//! [`NetOps::stencil_gather`]: crate::ops::NetOps::stencil_gather
//! [`NetOps::stencil_splat`]: crate::ops::NetOps::stencil_splat
//! [`NetOps::dense_stencil`]: crate::ops::NetOps::dense_stencil
//! [`NetOps::sparse_stencil`]: crate::ops::NetOps::sparse_stencil

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{DType, Shape, TensorMetadata};
use burn_cubecl::tensor::CubeTensor;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};

use super::conv::{contiguous, elementwise, Cuda, Inner, Runtime};
use super::stencil_kernels::{
    clear_kernel, gather_kernel, splat_kernel, stencil_kernel, unfix_kernel,
};
use crate::ops::OpsError;

/// Which of the two transfers a recorded operation runs.
#[derive(Clone, Copy, Debug)]
enum Kind {
    Gather,
    Splat,
}

/// The recorded operation: inputs `[x, index, weight]` (gather: x the grid) or `[x, index,
/// weight, max]` (splat: x the values, `max` their largest `|value|`), output `[y]` of
/// `out_shape`; `c` channels.
#[derive(Debug)]
struct StencilOp {
    desc: CustomOpIr,
    kind: Kind,
    out_shape: Shape,
    c: usize,
}

impl Operation<Runtime> for StencilOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let (x, index, weight, max, y) = match self.kind {
            Kind::Gather => {
                let ([x, index, weight], [y]) = self.desc.as_fixed();
                (x, index, weight, None, y)
            }
            Kind::Splat => {
                let ([x, index, weight, max], [y]) = self.desc.as_fixed();
                (x, index, weight, Some(max), y)
            }
        };
        let x = contiguous(handles.get_float_tensor::<Inner>(x));
        let index = handles.get_int_tensor::<Inner>(index);
        // The kernels read 32-bit node indices (`Cuda<f32, i32>`'s); any other is cast.
        let index = contiguous(match index.dtype {
            DType::I32 => index,
            _ => burn_cubecl::kernel::cast(index, DType::I32),
        });
        let weight = contiguous(handles.get_float_tensor::<Inner>(weight));
        let out = match max {
            None => launch_gather(x, index, weight, self),
            Some(max) => {
                let max = handles.get_float_tensor::<Inner>(max);
                launch_splat(x, index, weight, contiguous(max), self)
            }
        };
        let out = out.unwrap_or_else(|e| e.raise("P2G / G2P kernel"));
        handles.register_float_tensor::<Inner>(&y.id, out);
    }
}

/// A new contiguous tensor of `shape` and `dtype` on `like`'s device. Both kernels index
/// their outputs flat (`row * c + j`), so never `zeros_client` / `empty_device_dtype`, whose
/// CUDA layout is pitched (see [`clear_kernel`]).
fn contiguous_empty(
    like: &CubeTensor<CudaRuntime>,
    shape: Shape,
    dtype: DType,
) -> CubeTensor<CudaRuntime> {
    let out = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
        like.client.clone(),
        like.device.clone(),
        shape,
        dtype,
    );
    debug_assert!(
        out.is_contiguous(),
        "stencil output {:?} is not contiguous",
        out.meta
    );
    out
}

/// Launches [`gather_kernel`], one thread per output element; returns its output.
fn launch_gather(
    grid: CubeTensor<CudaRuntime>,
    index: CubeTensor<CudaRuntime>,
    weight: CubeTensor<CudaRuntime>,
    op: &StencilOp,
) -> Result<CubeTensor<CudaRuntime>, OpsError> {
    let (client, dtype) = (grid.client.clone(), grid.dtype);
    let out = contiguous_empty(&grid, op.out_shape.clone(), dtype);
    let (count, dim) = elementwise(&client, out.meta.num_elements());
    let c = OpsError::fit_u32("channel count", op.c)?;
    gather_kernel::launch::<CudaRuntime>(
        &client,
        count,
        dim,
        grid.into_tensor_arg(),
        index.into_tensor_arg(),
        weight.into_tensor_arg(),
        out.clone().into_tensor_arg(),
        c,
        dtype.into(),
    );
    Ok(out)
}

/// Launches P2G's three kernels ([`clear_kernel`], [`splat_kernel`] one thread per value,
/// [`unfix_kernel`]); returns the f32 output.
fn launch_splat(
    values: CubeTensor<CudaRuntime>,
    index: CubeTensor<CudaRuntime>,
    weight: CubeTensor<CudaRuntime>,
    max: CubeTensor<CudaRuntime>,
    op: &StencilOp,
) -> Result<CubeTensor<CudaRuntime>, OpsError> {
    let (client, dtype) = (values.client.clone(), values.dtype);
    let acc = contiguous_empty(&values, op.out_shape.clone(), DType::I64);
    let out = contiguous_empty(&values, op.out_shape.clone(), dtype);
    let nodes = out.meta.num_elements();
    let c = OpsError::fit_u32("channel count", op.c)?;
    let particles = values.meta.num_elements() / op.c.max(1);
    let count = OpsError::fit_u32("particle count", particles)?;
    let (cubes, dim) = elementwise(&client, nodes);
    clear_kernel::launch::<CudaRuntime>(&client, cubes, dim, acc.clone().into_tensor_arg());
    let (cubes, dim) = elementwise(&client, values.meta.num_elements());
    splat_kernel::launch::<CudaRuntime>(
        &client,
        cubes,
        dim,
        values.into_tensor_arg(),
        index.into_tensor_arg(),
        weight.into_tensor_arg(),
        max.clone().into_tensor_arg(),
        acc.clone().into_tensor_arg(),
        c,
        count,
        dtype.into(),
    );
    let (cubes, dim) = elementwise(&client, nodes);
    unfix_kernel::launch::<CudaRuntime>(
        &client,
        cubes,
        dim,
        acc.into_tensor_arg(),
        max.into_tensor_arg(),
        out.clone().into_tensor_arg(),
        count,
        dtype.into(),
    );
    Ok(out)
}

/// Records `kind` on the fusion stream of its inputs (`[x, index, weight]`, and for P2G the
/// values' largest `|value|`, one reduction recorded first); returns its output of
/// `out_shape`.
fn record(
    kind: Kind,
    x: FloatTensor<Cuda>,
    index: IntTensor<Cuda>,
    weight: FloatTensor<Cuda>,
    out_shape: Shape,
    c: usize,
) -> FloatTensor<Cuda> {
    use burn::tensor::ops::FloatTensorOps;
    let client = x.client.clone();
    let dtype = x.dtype();
    let out = TensorIr::uninit(client.create_empty_handle(), out_shape.clone(), dtype);
    let (name, desc, streams) = match kind {
        Kind::Gather => {
            let streams = OperationStreams::with_inputs([&x, &index, &weight]);
            let inputs = [x.into_ir(), index.into_ir(), weight.into_ir()];
            ("minflow_stencil_gather", inputs.to_vec(), streams)
        }
        Kind::Splat => {
            let max = <Cuda as FloatTensorOps<Cuda>>::float_max_abs(x.clone());
            let streams = OperationStreams::with_inputs([&x, &index, &weight, &max]);
            let inputs = [
                x.into_ir(),
                index.into_ir(),
                weight.into_ir(),
                max.into_ir(),
            ];
            ("minflow_stencil_splat", inputs.to_vec(), streams)
        }
    };
    let desc = CustomOpIr::new(name, &desc, &[out]);
    let op = StencilOp {
        desc: desc.clone(),
        kind,
        out_shape,
        c,
    };
    client
        .register(streams, OperationIr::Custom(desc), op)
        .remove(0)
}

/// The `(B, N)` of a `[B, N, 9]` stencil weight.
///
/// # Panics
/// `weight` is not `[B, N, 9]`, or `index` does not hold `B N 9` nodes.
fn stencil_dims(index: &IntTensor<Cuda>, weight: &FloatTensor<Cuda>) -> (usize, usize) {
    let (w, i) = (weight.shape(), index.shape());
    assert!(
        w.num_dims() == 3 && w[2] == 9 && i.num_elements() == w.num_elements(),
        "stencil: weight {w:?} is not [B, N, 9] or index {i:?} does not match it"
    );
    (w[0], w[1])
}

/// [`NetOps::stencil_gather`](crate::ops::NetOps::stencil_gather) on the GPU: `grid` `[B, n^2, C]`,
/// `index` `[B N 9]` (flat rows of the `[B n^2, C]` grid), `weight` `[B, N, 9]` -> `[B, N, C]`,
/// one kernel.
///
/// # Panics
/// The shapes do not match (the kernel would read out of bounds).
pub(crate) fn gather(
    grid: FloatTensor<Cuda>,
    index: IntTensor<Cuda>,
    weight: FloatTensor<Cuda>,
) -> FloatTensor<Cuda> {
    let (b, n) = stencil_dims(&index, &weight);
    let g = grid.shape();
    assert!(
        g.num_dims() == 3 && g[0] == b,
        "gather: grid {g:?} for a batch of {b}"
    );
    let c = g[2];
    record(Kind::Gather, grid, index, weight, Shape::new([b, n, c]), c)
}

/// [`NetOps::stencil_splat`](crate::ops::NetOps::stencil_splat) on the GPU: `values` `[B, N, C]`,
/// `index` `[B N 9]` (flat rows of a `[B nodes, C]` grid), `weight` `[B, N, 9]` ->
/// `[B, nodes, C]`, deterministic to the bit ([`splat_kernel`]: the values' largest
/// `|value|`, then three kernels). The caller's `index` must stay below `B nodes` (the
/// stencil's nodes lie on the grid: `model::grid::transfer`).
///
/// # Panics
/// The shapes do not match.
pub(crate) fn splat(
    values: FloatTensor<Cuda>,
    index: IntTensor<Cuda>,
    weight: FloatTensor<Cuda>,
    nodes: usize,
) -> FloatTensor<Cuda> {
    let (b, n) = stencil_dims(&index, &weight);
    let v = values.shape();
    assert!(
        v.num_dims() == 3 && v[0] == b && v[1] == n,
        "splat: values {v:?} for a stencil of [{b}, {n}, 9]"
    );
    let c = v[2];
    record(
        Kind::Splat,
        values,
        index,
        weight,
        Shape::new([b, nodes, c]),
        c,
    )
}

/// The recorded stencil operation: input `[pos]`, outputs `[index, weight]`.
#[derive(Debug)]
struct BuildOp {
    desc: CustomOpIr,
    batch: usize,
    particles: usize,
    n: usize,
}

impl Operation<Runtime> for BuildOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let ([pos], [index_ir, weight_ir]) = self.desc.as_fixed();
        let pos = contiguous(handles.get_float_tensor::<Inner>(pos));
        let client = pos.client.clone();
        let (device, dtype) = (pos.device.clone(), pos.dtype);
        let (b, n_p) = (self.batch, self.particles);
        let index = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            device.clone(),
            Shape::new([b * n_p * 9]),
            DType::I32,
        );
        let weight = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
            client.clone(),
            device,
            Shape::new([b, n_p, 9]),
            dtype,
        );
        let (cube_count, cube_dim) = elementwise(&client, b * n_p);
        let int = |v: usize| {
            OpsError::fit_u32("stencil dimension", v).unwrap_or_else(|e| e.raise("stencil kernel"))
        };
        stencil_kernel::launch::<CudaRuntime>(
            &client,
            cube_count,
            cube_dim,
            pos.into_tensor_arg(),
            index.clone().into_tensor_arg(),
            weight.clone().into_tensor_arg(),
            int(n_p),
            int(self.n),
            dtype.into(),
        );
        handles.register_int_tensor::<Inner>(&index_ir.id, index);
        handles.register_float_tensor::<Inner>(&weight_ir.id, weight);
    }
}

/// [`NetOps::sparse_stencil`](crate::ops::NetOps::sparse_stencil) on the GPU: `pos` `[B, N, 2]`
/// (domain units) -> (`index` `[B N 9]`, `weight` `[B, N, 9]`) on an `n x n` grid, one kernel
/// (burn's tensor operations take ~20 launches for it: `model::grid::transfer::composed_stencil`).
///
/// # Panics
/// `pos` is not `[B, N, 2]`.
pub(crate) fn stencil(pos: FloatTensor<Cuda>, n: usize) -> (IntTensor<Cuda>, FloatTensor<Cuda>) {
    let s = pos.shape();
    assert!(
        s.num_dims() == 3 && s[2] == 2,
        "stencil: positions {s:?} are not [B, N, 2]"
    );
    let (b, n_p) = (s[0], s[1]);
    let client = pos.client.clone();
    let dtype = pos.dtype();
    let streams = OperationStreams::with_inputs([&pos]);
    let index = TensorIr::uninit(
        client.create_empty_handle(),
        Shape::new([b * n_p * 9]),
        DType::I32,
    );
    let weight = TensorIr::uninit(client.create_empty_handle(), Shape::new([b, n_p, 9]), dtype);
    let desc = CustomOpIr::new("minflow_stencil", &[pos.into_ir()], &[index, weight]);
    let op = BuildOp {
        desc: desc.clone(),
        batch: b,
        particles: n_p,
        n,
    };
    let mut out = client.register(streams, OperationIr::Custom(desc), op);
    let weight = out.pop().expect("two outputs");
    let index = out.pop().expect("two outputs");
    (index, weight)
}
