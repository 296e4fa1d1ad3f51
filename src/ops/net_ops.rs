//! [`NetOps`], the backend extension trait of `ops`: each operation's contract (shapes, what
//! it computes) and its default, composed from burn's tensor operations (`composed.rs`,
//! `composed_grid.rs`, `scan.rs`, `mingru.rs`, `adam_step.rs`), so any backend opts in with an
//! empty impl and overrides what it does faster (the module doc of `ops` says where each
//! backend's implementation lives).

use burn::tensor::backend::Backend;
use burn::tensor::ops::{FloatTensor, IntTensor};
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};

use super::{adam_step, composed, composed_grid, mingru, scan};
use super::{AdamStep, Kernels, ParticleFrames, PreparedWeights, ProjectionPlan, ReadAhead};

/// The backend operations minflow's networks need beyond burn's (see the module doc for
/// where each implementation lives). ELU is always `alpha = 1`.
pub trait NetOps: Backend {
    /// `elu(x)`, any shape.
    fn elu_forward(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = x.shape();
        let n = shape.num_elements();
        let flat = Tensor::<Self, 1>::from_primitive(TensorPrimitive::Float(Self::float_reshape(
            x,
            [n].into(),
        )));
        let y = burn::tensor::activation::elu(flat, 1.0)
            .into_primitive()
            .tensor();
        Self::float_reshape(y, shape)
    }

