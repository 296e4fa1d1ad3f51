//! minGRU and minLSTM (Feng et al. 2024, "Were RNNs All We Needed?"; reference code
//! BorealisAI/minRNNs, models/minRNNs.py): recurrent layers whose gates depend on the input
//! only, so a whole window trains at once with the log-space parallel scan of Heinsen (2023),
//! while inference steps one frame at a time carrying the hidden state.
//!
//! minGRU:  `h_t = (1 - z_t) h_{t-1} + z_t g(h~_t)`, `z_t = sigmoid(W_z x_t)`, `h~_t = W_h x_t`
//! minLSTM: `h_t = f'_t h_{t-1} + i'_t g(h~_t)`, `f' = f / (f + i)`, `i' = i / (f + i)`,
//!          `f_t = sigmoid(W_f x_t)`, `i_t = sigmoid(W_i x_t)`
//! with `g(x) = x + 0.5` for `x >= 0`, `sigmoid(x)` otherwise (keeps h positive, so the scan
//! can run on `log h`), then `out_t = W_o h_t` (the reference's `to_out`).
//! A missing initial state means `h_0 = 0`. Used by [`crate::model::paper::temporal`].

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::{relu, sigmoid};
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorPrimitive};

use crate::ops::mingru::mingru_update;
use crate::ops::scan::scan_with_state;
use crate::ops::{linear, recurrence, NetOps};

pub use crate::ops::mingru::g;

/// `log g(x)`: `log(x + 0.5)` for `x >= 0`, `-softplus(-x)` otherwise.
pub fn log_g<B: Backend, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    let pos = x.clone().greater_equal_elem(0.0);
    let neg = softplus(-x.clone()).neg();
    neg.mask_where(pos, (relu(x) + 0.5).log())
}

/// Numerically stable `log(1 + exp(x))` (burn's `softplus` overflows for large x): `x` above
/// 20 (where the two differ by under `exp(-20)`), `log1p(exp(x))` below, so the gradient is
/// `sigmoid(x)` everywhere, 1/2 at 0 included (the form `relu(x) + log1p(exp(-|x|))` gives 0
/// there: burn's derivatives of `relu` and `abs` at 0 are both 0).
pub fn softplus<B: Backend, const D: usize>(x: Tensor<B, D>) -> Tensor<B, D> {
    let big = x.clone().greater_elem(20.0);
    x.clone().clamp_max(20.0).exp().log1p().mask_where(big, x)
}

/// minLSTM's normalised gates `(f', i') = (f, i) / (f + i)` with `f = sigmoid(a)`,
/// `i = sigmoid(b)`, from the pre-activations `a`, `b` (any shape, the same).
///
/// Computed as `f' = sigmoid(-d)`, `i' = sigmoid(d)` with
/// `d = log f - log i`, negated: `d = softplus(-a) - softplus(-b)` (the same quantity the
/// log-space scan uses). The direct quotient is the same function but not the same numbers:
/// when both gates are tiny (`a, b < -44`), `(f + i)^2` in its gradient underflows in f32 and
/// training hits a non-finite loss; this form is bounded (`|df'/da| <= 1/4`) everywhere.
pub fn normalized_gates<B: Backend, const D: usize>(
    a: Tensor<B, D>,
    b: Tensor<B, D>,
) -> (Tensor<B, D>, Tensor<B, D>) {
    let d = softplus(a.neg()) - softplus(b.neg());
    (sigmoid(d.clone().neg()), sigmoid(d))
}

/// Last time step of `[B, T, H]` as `[B, H]`.
pub(crate) fn last_step<B: Backend>(x: Tensor<B, 3>) -> Tensor<B, 2> {
    let [b, t, h] = x.dims();
    x.narrow(1, t - 1, 1).reshape([b, h])
}

/// A minGRU layer of width `hidden`.
#[derive(Module, Debug)]
pub struct MinGru<B: Backend> {
    /// `x -> [h~, z pre-activation]`, `[d_in, 2 hidden]`.
    pub to_hidden_and_gate: Linear<B>,
    /// `h -> out`, `[hidden, d_out]`.
    pub to_out: Linear<B>,
    hidden: usize,
}

impl<B: NetOps> MinGru<B> {
    /// New layer `d_in -> hidden -> d_out`.
    pub fn new(d_in: usize, hidden: usize, d_out: usize, device: &B::Device) -> Self {
        Self {
            to_hidden_and_gate: LinearConfig::new(d_in, 2 * hidden).init(device),
            to_out: LinearConfig::new(hidden, d_out).init(device),
            hidden,
        }
    }

