//! The grid model's sparse particle-grid transfers on burn's CUDA backend (feature `cuda`):
//! G2P ([`NetOps::stencil_gather`]) and P2G ([`NetOps::stencil_splat`]) as one cubecl kernel
//! each, recorded as custom operations of burn's fusion layer (as `cuda_conv.rs`).
//!
//! Why: the separable dense form (`model::grid::transfer`) turns a transfer into two batched
//! products over `[B, N, n]` weights and a `[B, N, n C]` intermediate. With 256 scenes of
//! 2,500 particles on a 64 x 64 grid that intermediate is ~3 GB, and cubecl's kernel profile
//! of one network call on an H100 put ~45 of its ~104 ms in those passes (docs/scale.md).
//! The sparse form reads 9 nodes a particle: G2P is a gather (one thread per particle and
//! channel, no atomics); P2G a scatter-add with one f32 atomic add per node, as MPM codes
//! do their P2G on GPUs (Hu et al. 2019, "Taichi", the MLS-MPM example; Wang et al. 2020,
//! "A massively parallel and scalable multi-GPU material point method"). The atomics sum in
//! no fixed order, so P2G is exact to rounding but not bitwise reproducible: meant for
//! inference only; training on a GPU keeps the dense products. The stencil itself
//! ([`NetOps::sparse_stencil`]) is one kernel too.
//!
//! Inference on CUDA takes these ([`NetOps::dense_stencil`]). P2G's output is allocated
//! contiguous and zeroed by [`zero_kernel`]: burn's `zeros_client` pitches each innermost row
//! of CUDA memory to a power of two bytes (12 f32 channels -> a row stride of 16), while the
//! kernel writes flat `row * c + j`. On one H100 every form matches the CPU backend to 1.2e-7
//! (`minflow bench transfer --device cuda`).
//!
//! [`NetOps::stencil_gather`]: super::NetOps::stencil_gather
//! [`NetOps::stencil_splat`]: super::NetOps::stencil_splat
//! [`NetOps::dense_stencil`]: super::NetOps::dense_stencil
//! [`NetOps::sparse_stencil`]: super::NetOps::sparse_stencil

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{DType, Shape, TensorMetadata};
use burn_cubecl::cubecl;
use burn_cubecl::tensor::CubeTensor;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::{calculate_cube_count_elemwise, prelude::*};

use super::cuda_conv::{contiguous, Cuda, Inner, Runtime};

/// G2P: `out[p, j] = sum_k weight[p, k] grid[index[p, k], j]` for every particle `p` of the
/// batch (`B N` of them) and channel `j < c`; `grid` `[B n^2, c]`, `index` and `weight`
/// `[B N, 9]`, `out` `[B N, c]`, all contiguous. One thread per output element.
#[cube(launch)]
fn gather_kernel<F: Float>(
    grid: &Tensor<F>,
    index: &Tensor<i32>,
    weight: &Tensor<F>,
    out: &mut Tensor<F>,
    c: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= out.len() {
        terminate!();
    }
    let c = c as usize;
    let p = ABSOLUTE_POS / c;
    let j = ABSOLUTE_POS % c;
    let mut acc = F::new(0.0);
    #[unroll]
    for k in 0..9 {
        let row = usize::cast_from(index[p * 9 + k]);
        acc += weight[p * 9 + k] * grid[row * c + j];
    }
    out[ABSOLUTE_POS] = acc;
}

/// `slot += value`, atomically.
#[cube]
fn atomic_add<F: Float>(slot: &mut Atomic<F>, value: F) {
    slot.fetch_add(value);
}

/// One axis of MLS-MPM's quadratic B-spline at distance `x` (grid units) from a node: `0.75 -
/// x^2` within 0.5, `0.5 (1.5 - |x|)^2` within 1.5, else 0 (Hu et al. 2018; the GPU form of
/// [`crate::bspline::weights`], which the CPU sites share, at distances `f`, `f - 1`, `f - 2`;
/// a `#[cube]` function cannot call it).
#[cube]
fn bspline<F: Float>(x: F) -> F {
    let a = F::abs(x);
    let mut w = F::new(0.0);
    if a < F::new(0.5) {
        w = F::new(0.75) - a * a;
    } else if a < F::new(1.5) {
        let d = F::new(1.5) - a;
        w = F::new(0.5) * d * d;
    }
    w
}

