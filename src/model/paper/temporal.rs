//! The temporal core of the paper's Table 1, row 3: `layers` stacked recurrent layers of
//! width W (minGRU | minLSTM | GRU | LSTM), dropout after each, then an MLP `W -> W` (Linear +
//! ELU) on the last time step. `mlp` replaces the recurrent layers by per-step Linear + ELU
//! layers and is stateless (the paper's MLP baseline). Used by [`crate::model::Model`].

use crate::model::minrnn::{last_step, MinGru, MinLstm};
use crate::model::rnn::{Gru, Lstm, LstmState};
use crate::ops::{linear_elu, NetOps};
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Dropout, DropoutConfig, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

/// Which recurrent core.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum CoreKind {
    /// No recurrence: per-step Linear + ELU layers (the paper's MLP baseline).
    Mlp,
    /// Classical LSTM.
    Lstm,
    /// Classical GRU.
    Gru,
    /// minLSTM (Feng et al. 2024).
    MinLstm,
    /// minGRU (Feng et al. 2024).
    MinGru,
}

impl CoreKind {
    /// All kinds, in the paper's table order.
    pub const ALL: [CoreKind; 5] = [
        CoreKind::Mlp,
        CoreKind::Lstm,
        CoreKind::Gru,
        CoreKind::MinLstm,
        CoreKind::MinGru,
    ];

    /// Command-line name: `mlp`, `lstm`, `gru`, `minlstm`, `mingru`.
    pub fn name(self) -> &'static str {
        match self {
            CoreKind::Mlp => "mlp",
            CoreKind::Lstm => "lstm",
            CoreKind::Gru => "gru",
            CoreKind::MinLstm => "minlstm",
            CoreKind::MinGru => "mingru",
        }
    }

    /// Parses a command-line name.
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

/// One layer of the stack.
// One instance per model: variant sizes do not matter, and burn's derive wants plain fields.
#[allow(clippy::large_enum_variant)]
#[derive(Module, Debug)]
pub enum Layer<B: Backend> {
    /// Linear + ELU per time step.
    Mlp(Linear<B>),
    /// Classical GRU.
    Gru(Gru<B>),
    /// Classical LSTM.
    Lstm(Lstm<B>),
    /// minGRU.
    MinGru(MinGru<B>),
    /// minLSTM.
    MinLstm(MinLstm<B>),
}

/// The state a layer carries between frames.
#[derive(Clone, Debug)]
pub enum LayerState<B: Backend> {
    /// Stateless layer.
    None,
    /// Hidden state `[B, W]` (GRU, minGRU, minLSTM).
    Hidden(Tensor<B, 2>),
    /// LSTM hidden and cell state.
    Lstm(LstmState<B>),
}

/// The core: recurrent layers, dropout, MLP.
#[derive(Module, Debug)]
pub struct Core<B: Backend> {
    /// The stacked layers.
    pub layers: Vec<Layer<B>>,
    /// The MLP `W -> W` on the last step.
    pub mlp: Linear<B>,
    dropout: Dropout,
}

impl<B: NetOps> Core<B> {
    /// A stack of `layers` layers `d_in -> width -> ... -> width`, dropout `p`.
    pub fn new(
        kind: CoreKind,
        d_in: usize,
        width: usize,
        layers: usize,
        p: f64,
        device: &B::Device,
    ) -> Self {
        let layers = (0..layers.max(1))
            .map(|k| {
                let d = if k == 0 { d_in } else { width };
                match kind {
                    CoreKind::Mlp => Layer::Mlp(LinearConfig::new(d, width).init(device)),
                    CoreKind::Gru => Layer::Gru(Gru::new(d, width, device)),
                    CoreKind::Lstm => Layer::Lstm(Lstm::new(d, width, device)),
                    CoreKind::MinGru => Layer::MinGru(MinGru::new(d, width, width, device)),
                    CoreKind::MinLstm => Layer::MinLstm(MinLstm::new(d, width, width, device)),
                }
            })
            .collect();
        Self {
            layers,
            mlp: LinearConfig::new(width, width).init(device),
            dropout: DropoutConfig::new(p).init(),
        }
    }

    /// Initial (empty) state of every layer.
    pub fn init_state(&self) -> Vec<LayerState<B>> {
        vec![LayerState::None; self.layers.len()]
    }

    /// Runs a whole window from `states` (the parallel scan for min-RNNs).
    ///
    /// # Shapes
    /// - `x`: `[B, T, d_in]` -> (`[B, W]` latent of the last step, per-layer states)
    pub fn forward(
        &self,
        x: Tensor<B, 3>,
        states: Vec<LayerState<B>>,
    ) -> (Tensor<B, 2>, Vec<LayerState<B>>) {
        let mut x = x;
        let mut next = Vec::with_capacity(self.layers.len());
        for (layer, state) in self.layers.iter().zip(states) {
            let (out, s) = match (layer, state) {
                (Layer::Mlp(l), _) => (linear_elu(l, x), LayerState::None),
                (Layer::Gru(l), s) => {
                    let (o, h) = l.forward(x, hidden(s));
                    (o, LayerState::Hidden(h))
                }
                (Layer::Lstm(l), s) => {
                    let (o, st) = l.forward(x, lstm(s));
                    (o, LayerState::Lstm(st))
                }
                (Layer::MinGru(l), s) => {
                    let (o, h) = l.forward(x, hidden(s));
                    (o, LayerState::Hidden(h))
                }
                (Layer::MinLstm(l), s) => {
                    let (o, h) = l.forward(x, hidden(s));
                    (o, LayerState::Hidden(h))
                }
            };
            x = self.dropout.forward(out);
            next.push(s);
        }
        (linear_elu(&self.mlp, last_step(x)), next)
    }

    /// One frame (step-by-step inference).
    ///
    /// # Shapes
    /// - `x`: `[B, d_in]` -> (`[B, W]`, per-layer states)
    pub fn step(
        &self,
        x: Tensor<B, 2>,
        states: Vec<LayerState<B>>,
    ) -> (Tensor<B, 2>, Vec<LayerState<B>>) {
        let mut x = x;
        let mut next = Vec::with_capacity(self.layers.len());
        for (layer, state) in self.layers.iter().zip(states) {
            let (out, s) = match (layer, state) {
                (Layer::Mlp(l), _) => (linear_elu(l, x), LayerState::None),
                (Layer::Gru(l), s) => {
                    let h = l.step(x, hidden(s));
                    (h.clone(), LayerState::Hidden(h))
                }
                (Layer::Lstm(l), s) => {
                    let st = l.step(x, lstm(s));
                    (st.h.clone(), LayerState::Lstm(st))
                }
                (Layer::MinGru(l), s) => {
                    let (o, h) = l.step(x, hidden(s));
                    (o, LayerState::Hidden(h))
                }
                (Layer::MinLstm(l), s) => {
                    let (o, h) = l.step(x, hidden(s));
                    (o, LayerState::Hidden(h))
                }
            };
            x = self.dropout.forward(out);
            next.push(s);
        }
        (linear_elu(&self.mlp, x), next)
    }
}

fn hidden<B: Backend>(s: LayerState<B>) -> Option<Tensor<B, 2>> {
    match s {
        LayerState::Hidden(h) => Some(h),
        _ => None,
    }
}

fn lstm<B: Backend>(s: LayerState<B>) -> Option<LstmState<B>> {
    match s {
        LayerState::Lstm(s) => Some(s),
        _ => None,
    }
}
