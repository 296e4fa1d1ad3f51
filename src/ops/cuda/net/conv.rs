//! The grid model's im2col and col2im on burn's CUDA backend (feature `cuda`): one cubecl
//! kernel each, recorded as custom operations of burn's fusion layer, so a `k x k`
//! convolution is one im2col launch + one product forward and one col2im launch + two products
//! backward.
//!
//! Why: composed from burn's tensor operations (the padded input's `k^2` shifted slices,
//! concatenated; `composed_grid.rs`), a training step of the U-Net launched ~1,500 kernels,
//! most of them slice assignments and fills of the padding and of the slices' gradients, and
//! the GPU sat idle while the host recorded them (docs/grid.md, "GPU speed"). The column order
//! is [`NetOps::im2col`]'s (that of burn's `Conv2d` weight `[C_out, C_in, k, k]` flattened
//! over its last three dims), the same as the CPU kernels of `cpu/conv.rs`.
//!
//! im2col runs one cube per few rows of columns, staged through shared memory so that both
//! its reads and its writes are coalesced; col2im one thread per output element, which gathers the `k^2` columns that read it instead of scattering into
//! it, so it needs no atomics and is deterministic. How a custom operation joins the fusion stream: see `cublas.rs`.
//!
//! [`NetOps::im2col`]: crate::ops::NetOps::im2col

use burn::cubecl::cuda::CudaRuntime;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Shape, TensorMetadata};
use burn_cubecl::cubecl;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::CubeBackend;
use burn_fusion::stream::{Operation, OperationStreams};
use burn_fusion::FusionRuntime;
use burn_ir::{CustomOpIr, HandleContainer, OperationIr, TensorIr};
use cubecl::{calculate_cube_count_elemwise, prelude::*};

use crate::ops::OpsError;

/// The backend under burn's fusion layer for `Cuda<f32, i32>` (also `cuda/net/stencil.rs`'s).
pub(in crate::ops) type Inner = CubeBackend<CudaRuntime, f32, i32, u8>;
/// burn's CUDA backend with fusion.
pub(in crate::ops) type Cuda = burn::backend::Cuda<f32, i32>;
/// The fusion runtime of [`Inner`].
pub(in crate::ops) type Runtime = <Inner as burn_fusion::FusionBackend>::FusionRuntime;

/// `t` itself when contiguous, else a contiguous copy: what the custom kernels index.
pub(in crate::ops) fn contiguous(t: CubeTensor<CudaRuntime>) -> CubeTensor<CudaRuntime> {
    match t.is_contiguous() {
        true => t,
        false => burn_cubecl::kernel::into_contiguous(t),
    }
}

/// The channel concatenation of channels-last `parts` (`[B, H, W, C_p]` each) -> `[B, H, W,
/// Σ C_p]`: the one part itself, or one concatenation (the convolutions of several parts).
pub(in crate::ops) fn cat_channels(parts: &[FloatTensor<Cuda>]) -> FloatTensor<Cuda> {
    match parts {
        [x] => x.clone(),
        _ => <Cuda as burn::tensor::ops::FloatTensorOps<Cuda>>::float_cat(parts.to_vec(), 3),
    }
}

/// The cube count and size of an element-wise launch over `units` threads (what the custom
/// kernels here and in `cuda/net/stencil.rs` that run one thread per element launch with).
pub(in crate::ops) fn elementwise(
    client: &ComputeClient<CudaRuntime>,
    units: usize,
) -> (CubeCount, CubeDim) {
    let cube_dim = CubeDim::new(client, units);
    (
        calculate_cube_count_elemwise(client, units, cube_dim),
        cube_dim,
    )
}

