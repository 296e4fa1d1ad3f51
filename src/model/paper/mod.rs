//! `--arch paper`: the paper's encoder - temporal core - decoder network (Table 1) with our
//! fixes, generic over the burn backend. Input: T frames of N particles with features
//! (x, y, vx, vy, m), min-max scaled; output: the next frame's scaled (x, y, vx, vy).
//! The decoder predicts a velocity change `dv` (scaled units), integrated in physical units
//! by semi-implicit Euler: `v' = v + dv`, `x' = x + v' dt` (docs/design.md, "Models").
//!
//! Layout: [`encoder`], [`temporal`] (minGRU | minLSTM | GRU | LSTM | MLP stack over the
//! cells of [`crate::model::minrnn`] and [`crate::model::rnn`]), [`decoder`]. Trained by
//! [`crate::train::paper`]; served by [`crate::model::store::Surrogate`].

pub mod decoder;
pub mod encoder;
pub mod temporal;

pub use decoder::{Decoder, DecoderKind};
pub use encoder::{Encoder, LastActivation, Pooling};
pub use temporal::{Core, CoreKind, LayerState};

use burn::config::Config;
use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use super::Scaling;
use crate::ops::NetOps;

/// Every width, depth, pooling and dropout of the network; saved with each checkpoint.
#[derive(Config, Debug)]
pub struct ModelConfig {
    /// Recurrent core.
    pub core: CoreKind,
    /// Particle count N (fixes the global decoder's width).
    pub particles: usize,
    /// Input window T (frames per sample).
    #[config(default = 2)]
    pub window: usize,
    /// Features per particle (x, y, vx, vy, m).
    #[config(default = 5)]
    pub features: usize,
    /// Encoder hidden width.
    #[config(default = 256)]
    pub encoder_hidden: usize,
    /// Latent width W (encoder output, core width).
    #[config(default = 1250)]
    pub width: usize,
    /// Activation after the encoder's last Linear.
    #[config(default = "LastActivation::Elu")]
    pub encoder_last_activation: LastActivation,
    /// Pooling over particles.
    #[config(default = "Pooling::Mean")]
    pub pooling: Pooling,
    /// Recurrent layers.
    #[config(default = 2)]
    pub layers: usize,
    /// Dropout after each recurrent layer.
    #[config(default = 0.1)]
    pub dropout: f64,
    /// Decoder.
    #[config(default = "DecoderKind::Global")]
    pub decoder: DecoderKind,
    /// Pointwise decoder hidden width.
    #[config(default = 128)]
    pub decoder_hidden: usize,
    /// Start the decoder's output layer at zero, so an untrained model predicts dv = 0 (the
    /// constant-velocity baseline) and training starts from there instead of from random
    /// velocity changes (zero-initialised last layers as in Goyal et al. 2017, "Accurate,
    /// Large Minibatch SGD", section 5.1, for residual branches).
    #[config(default = false)]
    pub decoder_zero_init: bool,
}

impl ModelConfig {
    /// Builds the network with fresh weights.
    pub fn init<B: NetOps>(&self, device: &B::Device) -> Model<B> {
        let encoder = Encoder::new(
            self.features,
            self.encoder_hidden,
            self.width,
            self.encoder_last_activation,
            self.pooling,
            device,
        );
        let d_in = encoder.out_width(self.width);
        Model {
            encoder,
            core: Core::new(
                self.core,
                d_in,
                self.width,
                self.layers,
                self.dropout,
                device,
            ),
            decoder: Decoder::new(
                self.decoder,
                self.width,
                self.features,
                self.particles,
                self.decoder_hidden,
                self.decoder_zero_init,
                device,
            ),
        }
    }
}

/// The network.
#[derive(Module, Debug)]
pub struct Model<B: Backend> {
    /// Pointwise encoder + pooling.
    pub encoder: Encoder<B>,
    /// Temporal core.
    pub core: Core<B>,
    /// Decoder to `dv`.
    pub decoder: Decoder<B>,
}

impl<B: NetOps> Model<B> {
    /// Encodes each frame of a window.
    ///
    /// # Shapes
    /// - `inputs`: `[B, T, N, F]` -> `[B, T, W']`
    pub fn encode(&self, inputs: Tensor<B, 4>) -> Tensor<B, 3> {
        let [b, t, n, f] = inputs.dims();
        let z = self.encoder.forward(inputs.reshape([b * t, n, f]));
        let [_, w] = z.dims();
        z.reshape([b, t, w])
    }

    /// Predicts the next frame from a window (training; the core scans the whole window
    /// from an empty state).
    ///
    /// # Shapes
    /// - `inputs`: `[B, T, N, 5]` scaled, `dt`: `[B]` time units -> `[B, N, 4]` scaled
    pub fn forward(
        &self,
        inputs: Tensor<B, 4>,
        dt: Tensor<B, 1>,
        scaling: &Scaling,
    ) -> Tensor<B, 3> {
        let [b, t, n, f] = inputs.dims();
        let latents = self.encode(inputs.clone());
        let (latent, _) = self.core.forward(latents, self.core.init_state());
        let last = inputs.narrow(1, t - 1, 1).reshape([b, n, f]);
        self.decode(latent, last, dt, scaling)
    }

    /// Decodes a latent and integrates: `v' = v + dv`, `x' = x + v' dt` in physical units.
    ///
    /// # Shapes
    /// - `latent`: `[B, W]`, `last`: `[B, N, 5]` scaled, `dt`: `[B]` -> `[B, N, 4]` scaled
    pub fn decode(
        &self,
        latent: Tensor<B, 2>,
        last: Tensor<B, 3>,
        dt: Tensor<B, 1>,
        scaling: &Scaling,
    ) -> Tensor<B, 3> {
        let [b, _, _] = last.dims();
        let dv = self.decoder.forward(latent, last.clone()); // [b, n, 2] scaled
        let (min, range) = scaling.tensors::<B>(&last.device());
        let phys = last.narrow(2, 0, 4) * range.clone() + min.clone(); // [b, n, 4]
        let x = phys.clone().narrow(2, 0, 2);
        let v = phys.narrow(2, 2, 2);
        let v_range = range.clone().narrow(2, 2, 2);
        let v_next = v + dv * v_range;
        let x_next = x + v_next.clone() * dt.reshape([b, 1, 1]);
        (Tensor::cat(vec![x_next, v_next], 2) - min) / range
    }

    /// One frame of step-by-step inference from `state` (see [`Model::forward`] for units).
    ///
    /// # Shapes
    /// - `frame`: `[B, N, 5]` scaled, `dt`: `[B]` -> (`[B, N, 4]` scaled, new state)
    pub fn step(
        &self,
        frame: Tensor<B, 3>,
        dt: Tensor<B, 1>,
        state: Vec<LayerState<B>>,
        scaling: &Scaling,
    ) -> (Tensor<B, 3>, Vec<LayerState<B>>) {
        let latent = self.encoder.forward(frame.clone());
        let (latent, state) = self.core.step(latent, state);
        (self.decode(latent, frame, dt, scaling), state)
    }
}
