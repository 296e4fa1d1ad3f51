//! The network's layers on burn's CUDA backend (feature `cuda`), each a custom operation of
//! burn's fusion layer: `conv.rs` im2col and col2im, `cudnn.rs` the 3x3 convolutions through
//! cuDNN (its plans in `cudnn_plan.rs`, its handles and calls in `cudnn_calls.rs`),
//! `implicit_conv.rs` burn-cubecl's implicit GEMM, `stencil.rs` the sparse P2G / G2P (its
//! kernels in `stencil_kernels.rs`), `minrnn.rs` the minGRU's and minLSTM's inference
//! updates, `frames.rs` a grid call's per-particle frames (G2P, head, integration) in one
//! kernel (in `frames_kernels.rs`), `adam.rs` the Adam step. Their host forms: `ops/cpu/`.

pub(in crate::ops) mod adam;
pub(in crate::ops) mod conv;
pub(in crate::ops) mod cudnn;
pub(in crate::ops) mod cudnn_calls;
pub(in crate::ops) mod cudnn_plan;
pub(in crate::ops) mod frames;
pub(in crate::ops) mod frames_kernels;
pub(in crate::ops) mod implicit_conv;
pub(in crate::ops) mod minrnn;
pub(in crate::ops) mod stencil;
pub(in crate::ops) mod stencil_kernels;
