//! Decoders from the latent `[B, W]` to a per-particle velocity change `[B, N, 2]` in scaled
//! units. `global` is the paper's (Table 1, row 4): one `Linear W -> N x 2`, tied to N and to
//! the particle order. `pointwise` is ours: a small MLP per particle on [its scaled features,
//! the latent], `Linear(5 + W -> H)`, ELU, `Linear(H -> 2)`, for any N and any order (the
//! first Linear is split into a per-particle and a per-frame part, which is exactly equal).
//! Used by [`crate::model::Model`].

use crate::ops::{elu, linear, NetOps};
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

/// Which decoder.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum DecoderKind {
    /// `Linear W -> N x 2` (the paper's; fixed N and particle order).
    Global,
    /// Per-particle MLP on [features, latent] (any N, any order).
    Pointwise,
}

/// The per-particle MLP of the pointwise decoder.
#[derive(Module, Debug)]
pub struct PointwiseMlp<B: Backend> {
    /// `features -> H` (with bias).
    pub features: Linear<B>,
    /// `W -> H` (no bias), computed once per frame.
    pub latent: Linear<B>,
    /// `H -> 2`.
    pub out: Linear<B>,
}

/// The decoder.
// One instance per model: variant sizes do not matter, and burn's derive wants plain fields.
#[allow(clippy::large_enum_variant)]
#[derive(Module, Debug)]
pub enum Decoder<B: Backend> {
    /// `Linear W -> N x 2`.
    Global(Linear<B>),
    /// Per-particle MLP.
    Pointwise(PointwiseMlp<B>),
}

impl<B: NetOps> Decoder<B> {
    /// New decoder for `particles` particles (global) or any count (pointwise); with
    /// `zero_init` the output layer starts at zero (dv = 0).
    pub fn new(
        kind: DecoderKind,
        width: usize,
        features: usize,
        particles: usize,
        hidden: usize,
        zero_init: bool,
        device: &B::Device,
    ) -> Self {
        let last = |d_in: usize, d_out: usize| {
            let config = LinearConfig::new(d_in, d_out);
            if zero_init {
                config.with_initializer(Initializer::Zeros).init(device)
            } else {
                config.init(device)
            }
        };
        match kind {
            DecoderKind::Global => Decoder::Global(last(width, particles * 2)),
            DecoderKind::Pointwise => Decoder::Pointwise(PointwiseMlp {
                features: LinearConfig::new(features, hidden).init(device),
                latent: LinearConfig::new(width, hidden)
                    .with_bias(false)
                    .init(device),
                out: last(hidden, 2),
            }),
        }
    }

    /// Decodes.
    ///
    /// # Shapes
    /// - `latent`: `[B, W]`, `features`: `[B, N, features]` (scaled last frame)
    /// - returns `dv`: `[B, N, 2]` (scaled units)
    pub fn forward(&self, latent: Tensor<B, 2>, features: Tensor<B, 3>) -> Tensor<B, 3> {
        let [b, n, _] = features.dims();
        match self {
            Decoder::Global(l) => linear(l, latent).reshape([b, n, 2]),
            Decoder::Pointwise(mlp) => {
                let per_frame = linear(&mlp.latent, latent);
                let [_, hidden] = per_frame.dims();
                let per_frame = per_frame.reshape([b, 1, hidden]);
                let h = elu(linear(&mlp.features, features) + per_frame);
                linear(&mlp.out, h)
            }
        }
    }
}