/// im2col: `input` `[B, H, W, C]` (contiguous) -> `output` `[B H W, C k^2]`. Output element
/// `(row, i k^2 + ky k + kx)`, row = `(b H + y) W + x`, is channel `i` of input position
/// `(y + ky - k/2, x + kx - k/2)`, or 0 outside the grid.
///
/// One cube per `r` consecutive rows (`rows` in all; cubes laid out 2-D past 65,535), in two
/// coalesced passes through shared memory: its threads read the rows' `k^2` input positions
/// channel by channel (adjacent threads, adjacent channels) into the tile in column order,
/// then write the tile out as the rows' contiguous `r C k^2` columns. The sizes are
/// compile-time, so every index is a division by a constant. One thread per output element
/// straight from the input ran at a quarter of the H100's bandwidth (adjacent outputs read
/// `k^2` different positions); one cube per row was latency-bound (docs/kernels.md,
/// "Roofline").
#[cube(launch)]
fn im2col_kernel<F: Float>(
    input: &Tensor<F>,
    output: &mut Tensor<F>,
    rows: u32,
    #[comptime] h: u32,
    #[comptime] w: u32,
    #[comptime] c: u32,
    #[comptime] k: u32,
    #[comptime] r: u32,
    #[define(F)] _dtype: StorageType,
) {
    let rows = rows as usize;
    let (h, w, c, k, r) = (h as usize, w as usize, c as usize, k as usize, r as usize);
    let first = (CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) as usize * r;
    if first >= rows {
        terminate!();
    }
    let (kk, half) = (k * k, k / 2);
    let width = c * kk;
    let mut tile = SharedMemory::<F>::new(r * c * k * k);
    // Pass 1: element j = (rr, s C + i) of the rows' inputs, offset s = ky k + kx, channel
    // i; stored at the tile's column i k^2 + s of row rr.
    let mut j = UNIT_POS_X as usize;
    while j < r * width {
        let rr = j / width;
        let s = (j % width) / c;
        let i = j % c;
        let row = first + rr;
        let (ky, kx) = (s / k, s % k);
        let (x, y, b) = (row % w, (row / w) % h, row / (w * h));
        // Input position (y + ky - half, x + kx - half), kept unsigned: yy = y + ky.
        let (yy, xx) = (y + ky, x + kx);
        let mut value = F::new(0.0);
        if row < rows && yy >= half && yy < h + half && xx >= half && xx < w + half {
            value = input[((b * h + yy - half) * w + xx - half) * c + i];
        }
        tile[rr * width + i * kk + s] = value;
        j += CUBE_DIM_X as usize;
    }
    sync_cube();
    // Pass 2: the rows' columns, in order.
    let mut j = UNIT_POS_X as usize;
    while j < r * width {
        if first + j / width < rows {
            output[first * width + j] = tile[j];
        }
        j += CUBE_DIM_X as usize;
    }
}

/// col2im, the adjoint of [`im2col_kernel`]: `cols` `[B H W, C k^2]` (contiguous) ->
/// `output` `[B, H, W, C]`. Output element `(b, y, x, i)` sums the `k^2` columns that read
/// it: `cols[(b H + y - ky + k/2) W + x - kx + k/2, i k^2 + ky k + kx]` over the offsets whose
/// row lies inside the grid.
#[cube(launch)]
fn col2im_kernel<F: Float>(
    cols: &Tensor<F>,
    output: &mut Tensor<F>,
    h: u32,
    w: u32,
    c: u32,
    #[comptime] k: u32,
    #[define(F)] _dtype: StorageType,
) {
    if ABSOLUTE_POS >= output.len() {
        terminate!();
    }
    let (h, w, c) = (h as usize, w as usize, c as usize);
    let k = k as usize;
    let (kk, half) = (k * k, k / 2);
    let pos = ABSOLUTE_POS;
    let i = pos % c;
    let x = (pos / c) % w;
    let y = (pos / (c * w)) % h;
    let b = pos / (c * w * h);
    // The reading row's position (y0, x0) = (y - ky + half, x - kx + half), unsigned.
    let (yp, xp) = (y + half, x + half);
    let mut acc = F::new(0.0);
    #[unroll]
    for s in 0..kk {
        let (ky, kx) = (s / k, s % k);
        if yp >= ky && yp < h + ky && xp >= kx && xp < w + kx {
            acc += cols[((b * h + yp - ky) * w + xp - kx) * (c * kk) + i * kk + s];
        }
    }
    output[pos] = acc;
}

/// Which of the two kernels a recorded operation launches.
#[derive(Clone, Copy, Debug)]
enum Kind {
    Im2col,
    Col2im,
}

impl Kind {
    /// The output shape for a `[B, H, W, C]` grid and a `k x k` kernel.
    fn out_shape(self, [b, h, w, c]: [usize; 4], k: usize) -> Shape {
        match self {
            Kind::Im2col => Shape::new([b * h * w, c * k * k]),
            Kind::Col2im => Shape::new([b, h, w, c]),
        }
    }
}

/// The recorded operation: input `[x]`, output `[y]`; `dims` = `[B, H, W, C]` of the grid.
#[derive(Debug)]
struct ConvOp {
    desc: CustomOpIr,
    kind: Kind,
    dims: [usize; 4],
    k: usize,
}

