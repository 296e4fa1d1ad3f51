//! The linear recurrence `h_t = a_t h_{t-1} + b_t` (minGRU's and minLSTM's hidden state) in
//! burn's tensor operations: the log-space parallel scan of Heinsen (2023), which is
//! [`NetOps::recurrence`]'s default and how minGRU and minLSTM train on a GPU, and the
//! reverse loop that is [`NetOps::recurrence_backward`]'s default. The CPU runs the
//! recurrence as one sequential pass instead (`cpu/scan.rs`).
//!
//! [`NetOps::recurrence`]: super::NetOps::recurrence
//! [`NetOps::recurrence_backward`]: super::NetOps::recurrence_backward

use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;
use burn::tensor::{Tensor, TensorPrimitive};

/// `log(exp(a) + exp(b))`, stable.
fn log_add_exp<B: Backend, const D: usize>(a: Tensor<B, D>, b: Tensor<B, D>) -> Tensor<B, D> {
    let hi = a.clone().max_pair(b.clone());
    let diff = (a - b).abs().neg();
    hi + diff.exp().log1p()
}

/// Stand-in for `log 0` in padded scan positions (finite, so gradients stay finite).
const LOG_ZERO: f32 = -1e30;

/// The log-space scan for `h_t = a_t h_{t-1} + b_t` (`h_0 = 0`): returns `log h_t`.
///
/// Heinsen (2023) writes it as `log h_t = a*_t + logcumsumexp(log b - a*)_t` with
/// `a*_t = sum_{s <= t} log a_s`; in f32 that subtracts offsets that grow with t (|a*| ~ 180
/// after 256 steps, losing ~1e-5). Here the same prefix is computed by a Hillis-Steele scan
/// over pairs `(log a, log b)` with the associative operator
/// `(a1, b1) o (a2, b2) = (a1 + a2, logaddexp(b1 + a2, b2))`: `ceil(log2 T)` parallel passes,
/// no cancellation, and the result agrees with the step-by-step recurrence to ~1e-6.
///
/// # Shapes
/// - `log_coeffs` (log a), `log_values` (log b): `[B, T, H]` -> `log h`: `[B, T, H]`
pub fn scan_log<B: Backend>(log_coeffs: Tensor<B, 3>, log_values: Tensor<B, 3>) -> Tensor<B, 3> {
    let [b, t, h] = log_values.dims();
    let device = log_values.device();
    let (mut la, mut lb) = (log_coeffs, log_values);
    let mut shift = 1;
    while shift < t {
        // The element `shift` steps back, or the identity (a = 1, b = 0) before the start.
        let prev_a = Tensor::cat(
            vec![
                Tensor::zeros([b, shift, h], &device),
                la.clone().narrow(1, 0, t - shift),
            ],
            1,
        );
        let prev_b = Tensor::cat(
            vec![
                Tensor::full([b, shift, h], LOG_ZERO, &device),
                lb.clone().narrow(1, 0, t - shift),
            ],
            1,
        );
        lb = log_add_exp(prev_b + la.clone(), lb);
        la = prev_a + la;
        shift *= 2;
    }
    lb
}

/// Prepends `log h_0` (a value with coefficient 1) and scans; returns the `T` new steps.
pub(crate) fn scan_with_state<B: Backend>(
    log_coeffs: Tensor<B, 3>,
    log_values: Tensor<B, 3>,
    h0: Option<Tensor<B, 2>>,
) -> Tensor<B, 3> {
    let Some(h0) = h0 else {
        return scan_log(log_coeffs, log_values).exp();
    };
    let [b, t, h] = log_values.dims();
    let log_h0 = h0.log().reshape([b, 1, h]);
    let zeros = Tensor::zeros([b, 1, h], &log_coeffs.device());
    let coeffs = Tensor::cat(vec![zeros, log_coeffs], 1);
    let values = Tensor::cat(vec![log_h0, log_values], 1);
    scan_log(coeffs, values).narrow(1, 1, t).exp()
}

/// [`NetOps::recurrence`](super::NetOps::recurrence)'s default: `exp` of the log-space scan of `log a`, `log b`.
pub(crate) fn log_scan_recurrence<B: Backend>(
    a: FloatTensor<B>,
    b: FloatTensor<B>,
    h0: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    let t3 = |p| Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(p));
    let h0 = h0.map(|p| Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(p)));
    scan_with_state(t3(a).log(), t3(b).log(), h0)
        .into_primitive()
        .tensor()
}

/// [`NetOps::recurrence_backward`](super::NetOps::recurrence_backward)'s default, with tensor ops.
pub(crate) fn composed_recurrence_backward<B: Backend>(
    a: FloatTensor<B>,
    h0: Option<FloatTensor<B>>,
    h: FloatTensor<B>,
    grad: FloatTensor<B>,
) -> [Option<FloatTensor<B>>; 3] {
    let t3 = |p| Tensor::<B, 3>::from_primitive(TensorPrimitive::Float(p));
    let (a, h, grad) = (t3(a), t3(h), t3(grad));
    let h0 = h0.map(|p| Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(p)));
    let [batch, t, w] = a.dims();
    let step = |x: &Tensor<B, 3>, s: usize| x.clone().narrow(1, s, 1).reshape([batch, w]);
    let mut carry = Tensor::<B, 2>::zeros([batch, w], &a.device());
    let (mut da, mut db) = (Vec::with_capacity(t), Vec::with_capacity(t));
    for s in (0..t).rev() {
        let d = step(&grad, s) + carry;
        let prev = if s > 0 {
            step(&h, s - 1)
        } else {
            h0.clone()
                .unwrap_or_else(|| Tensor::zeros([batch, w], &a.device()))
        };
        da.push((d.clone() * prev).reshape([batch, 1, w]));
        carry = step(&a, s) * d.clone();
        db.push(d.reshape([batch, 1, w]));
    }
    da.reverse();
    db.reverse();
    let prim = |x: Tensor<B, 3>| Some(x.into_primitive().tensor());
    [
        prim(Tensor::cat(da, 1)),
        prim(Tensor::cat(db, 1)),
        h0.map(|_| carry.into_primitive().tensor()),
    ]
}
