//! `model`: minflow's networks, generic over the burn backend, as two sibling
//! architectures over shared recurrent cells:
//!
//! - [`paper`]: the paper's encoder - temporal core - decoder (Table 1), `--arch paper`;
//! - [`grid`]: P2G -> U-Net -> G2P with a per-particle memory, `--arch grid` (the default);
//! - [`minrnn`] (minGRU, minLSTM) and [`rnn`] (GRU, LSTM): the cells both use;
//! - [`store`]: saved models and [`store::Surrogate`], the inference API of `eval`, `node`
//!   and `report`;
//! - [`constraints`]: the projection of every predicted frame onto the material's
//!   constraints (rope, shape matching, liquid density, walls, contact), of either
//!   architecture, and its fit (`minflow constraints fit`);
//! - [`roofline`]: a grid call's time and needs by part (`bench rollout --stages`);
//! - [`average`]: weight averaging of networks of one run (`minflow average`).
//!
//! Here: the host <-> device copies ([`upload`], [`download`]) and the min-max [`Scaling`]
//! constants. The networks' kernels (fused dense layers, the recurrence scans, im2col,
//! P2G/G2P) live in [`crate::ops`] behind [`crate::ops::NetOps`].

pub mod average;
pub mod constraints;
pub mod grid;
pub mod minrnn;
pub mod paper;
pub mod rnn;
pub mod roofline;
pub mod store;

pub use paper::{
    Core, CoreKind, Decoder, DecoderKind, Encoder, LastActivation, LayerState, Model, ModelConfig,
    Pooling,
};

use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

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
        .into_vec()
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