    /// Whole window at once: the log-space parallel scan, or on a backend with
    /// [`NetOps::ON_HOST`] (the CPU) the same recurrence in linear space as one
    /// fused pass (`a = 1 - z`, `b = z g(h~)`; equal up to float rounding).
    ///
    /// # Shapes
    /// - `x`: `[B, T, d_in]`, `h0`: `[B, hidden]` (positive) or `None` (zeros)
    /// - returns `([B, T, d_out], h_T: [B, hidden])`
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        h0: Option<Tensor<B, 2>>,
    ) -> (Tensor<B, 3>, Tensor<B, 2>) {
        if !B::ON_HOST {
            return self.forward_log_scan(x, h0);
        }
        let hg = linear(&self.to_hidden_and_gate, x);
        let tilde = g(hg.clone().narrow(2, 0, self.hidden));
        let z = sigmoid(hg.narrow(2, self.hidden, self.hidden));
        let h = recurrence(z.clone().neg().add_scalar(1.0), z * tilde, h0);
        let last = last_step(h.clone());
        (linear(&self.to_out, h), last)
    }

    /// Whole window at once with the log-space parallel scan (Heinsen 2023), on any backend.
    /// Shapes as [`MinGru::forward`].
    pub fn forward_log_scan(
        &self,
        x: Tensor<B, 3>,
        h0: Option<Tensor<B, 2>>,
    ) -> (Tensor<B, 3>, Tensor<B, 2>) {
        let hg = linear(&self.to_hidden_and_gate, x);
        let hidden = hg.clone().narrow(2, 0, self.hidden);
        let gate = hg.narrow(2, self.hidden, self.hidden);
        let log_coeffs = softplus(gate.clone()).neg();
        let log_z = softplus(gate.neg()).neg();
        let log_values = log_z + log_g(hidden);
        let h = scan_with_state(log_coeffs, log_values, h0);
        let last = last_step(h.clone());
        (linear(&self.to_out, h), last)
    }

    /// One step.
    ///
    /// # Shapes
    /// - `x`: `[B, d_in]`, `h`: `[B, hidden]` or `None` -> `([B, d_out], [B, hidden])`
    pub fn step(&self, x: Tensor<B, 2>, h: Option<Tensor<B, 2>>) -> (Tensor<B, 2>, Tensor<B, 2>) {
        let hg = linear(&self.to_hidden_and_gate, x);
        let next = mingru_update(hg, h);
        (linear(&self.to_out, next.clone()), next)
    }
}

/// A minLSTM layer of width `hidden` (with the reference's coefficient normalisation).
#[derive(Module, Debug)]
pub struct MinLstm<B: Backend> {
    /// `x -> [h~, f pre-activation, i pre-activation]`, `[d_in, 3 hidden]`.
    pub to_hidden_and_gates: Linear<B>,
    /// `h -> out`, `[hidden, d_out]`.
    pub to_out: Linear<B>,
    hidden: usize,
}

impl<B: NetOps> MinLstm<B> {
    /// New layer `d_in -> hidden -> d_out`.
    pub fn new(d_in: usize, hidden: usize, d_out: usize, device: &B::Device) -> Self {
        Self {
            to_hidden_and_gates: LinearConfig::new(d_in, 3 * hidden).init(device),
            to_out: LinearConfig::new(hidden, d_out).init(device),
            hidden,
        }
    }

    /// Whole window at once, as [`MinGru::forward`] (linear-space fused pass on the CPU:
    /// `a = f'`, `b = i' g(h~)`). Shapes as [`MinGru::forward`].
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        h0: Option<Tensor<B, 2>>,
    ) -> (Tensor<B, 3>, Tensor<B, 2>) {
        if !B::ON_HOST {
            return self.forward_log_scan(x, h0);
        }
        let hfi = linear(&self.to_hidden_and_gates, x);
        let n = self.hidden;
        let tilde = g(hfi.clone().narrow(2, 0, n));
        let (f, i) = normalized_gates(hfi.clone().narrow(2, n, n), hfi.narrow(2, 2 * n, n));
        let h = recurrence(f, i * tilde, h0);
        let last = last_step(h.clone());
        (linear(&self.to_out, h), last)
    }

    /// Whole window at once with the log-space parallel scan, on any backend. Shapes as
    /// [`MinGru::forward`].
    pub fn forward_log_scan(
        &self,
        x: Tensor<B, 3>,
        h0: Option<Tensor<B, 2>>,
    ) -> (Tensor<B, 3>, Tensor<B, 2>) {
        let hfi = linear(&self.to_hidden_and_gates, x);
        let n = self.hidden;
        let hidden = hfi.clone().narrow(2, 0, n);
        let f = hfi.clone().narrow(2, n, n);
        let i = hfi.narrow(2, 2 * n, n);
        // log f' = -softplus(d), log i' = -softplus(-d), d = softplus(-f) - softplus(-i).
        let diff = softplus(f.neg()) - softplus(i.neg());
        let log_coeffs = softplus(diff.clone()).neg();
        let log_values = softplus(diff.neg()).neg() + log_g(hidden);
        let h = scan_with_state(log_coeffs, log_values, h0);
        let last = last_step(h.clone());
        (linear(&self.to_out, h), last)
    }

    /// One step. Shapes as [`MinGru::step`].
    pub fn step(&self, x: Tensor<B, 2>, h: Option<Tensor<B, 2>>) -> (Tensor<B, 2>, Tensor<B, 2>) {
        let hfi = linear(&self.to_hidden_and_gates, x);
        // One pass where the backend has it (the CPU's inference).
        let fused = B::minlstm_update(
            &hfi.clone().into_primitive().tensor(),
            h.clone().map(|h| h.into_primitive().tensor()).as_ref(),
        );
        if let Some(next) = fused {
            let next = Tensor::<B, 2>::from_primitive(TensorPrimitive::Float(next));
            return (linear(&self.to_out, next.clone()), next);
        }
        let n = self.hidden;
        let tilde = g(hfi.clone().narrow(1, 0, n));
        let (f, i) = normalized_gates(hfi.clone().narrow(1, n, n), hfi.narrow(1, 2 * n, n));
        let next = match h {
            Some(h) => f * h + i * tilde,
            None => i * tilde,
        };
        (linear(&self.to_out, next.clone()), next)
    }
}