/// The sparse stencil of every particle (as `ops::cpu::transfer::sparse_stencil`): `pos`
/// `[B N, 2]` (domain units, contiguous), clamped into `[dx / 2, 1 - 1.5 dx - 1e-5]`, ->
/// `index` `[B N 9]` (flat rows `b n^2 + (bx + i) n + by + j` for node `k = 3 i + j`) and
/// `weight` `[B N 9]`. One thread per particle; `particles` = N, `n` the grid size.
#[cube(launch)]
fn stencil_kernel<F: Float>(
    pos: &Tensor<F>,
    index: &mut Tensor<i32>,
    weight: &mut Tensor<F>,
    particles: u32,
    n: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS * 9 >= weight.len() {
        terminate!();
    }
    let p = ABSOLUTE_POS;
    let nn = n as usize;
    let b = p / (particles as usize);
    let nf = F::cast_from(n);
    let dx = F::new(1.0) / nf;
    let lo = F::new(0.5) * dx;
    let hi = F::new(1.0) - F::new(1.5) * dx - F::new(0.00001);
    let mut x = pos[p * 2];
    let mut y = pos[p * 2 + 1];
    if x < lo {
        x = lo;
    }
    if x > hi {
        x = hi;
    }
    if y < lo {
        y = lo;
    }
    if y > hi {
        y = hi;
    }
    let (gx, gy) = (x * nf, y * nf);
    let (bx, by) = (F::floor(gx - F::new(0.5)), F::floor(gy - F::new(0.5)));
    let (fx, fy) = (gx - bx, gy - by);
    let row = b * nn * nn + usize::cast_from(bx) * nn + usize::cast_from(by);
    #[unroll]
    for k in 0..9usize {
        let i = k / 3;
        let j = k % 3;
        index[p * 9 + k] = i32::cast_from(row + i * nn + j);
        weight[p * 9 + k] = bspline::<F>(fx - F::cast_from(i)) * bspline::<F>(fy - F::cast_from(j));
    }
}

/// P2G, the adjoint of [`gather_kernel`]: `out[index[p, k], j] += weight[p, k] values[p, j]`;
/// `values` `[B N, c]`, `index` and `weight` `[B N, 9]`, `out` `[B n^2, c]` zeroed first. One
/// thread per value, nine atomic adds each.
#[cube(launch)]
fn splat_kernel<F: Float>(
    values: &Tensor<F>,
    index: &Tensor<i32>,
    weight: &Tensor<F>,
    out: &mut Tensor<Atomic<F>>,
    c: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= values.len() {
        terminate!();
    }
    let c = c as usize;
    let p = ABSOLUTE_POS / c;
    let j = ABSOLUTE_POS % c;
    let v = values[ABSOLUTE_POS];
    #[unroll]
    for k in 0..9 {
        let row = usize::cast_from(index[p * 9 + k]);
        atomic_add::<F>(&mut out[row * c + j], weight[p * 9 + k] * v);
    }
}

/// `out[i] = 0` for every element of a contiguous `out`: P2G's output before its atomic adds.
/// (burn-cubecl's `zeros_client` allocates through the runtime's layout policy, which on CUDA
/// pitches each innermost row to a power of two bytes: `[B, n^2, 12]` f32 gets row stride
/// 16, not 12, and [`splat_kernel`]'s flat `row * c + j` then lands in the wrong rows. wgpu's
/// policy is contiguous, which is why the same kernels matched there.)
#[cube(launch)]
fn zero_kernel<F: Float>(out: &mut Tensor<F>, #[define(F)] _dtype: StorageType) {
    if ABSOLUTE_POS >= out.len() {
        terminate!();
    }
    out[ABSOLUTE_POS] = F::new(0.0);
}

/// Which of the two kernels a recorded operation launches.
#[derive(Clone, Copy, Debug)]
enum Kind {
    Gather,
    Splat,
}

/// The recorded operation: inputs `[x, index, weight]` (x the grid or the values), output
/// `[y]` of `out_shape`; `c` channels.
#[derive(Debug)]
struct StencilOp {
    desc: CustomOpIr,
    kind: Kind,
    out_shape: Shape,
    c: usize,
}

impl Operation<Runtime> for StencilOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let ([x, index, weight], [y]) = self.desc.as_fixed();
        let x = handles.get_float_tensor::<Inner>(x);
        let index = handles.get_int_tensor::<Inner>(index);
        let weight = handles.get_float_tensor::<Inner>(weight);
        let out = launch(x, index, weight, self);
        handles.register_float_tensor::<Inner>(&y.id, out);
    }
}