    /// `x @ weight + bias`: `x` `[..., in]` (any rank >= 2), `weight` `[in, out]` (burn's
    /// `Linear` layout), `bias` `[out]`; returns `[..., out]`. Composed from matmul and add by
    /// default; the CPU backend calls AVX-512/AVX2 `gemm` (with the bias added in the same
    /// pass, and no copies for reshapes), or streams the weights for a handful of rows (the
    /// inference step).
    fn linear_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        composed::composed_linear::<Self>(x, weight, bias)
    }

    /// `elu(x @ weight + bias)`, shapes as [`NetOps::linear_forward`]. The CPU backend
    /// adds the bias and applies ELU in one pass over the product; by default bias and ELU
    /// are applied to the `[rows, out]` product before it takes `x`'s leading dims back (a
    /// fusing backend then compiles them into one kernel: a reshape between them split it).
    fn linear_elu_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        composed::composed_linear_map::<Self>(x, weight, bias, |y| {
            burn::tensor::activation::elu(y, 1.0)
        })
    }

    /// Gradients of `y = x @ weight (+ bias)` from `grad` = dL/dy `[..., out]`:
    /// `[dx [..., in], dweight [in, out], dbias [out]]`, each computed only when `need[i]`.
    fn linear_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        composed::composed_linear_backward::<Self>(x, weight, grad, need)
    }

    /// `a @ b` for 2-D `a` `[m, k]` and `b` `[k, n]` (either may be a transposed view) ->
    /// `[m, n]`: the products of the composed dense layer and its backward. burn's matmul
    /// by default; the CUDA backend sends large ones to cuBLAS ([`cublas`](super::cublas)).
    fn matmul(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::float_matmul(a, b)
    }

    /// Whether [`NetOps::matmul`] takes a `[m, k] x [k, n]` product with a long reduction
    /// `k` whole and still fills the device (cuBLAS chooses split-K itself), so the composed
    /// backward does not cut the weight gradient into row chunks ([`composed::weight_grad_chunks`]).
    fn splits_reduction(device: &Self::Device, m: usize, k: usize, n: usize) -> bool {
        let _ = (device, m, k, n);
        false
    }

    /// The kernel choices `device` was opened with ([`Kernels`]); the defaults on a backend
    /// with nothing to choose.
    fn kernels(device: &Self::Device) -> Kernels {
        let _ = device;
        Kernels::default()
    }

    /// One Adam step on a parameter (see [`AdamStep`]): returns the new parameter and the
    /// new first and second moments, all shaped like `param`; `m` / `v` None = zero (the
    /// first step); the gradient clipped first when `c.max_norm` is set. Composed from
    /// tensor ops by default (about 13 passes over memory, 7 more to clip); the CPU backend
    /// does it in one pass, in place (two when clipping), CUDA in one kernel (and one sum of
    /// squares when clipping).
    fn adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        m: Option<FloatTensor<Self>>,
        v: Option<FloatTensor<Self>>,
        c: &AdamStep,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        adam_step::composed_adam::<Self>(param, grad, m, v, c)
    }

    /// `x`'s values read back behind the work recorded so far, without waiting for them
    /// ([`read_ahead`](super::read_ahead)): the host may record more work before
    /// [`ReadAhead::wait`], and the device runs it meanwhile. None where a read has nothing to
    /// overlap (the CPU computes eagerly): the caller then reads as usual. CUDA's:
    /// `cuda/read.rs`.
    fn read_ahead(x: FloatTensor<Self>) -> Option<ReadAhead> {
        let _ = x;
        None
    }

    /// The constraint projection of a call's K predicted frames `out` (`[K B, N, 4]`,
    /// physical), predicted from the call's `input` frames (`[B, N, 4]`; None: the momentum
    /// and rebound parts are left out), as `plan` lays it out, on the device in the same
    /// stream as the network (no read-back between them; the rebound part's contacts cross
    /// back after the call): the projected frames and how far each scene's materials moved
    /// (`[B, MATERIALS]`, particle spacings summed over the call's frames), or None where this
    /// backend has no device form (the host then projects, `model::constraints`). CUDA's:
    /// `cuda/projection/op.rs`.
    fn project_constraints(
        out: FloatTensor<Self>,
        input: Option<FloatTensor<Self>>,
        plan: &ProjectionPlan,
    ) -> Option<(FloatTensor<Self>, FloatTensor<Self>)> {
        let _ = (out, input, plan);
        None
    }

    /// Whether [`NetOps::project_constraints`] projects on this backend's device (else the
    /// caller need not lay out a plan).
    fn projects_constraints() -> bool {
        false
    }

    /// Runs one inference step `f` where this backend's kernels start their parallel passes
    /// cheaply: as it is by default; on the CPU, on the rayon pool with a worker kept awake
    /// (`cpu/pool.rs`: 0.75x the full-size grid model's step p50 on 2 cores for running it on
    /// the pool, ~0.9x again for the awake worker).
    fn run_step<R: Send>(f: impl FnOnce() -> R + Send) -> R {
        f()
    }

    /// The grid model's input channels from P2G's splat `[B, n^2, 1 + own + r]` (mass, then
    /// `own` mass-weighted sums, then `r` more): `[B, n^2, 1 + own + 2 + r]` = `m / 4`, the
    /// `own` sums divided by `max(m, 1e-6)`, the two wall masks of node `(i, j)` (x walls by
    /// i, y walls by j: index < 3 or > n - 3), the `r` sums divided by the mass. Composed from
    /// burn's operations by default; one pass on the CPU (equal to the composed result).
    fn grid_channels(splat: FloatTensor<Self>, n: usize, own: usize) -> FloatTensor<Self> {
        composed_grid::composed_grid_channels::<Self>(splat, n, own)
    }

    /// The f32 elements of `x` in row-major order, read where that costs one copy (the CPU:
    /// its buffer, which burn's `into_data` walks element by element when it is shared, as a
    /// parameter's or a cloned tensor's is), or None (the default) for `into_data`
    /// ([`host_values`](super::host_values)).
    fn host_values(x: &FloatTensor<Self>) -> Option<Vec<f32>> {
        let _ = x;
        None
    }

    /// [`NetOps::host_values`] for an integer tensor (as i64), or None (the default) for
    /// `into_data` ([`host_indices`](super::host_indices)).
    fn host_indices(x: &IntTensor<Self>) -> Option<Vec<i64>> {
        let _ = x;
        None
    }

    /// The grid model's sparse stencil (`model::grid::transfer`) computed where reading the
    /// positions `pos` `[B, N, 2]` costs nothing: `index` `[B N 9]` and `weight` `[B, N, 9]`
    /// of each particle on an `n x n` grid, or None (the default) for the composed
    /// computation. The CPU computes it in one pass over the particles (the composed one is
    /// ~25 tensor passes over `[B, N, 2]` and `[B, N, 9]` tensors).
    fn sparse_stencil(
        pos: &FloatTensor<Self>,
        n: usize,
    ) -> Option<(IntTensor<Self>, FloatTensor<Self>)> {
        let _ = (pos, n);
        None
    }

    /// 2x2 average pooling, stride 2, of a channels-last grid: `[B, h, w, C]` ->
    /// `[B, h/2, w/2, C]` (h, w even). One pass on the CPU (inference); composed (and
    /// differentiated by autodiff) elsewhere.
    fn pool2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_grid::composed_pool2::<Self>(x)
    }

    /// Nearest-neighbour 2x upsampling of a channels-last grid: `[B, h, w, C]` ->
    /// `[B, 2h, 2w, C]`. One pass on the CPU (inference); composed elsewhere.
    fn upsample2(x: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_grid::composed_upsample2::<Self>(x)
    }

    /// True where [`NetOps::im2col`] and [`NetOps::col2im`] are single kernels (the CPU and
    /// CUDA backends) and, with [`NetOps::silu`] (a single pass on the CPU, burn's fused
    /// composition on CUDA), get their own autodiff nodes; elsewhere the grid model composes
    /// its convolutions from burn's tensor operations.
    const NATIVE_CONV_OPS: bool = false;

    /// im2col of a same-padding `k x k` convolution: `x` `[B, H, W, C]` -> `[B H W, C k^2]`.
    /// Row `(b H + y) W + x` holds, at column `i k^2 + ky k + kx`, channel `i` of input
    /// position `(y + ky - k/2, x + kx - k/2)` (zero outside the grid): the order of burn's
    /// `Conv2d` weight `[C_out, C_in, k, k]` flattened over its last three dims, so the
    /// product's weight matrix is a transposed view of it (no copy).
    fn im2col(x: FloatTensor<Self>, k: usize) -> FloatTensor<Self> {
        composed_grid::composed_im2col::<Self>(x, k)
    }

    /// A same-padding `k x k` convolution's product from its input, `im2col(x, k) @ matrix +
    /// bias`: `x` `[B, H, W, C]`, `matrix` `[C k^2, C_out]` (a transposed view of burn's
    /// weight, as [`NetOps::im2col`] says), `bias` `[C_out]` -> `[B H W, C_out]`. Composed by
    /// default; the autodiff backend over a backend with native im2col records it as one node
    /// that keeps `x` and recomputes the `k^2`-times larger columns in its backward instead of
    /// keeping them (activation recomputation, Chen et al. 2016, "Training deep nets with
    /// sublinear memory cost"): the kept columns were most of a GPU training step's memory.
    /// That node's product is the inner backend's `im2col_linear`: CUDA with
    /// `MINFLOW_CUDA_CONV=cudnn` runs its 3x3 convolutions through cuDNN (`cuda/net/cudnn.rs`),
    /// with no columns.
    fn im2col_linear(
        x: FloatTensor<Self>,
        matrix: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
        k: usize,
    ) -> FloatTensor<Self> {
        composed_grid::composed_im2col_linear::<Self>(x, matrix, bias, k)
    }

    /// The adjoint of [`NetOps::im2col`] (im2col's gradient): `cols` `[B H W, C k^2]` ->
    /// `[B, H, W, C]` = `shape`.
    fn col2im(cols: FloatTensor<Self>, shape: [usize; 4], k: usize) -> FloatTensor<Self> {
        composed_grid::composed_col2im::<Self>(cols, shape, k)
    }

    /// The gradients of [`NetOps::im2col_linear`] (its autodiff node's backward, backends
    /// with [`NetOps::NATIVE_CONV_OPS`]) from `grad` `[B H W, C_out]`:
    /// `[dx [B, H, W, C], dmatrix [C k^2, C_out], dbias [C_out]]`, each where `need` says. By
    /// default the columns recomputed from `x` (activation recomputation, Chen et al. 2016),
    /// [`NetOps::linear_backward`], and [`NetOps::col2im`] for `dx`; CUDA's 3x3 with
    /// `MINFLOW_CUDA_CONV=cudnn` through cuDNN's data and filter gradients.
    fn im2col_linear_backward(
        x: FloatTensor<Self>,
        matrix: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        k: usize,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        composed_grid::im2col_linear_backward::<Self>(x, matrix, grad, k, need)
    }

    /// The forward of a 3x3 same-padding convolution of the channel concatenation of
    /// `parts`, for inference: `parts` `[B, H, W, C_p]` each (`Σ C_p = C_in`), `weight`
    /// `[C_out, C_in, 3, 3]` (burn's `Conv2d` layout), `bias` `[C_out]` -> `[B, H, W, C_out]`.
    /// None where the backend has no such kernel for these operands, and always on backends
    /// that track gradients; the grid model then runs im2col and a product. The CPU computes
    /// it by Winograd's F(4x4, 3x3) (Lavin & Gray 2016; `cpu/winograd.rs`). With `silu`, the
    /// result is `x sigmoid(x)` of the convolution, applied as it is written (the U-Net's
    /// convolutions are all followed by SiLU but its last). `prepared` is the convolution's
    /// own slot for weights the backend transforms once and reuses while they stay the same
    /// ([`PreparedWeights`]; the CPU keeps its Winograd transform there).
    fn conv3x3_forward(
        parts: &[FloatTensor<Self>],
        weight: &FloatTensor<Self>,
        bias: Option<&FloatTensor<Self>>,
        silu: bool,
        prepared: &PreparedWeights,
    ) -> Option<FloatTensor<Self>> {
        let _ = (parts, weight, bias, silu, prepared);
        None
    }

    /// The minLSTM's step update in one pass where the backend has it: `hfi` `[M, 3H]` (`h~`,
    /// then the forget and input gates' pre-activations `a`, `b`), `h` `[M, H]` ->
    /// `f' h + i' g(h~)` `[M, H]`, `(f', i') = (f, i) / (f + i)` (Feng et al. 2024). None
    /// elsewhere, and always on backends that track gradients: `MinLstm::step` then composes
    /// it from burn's ops. The CPU's is `cpu/mingru.rs`.
    fn minlstm_update(
        hfi: &FloatTensor<Self>,
        h: Option<&FloatTensor<Self>>,
    ) -> Option<FloatTensor<Self>> {
        let _ = (hfi, h);
        None
    }

    /// The minGRU's step update ([`mingru`]): `hg` `[M, 2H]` (`h~`, then the gate's
    /// pre-activation), `h` `[M, H]` -> `(1 - z) h + z g(h~)`, `[M, H]`.
    fn mingru_update(hg: FloatTensor<Self>, h: Option<FloatTensor<Self>>) -> FloatTensor<Self> {
        mingru::composed_mingru_update::<Self>(hg, h)
    }

    /// A grid model's per-particle frames in one operation where the backend has it
    /// ([`ParticleFrames`]: each frame's G2P of its latent field, the head and the
    /// integration): the call's K frames `[K B, N, 4]` (position, velocity; frame k's rows
    /// `k B..`). None elsewhere, and always on backends that track gradients: the model
    /// then runs them as tensor operations (`model::grid::step`). CUDA's: `cuda/net/frames.rs`.
    fn particle_frames(frames: ParticleFrames<Self>) -> Option<FloatTensor<Self>> {
        let _ = frames;
        None
    }

    /// `x sigmoid(x)`, any shape.
    fn silu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_grid::composed_silu::<Self>(x)
    }

    /// SiLU's input gradient from its input `x` and the output gradient (same shape).
    fn silu_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_grid::composed_silu_backward::<Self>(x, grad)
    }

    /// G2P of a sparse stencil, one weighted gather `out_p = sum_k w_pk grid[i_pk]`: `grid`
    /// `[B, n^2, C]`, `index` `[B N 9]` (flat rows `b n^2 + node` of the `[B n^2, C]` grid,
    /// particle-major), `weight` `[B, N, 9]` -> `[B, N, C]`. The stencil's nodes and weights
    /// are constants (no gradient flows to them).
    fn stencil_gather(
        grid: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        composed_grid::composed_gather::<Self>(grid, index, weight)
    }

    /// P2G of a sparse stencil, the adjoint of [`NetOps::stencil_gather`], one weighted
    /// scatter-add `grid[i_pk] += w_pk v_p`: `values` `[B, N, C]` -> `[B, nodes, C]`.
    fn stencil_splat(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        weight: FloatTensor<Self>,
        nodes: usize,
    ) -> FloatTensor<Self> {
        composed_grid::composed_splat::<Self>(values, index, weight, nodes)
    }

    /// True where [`NetOps::elu_mean_forward`] has its own backward (the CPU backend).
    const FUSED_ELU_MEAN: bool = false;

    /// `mean_n elu(x @ w + b)`: the encoder's first layer and mean pooling (used when the
    /// second layer is applied after pooling). `x` `[M, N, F]`, `w` `[F, H]`, `b` `[H]` ->
    /// `[M, H]`. Composed by default; the CPU backend does it in one pass without the
    /// `[M, N, H]` activations and recomputes them in the backward; the autodiff backend over
    /// any other backend takes [`NetOps::linear_elu_mean_forward`]'s node.
    fn elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        composed::composed_elu_mean::<Self>(x, w, b)
    }

    /// Gradients of [`NetOps::elu_mean_forward`] from `grad` `[M, H]`: `[dx, dw, db]`, each
    /// only when `need[i]`. Only called where `FUSED_ELU_MEAN` is true.
    fn elu_mean_backward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        need: [bool; 3],
    ) -> [Option<FloatTensor<Self>>; 3] {
        let _ = (x, w, b, grad, need);
        unreachable!("elu_mean_backward is only called on backends with FUSED_ELU_MEAN")
    }

    /// `mean_n elu(x @ w + b)` keeping the activations (the paper encoder's second layer on
    /// the GPU, and the first where no recomputing kernel exists): `x` `[M, N, H]`, `w`
    /// `[H, W]`, `b` `[W]` -> `[M, W]`. Composed by default; the
    /// autodiff backend records it as one node whose backward forms the pre-activation
    /// gradient `elu'(out) * g / N` in one broadcast element-wise pass (burn's `mean_dim`
    /// backward writes the broadcast `g / N` out first, then ELU's backward reads it back).
    fn linear_elu_mean_forward(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        composed::composed_elu_mean::<Self>(x, w, b)
    }

    /// True where the backend computes on the host (the CPU backend). Then
    /// [`NetOps::recurrence`] is a fused sequential pass, through which minGRU and minLSTM
    /// train in linear space (elsewhere they use the log-space parallel scan, which is what
    /// pays on a GPU), and the grid model's inference takes its host passes (the
    /// per-particle part, the rest-shape features).
    const ON_HOST: bool = false;

    /// True where the grid model applies its particle-grid stencils in their separable dense
    /// form, two batched products per transfer (`model::grid::transfer`), instead of
    /// [`NetOps::stencil_gather`] / [`NetOps::stencil_splat`]. By default off the host (an
    /// accelerator without its own transfer kernels: burn's composed scatter is far slower
    /// there); false on the CPU, which has its own.
    const DENSE_STENCIL: bool = !Self::ON_HOST;

    /// Whether the model takes the dense transfers this run: [`NetOps::DENSE_STENCIL`],
    /// unless a backend lets the environment choose (CUDA: `MINFLOW_CUDA_TRANSFERS=dense`).
    fn dense_stencil() -> bool {
        Self::DENSE_STENCIL
    }

    /// The linear recurrence `h_t = a_t h_{t-1} + b_t` along T (`h_{-1}` = `h0` or 0), with
    /// `a`, `b` positive: `a`, `b` `[B, T, H]`, `h0` `[B, H]` -> `h` `[B, T, H]`. By default the
    /// log-space parallel scan (Heinsen 2023) of `log a`, `log b`.
    fn recurrence(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        scan::log_scan_recurrence::<Self>(a, b, h0)
    }

    /// Gradients of [`NetOps::recurrence`] from `a`, `h0`, its output `h` and `grad` =
    /// dL/dh: `[da, db, dh0]` (`dh0` None without `h0`). By default a reverse loop of tensor
    /// ops: `d_t = grad_t + a_{t+1} d_{t+1}`, `da_t = d_t h_{t-1}`, `db_t = d_t`, `dh0 = a_0 d_0`.
    fn recurrence_backward(
        a: FloatTensor<Self>,
        h0: Option<FloatTensor<Self>>,
        h: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> [Option<FloatTensor<Self>>; 3] {
        scan::composed_recurrence_backward::<Self>(a, h0, h, grad)
    }

    /// The input gradient from the forward output and the output gradient.
    fn elu_backward(out: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        composed::composed_elu_backward::<Self>(out, grad)
    }

    /// The element-wise sum of `tensors` over the ranks of a data-parallel group, one rank per
    /// device of `devices` (this rank's tensors on its own device, any shapes, the same shapes
    /// and order on every rank), through the backend's own collective: every rank calls this
    /// with its tensors and gets the sums back on its device, queued behind its work (on
    /// CUDA NCCL's all-reduce, as cubecl-cuda drives it, over NVLink where the GPUs have it).
    /// `Err` hands the tensors back where the backend has no collective for `devices` (the
    /// default; on CUDA, a list that names a GPU twice), and then on every rank alike: the
    /// caller sums them another way (`train::reduce`'s host rendezvous).
    #[allow(clippy::type_complexity)]
    fn all_reduce_sum(
        tensors: Vec<FloatTensor<Self>>,
        devices: &[Self::Device],
    ) -> Result<Vec<FloatTensor<Self>>, Vec<FloatTensor<Self>>> {
        let _ = devices;
        Err(tensors)
    }
}
