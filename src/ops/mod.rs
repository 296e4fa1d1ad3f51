//! `ops`: the backend operations minflow's networks need beyond burn's, as one backend
//! extension trait, [`NetOps`]: the dense layer `x @ W + b` (alone or fused with ELU) and its
//! gradients, the products under it, ELU, the paper encoder's dense layer + ELU + mean pooling,
//! the linear recurrence of minGRU / minLSTM and their inference updates, one Adam step, and
//! the grid model's im2col / col2im, SiLU, particle <-> grid stencil transfers, grid channels,
//! 2x2 pooling and upsampling and its inference 3x3 convolution. `model/` builds its networks
//! on these (through the tensor-level functions re-exported here, [`linear`], [`elu`],
//! [`recurrence`], ...), and `train::optimizer` on [`NetOps::adam_step`]. Nothing here imports
//! `model`.
//!
//! Every method has a default composed from burn's tensor operations, so any backend opts in
//! with an empty impl and overrides what it does faster. Where things live:
//!
//! - `mod.rs`: this map, and [`Kernels`], a device's kernel choices; `net_ops.rs`: the trait
//!   ([`NetOps`]): each operation's contract (shapes, what it computes) and default; [`host`],
//!   the CPU backend's product and SiLU as plain-f32 kernels for host passes (the grid model's
//!   CPU inference pass); [`bspline_axis`] and [`stencil_bounds`], a particle's quadratic
//!   B-spline stencil on the host.
//! - [`error`]: [`OpsError`], how a GPU library call fails, and the single place a failed GPU
//!   operation stops the caller (burn's backend API is infallible).
//! - `tensor.rs`: the operations on burn `Tensor`s that `model/` calls.
//! - [`composed`]: the defaults in burn's tensor operations for the dense layer, ELU and the
//!   pooled ELU, with the dense layer's chunked weight gradient; `composed_grid.rs`: those of
//!   im2col, col2im, SiLU, the stencil transfers, the grid channels, pooling and upsampling.
//! - [`mingru`]: the minGRU's activation `g` and its inference update.
//! - [`scan`]: the recurrence in burn's tensor operations (Heinsen's log-space parallel scan,
//!   the default, and its reverse-loop backward).
//! - [`adam_step`]: [`AdamStep`], the scalars of one Adam step, and its composed default.
//! - [`prepared`]: [`PreparedWeights`], a convolution's weights as a backend prepared them for
//!   inference, kept by the module that owns the convolution.
//! - `autodiff.rs`: the impl for `Autodiff<B>`: one graph node per fused forward, whose
//!   backward calls the inner backend's backward operation; `autodiff_grid.rs`: the nodes of
//!   the grid model's operations.
//! - `ndarray.rs`: the impl for `NdArray<f32>` (the CPU), on the kernels of `cpu/` (`mod.rs`:
//!   their shared helpers): `gemm.rs` (dense layers), `activation.rs` (ELU, SiLU),
//!   `elu_mean.rs` (the encoder's first layer and pooling in one pass), `scan.rs` (the
//!   sequential recurrence), `mingru.rs` (the minGRU's and minLSTM's inference updates in one
//!   pass), `adam_pass.rs` (one Adam step), `conv.rs` (im2col, col2im), `winograd.rs` (the
//!   inference forward of the 3x3 convolutions by Winograd F(4x4, 3x3)), `grid.rs` (the grid
//!   channels, 2x2 pooling and 2x upsampling for inference), `transfer.rs` (the stencil, its
//!   gather and scatter-add) and `pool.rs` (a whole inference step on the rayon pool with a
//!   worker kept awake).
//! - [`cublas`]: the choice of the GPU's large-product kernel ([`cublas::GpuGemm`],
//!   `--gpu-gemm`) and its layout logic, always built; with the feature `cuda`, those products
//!   through cuBLAS as custom operations of burn's fusion layer.
//! - `cuda/` (feature `cuda`), the device code by job: `mod.rs` the impl for burn's CUDA
//!   backend (the composed defaults, whose element-wise chains burn's fusion layer compiles
//!   into single kernels, the large products through [`cublas`]); `cuda/net/` the network's
//!   layers (im2col / col2im, cuDNN's 3x3 convolutions and their plans and calls, the
//!   implicit GEMM, the sparse P2G / G2P stencil kernels summing in fixed point, the minRNN
//!   updates, a grid call's per-particle frames, the Adam step); `cuda/projection/` the
//!   constraint projection's parts, each named as its host form in `model/constraints/`; `cuda/device.rs` what the library calls
//!   share (a GPU's context, calls queued on cubecl's device thread); `cuda/read.rs` a tensor
//!   read back without waiting for the work recorded after it ([`read_ahead`]).
//!
//! Two kernel choices belong to the device, as [`Kernels`]: the GPU's product kernel
//! (`--gpu-gemm`) and whether the composed dense-layer backward splits long weight-gradient
//! reductions (`bench train --split-weight-grad`). They are fixed when a command opens the GPU
//! ([`cublas::open`]) and read back through [`NetOps::kernels`] from a tensor's device; the CPU
//! has none to choose.

pub mod adam_step;
mod autodiff;
mod autodiff_grid;
pub mod composed;
mod composed_grid;
pub use composed_grid::pad_hw;
mod cpu;
pub mod cublas;
#[cfg(feature = "cuda")]
mod cuda;
pub mod error;
pub mod host;
pub mod mingru;
mod ndarray;
mod net_ops;
mod particle_frames;
pub mod prepared;
mod projection_plan;
pub mod read_ahead;
pub mod scan;
mod tensor;

pub use adam_step::AdamStep;
pub use error::OpsError;
pub use net_ops::NetOps;
pub use particle_frames::ParticleFrames;
pub use prepared::PreparedWeights;
pub use projection_plan::{
    event_table_len, DeviceCopy, EventStore, Events, ProjectionPlan, TablesLater, BODY_VALUES,
    EVENT_VALUES, MATERIALS, MAX_BODIES, MOMENTUM_AT, REBOUND_AT, SCENE_SOLIDS, SCENE_VALUES,
    SOLIDS_HEAD,
};
pub use read_ahead::ReadAhead;
pub use tensor::{
    elu, gather, grid_channels, host_indices, host_values, im2col, linear, linear_elu,
    linear_elu_mean, linear_elu_mean_pool, pool2, recurrence, silu, splat, upsample2,
};

/// Stencil nodes per particle of [`NetOps::stencil_gather`] and [`NetOps::stencil_splat`]
/// (3 x 3, quadratic B-spline).
pub(crate) const STENCIL_NODES: usize = 9;

pub use cpu::transfer::{bspline_axis, stencil_bounds};

/// The kernel choices of one device (see the module doc): fixed when the device is opened,
/// read by its ops. The default is what every command runs unless a flag says otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Kernels {
    /// The large dense-layer products on a GPU (`--gpu-gemm`).
    pub gemm: cublas::GpuGemm,
    /// Whether the composed dense-layer backward cuts long weight-gradient reductions into
    /// row chunks ([`composed::weight_grad_chunks`]; `bench train --split-weight-grad`).
    pub split_weight_grad: bool,
}

impl Default for Kernels {
    fn default() -> Self {
        Self {
            gemm: cublas::GpuGemm::Tf32,
            split_weight_grad: true,
        }
    }
}
