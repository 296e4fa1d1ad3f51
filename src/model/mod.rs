//! `model`: the paper's encoder - temporal core - decoder network (Table 1) with our fixes,
//! generic over the burn backend. Input: T frames of N particles with features
//! (x, y, vx, vy, m), min-max scaled; output: the next frame's scaled (x, y, vx, vy).
//! The decoder predicts a velocity change `dv` (scaled units), integrated in physical units
//! by semi-implicit Euler: `v' = v + dv`, `x' = x + v' dt` (docs/design.md, "Models").
//!
//! Layout: [`encoder`], [`temporal`] (minGRU | minLSTM | GRU | LSTM | MLP stack), [`minrnn`],
//! [`rnn`], [`decoder`]; the grid architecture in [`grid`]; saved models in [`store`]. The
//! networks are generic over a backend with [`NetOps`], whose kernels (fused dense layers,
//! the recurrence scans, im2col, P2G/G2P) live in [`crate::ops`]. Used by `minflow train`,
//! `eval`, `node`.

pub mod decoder;
pub mod encoder;
pub mod grid;
pub mod minrnn;
pub mod rnn;
pub mod store;
pub mod temporal;

pub use decoder::{Decoder, DecoderKind};
pub use encoder::{Encoder, LastActivation, Pooling};
pub use temporal::{Core, CoreKind, LayerState};

use burn::config::Config;
use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

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

/// `data` (row-major, `shape`) as a tensor on `device`, copied as one flat buffer and
/// reshaped there (a view, no copy). burn's CUDA backend (cubecl 0.10) copies a tensor of
/// rank 2 or more as one pitched 2-D copy of `shape[..D-1]` rows of `shape[D-1]` elements;
/// from pageable host memory with rows of 8-20 bytes (particle features) that ran at
/// ~0.2 GB/s on an H200 and was most of a training step (docs/cuda.md). A rank-1 copy is one
/// plain copy.
pub fn upload<B: Backend, const D: usize>(
    data: Vec<f32>,
    shape: [usize; D],
    device: &B::Device,
) -> Tensor<B, D> {
    let n = data.len();
    Tensor::<B, 1>::from_data(TensorData::new(data, [n]), device).reshape(shape)
}

/// The values of `x` in row-major order, read back as one flat buffer (see [`upload`]).
///
/// # Errors
/// [`DownloadError`] carrying the backend's read error.
pub fn download<B: Backend, const D: usize>(x: Tensor<B, D>) -> Result<Vec<f32>, DownloadError> {
    let shape = x.dims().to_vec();
    let n = x.shape().num_elements();
    x.reshape([n])
        .into_data()
        .to_vec()
        .map_err(|e| DownloadError {
            shape,
            source: Box::new(e),
        })
}

/// A tensor could not be read back from its device as `f32` values ([`download`]).
#[derive(Debug, thiserror::Error)]
#[error("reading a {shape:?} tensor back from the device: {source}")]
pub struct DownloadError {
    /// The tensor's shape.
    pub shape: Vec<usize>,
    /// The backend's error.
    #[source]
    pub source: Box<dyn std::error::Error + Send + Sync>,
}

/// Min-max scaling constants as the model uses them: `scaled = (phys - min) / range`.
#[derive(Clone, Debug, PartialEq)]
pub struct Scaling {
    /// Per feature minimum (x, y, vx, vy, m).
    pub min: [f32; 5],
    /// Per feature range (max - min, never 0).
    pub range: [f32; 5],
}

impl Scaling {
    /// Identity scaling.
    pub fn identity() -> Self {
        Self {
            min: [0.0; 5],
            range: [1.0; 5],
        }
    }

    /// `(min, range)` of (x, y, vx, vy) as `[1, 1, 4]` tensors, for `phys = scaled * range + min`.
    pub fn tensors<B: Backend>(&self, device: &B::Device) -> (Tensor<B, 3>, Tensor<B, 3>) {
        let min = Tensor::from_data(TensorData::new(self.min[..4].to_vec(), [1, 1, 4]), device);
        let range = Tensor::from_data(TensorData::new(self.range[..4].to_vec(), [1, 1, 4]), device);
        (min, range)
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
