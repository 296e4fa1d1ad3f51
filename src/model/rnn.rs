//! The classical recurrent cells the paper compares against (its appendix C, Fig. 6), with
//! the input projections of all time steps fused into one matrix product and the recurrence
//! stepped in time:
//!
//! GRU (Cho et al. 2014): `z = sigmoid(W_z x + U_z h)`, `r = sigmoid(W_r x + U_r h)`,
//! `h~ = tanh(W_h x + U_h (r * h))`, `h' = (1 - z) h + z h~`.
//! LSTM (Hochreiter & Schmidhuber 1997): `[i, f, o, c~] = W x + U h`,
//! `c' = sigmoid(f) c + sigmoid(i) tanh(c~)`, `h' = sigmoid(o) tanh(c')`.
//! The W projections carry the biases; U has none. A missing state means zeros.
//! Used by [`crate::model::paper::temporal`].

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::{sigmoid, tanh};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use crate::ops::{linear, NetOps};

/// A GRU layer of width `hidden`.
#[derive(Module, Debug)]
pub struct Gru<B: Backend> {
    /// `x -> [z, r, h~]` pre-activations, `[d_in, 3 hidden]`, with bias.
    pub input: Linear<B>,
    /// `h -> [z, r]`, `[hidden, 2 hidden]`, no bias.
    pub recurrent_gates: Linear<B>,
    /// `r * h -> h~`, `[hidden, hidden]`, no bias.
    pub recurrent_candidate: Linear<B>,
    hidden: usize,
}

impl<B: NetOps> Gru<B> {
    /// New layer `d_in -> hidden`.
    pub fn new(d_in: usize, hidden: usize, device: &B::Device) -> Self {
        let no_bias = |i, o| LinearConfig::new(i, o).with_bias(false).init(device);
        Self {
            input: LinearConfig::new(d_in, 3 * hidden).init(device),
            recurrent_gates: no_bias(hidden, 2 * hidden),
            recurrent_candidate: no_bias(hidden, hidden),
            hidden,
        }
    }

    /// One step from pre-computed input projections `xp` (`[B, 3 hidden]`).
    fn cell(&self, xp: Tensor<B, 2>, h: Tensor<B, 2>) -> Tensor<B, 2> {
        let n = self.hidden;
        let gates = linear(&self.recurrent_gates, h.clone());
        let z = sigmoid(xp.clone().narrow(1, 0, n) + gates.clone().narrow(1, 0, n));
        let r = sigmoid(xp.clone().narrow(1, n, n) + gates.narrow(1, n, n));
        let cand = tanh(xp.narrow(1, 2 * n, n) + linear(&self.recurrent_candidate, r * h.clone()));
        (z.clone().neg() + 1.0) * h + z * cand
    }

    /// Runs over a window.
    ///
    /// # Shapes
    /// - `x`: `[B, T, d_in]`, `h0`: `[B, hidden]` or `None` -> `([B, T, hidden], h_T)`
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        h0: Option<Tensor<B, 2>>,
    ) -> (Tensor<B, 3>, Tensor<B, 2>) {
        let [b, t, _] = x.dims();
        let xp = linear(&self.input, x); // [b, t, 3h]
        let mut h = h0.unwrap_or_else(|| Tensor::zeros([b, self.hidden], &xp.device()));
        let mut outs = Vec::with_capacity(t);
        for k in 0..t {
            let xk = xp.clone().narrow(1, k, 1).reshape([b, 3 * self.hidden]);
            h = self.cell(xk, h);
            outs.push(h.clone());
        }
        (Tensor::stack(outs, 1), h)
    }

    /// One step: `x`: `[B, d_in]` -> `h'`: `[B, hidden]`.
    pub fn step(&self, x: Tensor<B, 2>, h: Option<Tensor<B, 2>>) -> Tensor<B, 2> {
        let [b, _] = x.dims();
        let xp = linear(&self.input, x);
        let h = h.unwrap_or_else(|| Tensor::zeros([b, self.hidden], &xp.device()));
        self.cell(xp, h)
    }
}

/// LSTM state: hidden and cell, each `[B, hidden]`.
#[derive(Clone, Debug)]
pub struct LstmState<B: Backend> {
    /// Hidden state h.
    pub h: Tensor<B, 2>,
    /// Cell state c.
    pub c: Tensor<B, 2>,
}

/// An LSTM layer of width `hidden`.
#[derive(Module, Debug)]
pub struct Lstm<B: Backend> {
    /// `x -> [i, f, o, c~]` pre-activations, `[d_in, 4 hidden]`, with bias.
    pub input: Linear<B>,
    /// `h -> [i, f, o, c~]`, `[hidden, 4 hidden]`, no bias.
    pub recurrent: Linear<B>,
    hidden: usize,
}

impl<B: NetOps> Lstm<B> {
    /// New layer `d_in -> hidden`.
    pub fn new(d_in: usize, hidden: usize, device: &B::Device) -> Self {
        Self {
            input: LinearConfig::new(d_in, 4 * hidden).init(device),
            recurrent: LinearConfig::new(hidden, 4 * hidden)
                .with_bias(false)
                .init(device),
            hidden,
        }
    }

    fn cell(&self, xp: Tensor<B, 2>, s: LstmState<B>) -> LstmState<B> {
        let n = self.hidden;
        let pre = xp + linear(&self.recurrent, s.h);
        let i = sigmoid(pre.clone().narrow(1, 0, n));
        let f = sigmoid(pre.clone().narrow(1, n, n));
        let o = sigmoid(pre.clone().narrow(1, 2 * n, n));
        let cand = tanh(pre.narrow(1, 3 * n, n));
        let c = f * s.c + i * cand;
        LstmState {
            h: o * tanh(c.clone()),
            c,
        }
    }

    fn zeros(&self, b: usize, device: &B::Device) -> LstmState<B> {
        LstmState {
            h: Tensor::zeros([b, self.hidden], device),
            c: Tensor::zeros([b, self.hidden], device),
        }
    }

    /// Runs over a window.
    ///
    /// # Shapes
    /// - `x`: `[B, T, d_in]` -> `([B, T, hidden], state after the last step)`
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        s0: Option<LstmState<B>>,
    ) -> (Tensor<B, 3>, LstmState<B>) {
        let [b, t, _] = x.dims();
        let xp = linear(&self.input, x); // [b, t, 4h]
        let mut s = s0.unwrap_or_else(|| self.zeros(b, &xp.device()));
        let mut outs = Vec::with_capacity(t);
        for k in 0..t {
            let xk = xp.clone().narrow(1, k, 1).reshape([b, 4 * self.hidden]);
            s = self.cell(xk, s);
            outs.push(s.h.clone());
        }
        (Tensor::stack(outs, 1), s)
    }

    /// One step: `x`: `[B, d_in]`.
    pub fn step(&self, x: Tensor<B, 2>, s: Option<LstmState<B>>) -> LstmState<B> {
        let [b, _] = x.dims();
        let xp = linear(&self.input, x);
        let s = s.unwrap_or_else(|| self.zeros(b, &xp.device()));
        self.cell(xp, s)
    }
}
