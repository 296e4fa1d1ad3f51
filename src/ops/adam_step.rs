//! One Adam step as a backend operation ([`NetOps::adam_step`], the step of `train::optimizer`'s
//! optimizer): [`AdamStep`], its scalars, and the default in burn's tensor operations. The
//! CPU does it in one pass, in place (`cpu/adam_pass.rs`).
//!
//! [`NetOps::adam_step`]: super::NetOps::adam_step

use burn::grad_clipping::GradientClipping;
use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorMetadata, TensorPrimitive};

/// The scalars of one Adam step (Kingma & Ba 2015, Algorithm 1; epsilon added to
/// `sqrt(v) * sqrt(1 - b2^t)` as in PyTorch and burn): learning rate, betas, epsilon, the
/// step number `t` (1 for the first step) and the gradient's norm clipping.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamStep {
    /// Learning rate.
    pub lr: f32,
    /// First-moment decay.
    pub beta_1: f32,
    /// Second-moment decay.
    pub beta_2: f32,
    /// Denominator epsilon.
    pub epsilon: f32,
    /// Step number, from 1.
    pub time: usize,
    /// The gradient clipped to this L2 norm first (burn's `GradientClipping::Norm`, over the
    /// parameter tensor: `g * min(1, max_norm / (|g| + f32::MIN_POSITIVE))`); None: not
    /// clipped.
    pub max_norm: Option<f32>,
}

impl AdamStep {
    /// (`sqrt(1 - b2^t)`, `sqrt(1 - b2^t) / (1 - b1^t)`): burn's bias corrections.
    pub fn corrections(&self) -> (f32, f32) {
        let t = self.time as i32;
        let bc2 = (1.0 - self.beta_2.powi(t)).sqrt();
        (bc2, bc2 / (1.0 - self.beta_1.powi(t)))
    }
}

/// [`NetOps::adam_step`](super::NetOps::adam_step) with burn's tensor ops (the same arithmetic
/// as `burn::optim::Adam` behind burn's `GradientClipping::Norm`).
pub(crate) fn composed_adam<B: Backend>(
    param: FloatTensor<B>,
    grad: FloatTensor<B>,
    m: Option<FloatTensor<B>>,
    v: Option<FloatTensor<B>>,
    c: &AdamStep,
) -> (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>) {
    let t = |p| Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(p));
    let shape = param.shape();
    let n = shape.num_elements();
    let flat = |p| t(B::float_reshape(p, [n].into()));
    let (param, mut grad) = (flat(param), flat(grad));
    if let Some(norm) = c.max_norm {
        grad = GradientClipping::Norm(norm).clip_gradient(grad);
    }
    let m1 = grad.clone().mul_scalar(1.0 - c.beta_1);
    let m2 = grad.square().mul_scalar(1.0 - c.beta_2);
    let m1 = match m {
        Some(m) => flat(m).mul_scalar(c.beta_1).add(m1),
        None => m1,
    };
    let m2 = match v {
        Some(v) => flat(v).mul_scalar(c.beta_2).add(m2),
        None => m2,
    };
    let (bc2, factor) = c.corrections();
    let update = m1
        .clone()
        .mul_scalar(factor)
        .div(m2.clone().sqrt().add_scalar(c.epsilon * bc2));
    let param = param - update.mul_scalar(c.lr);
    let back = |x: Tensor<B, 1>| B::float_reshape(x.into_primitive().tensor(), shape.clone());
    (back(param), back(m1), back(m2))
}