impl Operation<Runtime> for ConvOp {
    fn execute(&self, handles: &mut HandleContainer<<Runtime as FusionRuntime>::FusionHandle>) {
        let ([x], [y]) = self.desc.as_fixed();
        let x = handles.get_float_tensor::<Inner>(x);
        let out = (launch(x, self.kind, self.dims, self.k))
            .unwrap_or_else(|e| e.raise("im2col / col2im kernel"));
        handles.register_float_tensor::<Inner>(&y.id, out);
    }
}

/// Launches `kind` on the cubecl tensor `x`; returns the new contiguous output.
///
/// # Errors
/// A size that does not fit the kernel's `u32`.
fn launch(
    x: CubeTensor<CudaRuntime>,
    kind: Kind,
    dims: [usize; 4],
    k: usize,
) -> Result<CubeTensor<CudaRuntime>, OpsError> {
    let [_, h, w, c] = dims;
    let x = contiguous(x);
    let shape = kind.out_shape(dims, k);
    let client = x.client.clone();
    let out = burn_cubecl::ops::numeric::empty_device_contiguous_dtype(
        client.clone(),
        x.device.clone(),
        shape,
        x.dtype,
    );
    let int = |v: usize| OpsError::fit_u32("grid dimension", v);
    let dtype = out.dtype.into();
    match kind {
        Kind::Im2col => {
            // r rows a cube, their tile at most 4,096 values (16 kB of shared memory), 256
            // threads; the cubes over a 2-D grid when they are more than 65,535.
            let rows = dims[0] * h * w;
            let width = c * k * k;
            let r = (4096 / width).clamp(1, 32);
            let cubes = rows.div_ceil(r);
            let x_count = cubes.clamp(1, 65_535);
            let count = CubeCount::Static(int(x_count)?, int(cubes.div_ceil(x_count))?, 1);
            im2col_kernel::launch::<CudaRuntime>(
                &client,
                count,
                CubeDim::new_1d(256),
                x.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                int(rows)?,
                int(h)?,
                int(w)?,
                int(c)?,
                int(k)?,
                int(r)?,
                dtype,
            );
        }
        Kind::Col2im => {
            // One thread per output element.
            let (cube_count, cube_dim) = elementwise(&client, out.meta.num_elements());
            col2im_kernel::launch::<CudaRuntime>(
                &client,
                cube_count,
                cube_dim,
                x.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                int(h)?,
                int(w)?,
                int(c)?,
                int(k)?,
                dtype,
            );
        }
    }
    Ok(out)
}

/// Records `kind` on `x`'s fusion stream; returns its output.
fn record(x: FloatTensor<Cuda>, kind: Kind, dims: [usize; 4], k: usize) -> FloatTensor<Cuda> {
    let shape = kind.out_shape(dims, k);
    let name = match kind {
        Kind::Im2col => "minflow_im2col",
        Kind::Col2im => "minflow_col2im",
    };
    let client = x.client.clone();
    let dtype = x.dtype();
    let streams = OperationStreams::with_inputs([&x]);
    let out = TensorIr::uninit(client.create_empty_handle(), shape, dtype);
    let desc = CustomOpIr::new(name, &[x.into_ir()], &[out]);
    let op = ConvOp {
        desc: desc.clone(),
        kind,
        dims,
        k,
    };
    client
        .register(streams, OperationIr::Custom(desc), op)
        .remove(0)
}

/// [`NetOps::im2col`](crate::ops::NetOps::im2col) on the GPU: `x` `[B, H, W, C]` ->
/// `[B H W, C k^2]`, one kernel.
pub(crate) fn im2col(x: FloatTensor<Cuda>, k: usize) -> FloatTensor<Cuda> {
    let s = x.shape();
    let dims = [s[0], s[1], s[2], s[3]];
    record(x, Kind::Im2col, dims, k)
}

/// [`NetOps::col2im`](crate::ops::NetOps::col2im) on the GPU: `cols` `[B H W, C k^2]` ->
/// `[B, H, W, C]` = `shape`, one kernel.
///
/// # Panics
/// `cols` is not `[B H W, C k^2]` for `shape` = `[B, H, W, C]` (the kernel would read out of
/// bounds).
pub(crate) fn col2im(cols: FloatTensor<Cuda>, shape: [usize; 4], k: usize) -> FloatTensor<Cuda> {
    let (s, expected) = (cols.shape(), Kind::Im2col.out_shape(shape, k));
    assert!(
        s == expected,
        "col2im: columns {s:?} do not match {shape:?} with k = {k} ({expected:?})"
    );
    record(cols, Kind::Col2im, shape, k)
}