/// Launches `op`'s kernel; returns its new contiguous output.
fn launch(
    x: CubeTensor<CudaRuntime>,
    index: CubeTensor<CudaRuntime>,
    weight: CubeTensor<CudaRuntime>,
    op: &StencilOp,
) -> CubeTensor<CudaRuntime> {
    // The kernels read 32-bit node indices (`Cuda<f32, i32>`'s); any other is cast.
    let index = match index.dtype {
        DType::I32 => index,
        _ => burn_cubecl::kernel::cast(index, DType::I32),
    };
    let (x, index, weight) = (contiguous(x), contiguous(index), contiguous(weight));
    let client = x.client.clone();
    let (device, dtype) = (x.device.clone(), x.dtype);
    // Both kernels index `out` flat (`row * c + j`), so it must be contiguous: never
    // `zeros_client` / `empty_device_dtype`, whose CUDA layout is pitched (see `zero_kernel`).
    let out = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
        client.clone(),
        device,
        op.out_shape.clone(),
        dtype,
    );
    debug_assert!(
        out.is_contiguous(),
        "stencil output {:?} is not contiguous",
        out.meta
    );
    if let Kind::Splat = op.kind {
        let units = out.meta.num_elements();
        let cube_dim = CubeDim::new(&client, units);
        let cube_count = calculate_cube_count_elemwise(&client, units, cube_dim);
        zero_kernel::launch::<CudaRuntime>(
            &client,
            cube_count,
            cube_dim,
            out.clone().into_tensor_arg(),
            dtype.into(),
        );
    }
    // One thread per output element (gather) or per value (splat).
    let units = match op.kind {
        Kind::Gather => out.meta.num_elements(),
        Kind::Splat => x.meta.num_elements(),
    };
    let cube_dim = CubeDim::new(&client, units);
    let cube_count = calculate_cube_count_elemwise(&client, units, cube_dim);
    let c = u32::try_from(op.c).expect("channel count fits u32");
    let run = match op.kind {
        Kind::Gather => gather_kernel::launch::<CudaRuntime>,
        Kind::Splat => splat_kernel::launch::<CudaRuntime>,
    };
    run(
        &client,
        cube_count,
        cube_dim,
        x.into_tensor_arg(),
        index.into_tensor_arg(),
        weight.into_tensor_arg(),
        out.clone().into_tensor_arg(),
        c,
        dtype.into(),
    );
    out
}

/// Records `kind` on the fusion stream of its inputs; returns its output of `out_shape`.
fn record(
    kind: Kind,
    x: FloatTensor<Cuda>,
    index: IntTensor<Cuda>,
    weight: FloatTensor<Cuda>,
    out_shape: Shape,
    c: usize,
) -> FloatTensor<Cuda> {
    let name = match kind {
        Kind::Gather => "minflow_stencil_gather",
        Kind::Splat => "minflow_stencil_splat",
    };
    let client = x.client.clone();
    let dtype = x.dtype();
    let streams = OperationStreams::with_inputs([&x, &index, &weight]);
    let out = TensorIr::uninit(client.create_empty_handle(), out_shape.clone(), dtype);
    let desc = CustomOpIr::new(
        name,
        &[x.into_ir(), index.into_ir(), weight.into_ir()],
        &[out],
    );
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

/// [`NetOps::stencil_gather`](super::NetOps::stencil_gather) on the GPU: `grid` `[B, n^2, C]`,
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

/// [`NetOps::stencil_splat`](super::NetOps::stencil_splat) on the GPU: `values` `[B, N, C]`,
/// `index` `[B N 9]` (flat rows of a `[B nodes, C]` grid), `weight` `[B, N, 9]` ->
/// `[B, nodes, C]`, one kernel after the output's zero fill. The caller's `index` must stay
/// below `B nodes` (the stencil's nodes lie on the grid: `model::grid::transfer`).
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
        let units = b * n_p;
        let cube_dim = CubeDim::new(&client, units);
        let cube_count = calculate_cube_count_elemwise(&client, units, cube_dim);
        let int = |v: usize| u32::try_from(v).expect("stencil dimension fits u32");
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

/// [`NetOps::sparse_stencil`](super::NetOps::sparse_stencil) on the GPU: `pos` `[B, N, 2]`
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
