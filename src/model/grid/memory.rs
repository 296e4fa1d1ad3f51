//! Lagrangian memory of the grid architecture: one hidden state per particle, carried with
//! the material as MPM carries a deformation gradient per particle. The cells are the paper
//! model's ([`MinGru`], [`MinLstm`] of Feng et al. 2024, "Were RNNs all we needed?",
//! arXiv 2410.01201; classical [`Gru`], [`Lstm`]) applied to particles as batch rows: the
//! input `u_i` of particle i is its own features and the grid features gathered at its
//! position, so a minGRU/minLSTM's gates never read `h` and a window of known inputs is one
//! parallel scan ([`MinGru::forward`]) while inference steps.

use burn::config::Config;
use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use crate::model::minrnn::{MinGru, MinLstm};
use crate::model::rnn::{Gru, Lstm, LstmState};
use crate::ops::NetOps;

/// Which per-particle memory.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum MemoryKind {
    /// Stateless (the reference).
    None,
    /// minGRU.
    MinGru,
    /// minLSTM.
    MinLstm,
    /// Classical GRU.
    Gru,
    /// Classical LSTM.
    Lstm,
}

impl MemoryKind {
    /// Every kind.
    pub const ALL: [MemoryKind; 5] = [
        MemoryKind::None,
        MemoryKind::MinGru,
        MemoryKind::MinLstm,
        MemoryKind::Gru,
        MemoryKind::Lstm,
    ];

    /// Command-line name: `none`, `mingru`, `minlstm`, `gru`, `lstm`.
    pub fn name(self) -> &'static str {
        match self {
            MemoryKind::None => "none",
            MemoryKind::MinGru => "mingru",
            MemoryKind::MinLstm => "minlstm",
            MemoryKind::Gru => "gru",
            MemoryKind::Lstm => "lstm",
        }
    }

    /// The kind named `name`.
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

/// Hidden state of every particle of a batch (`[B N, H]` rows).
#[derive(Clone, Debug)]
pub enum MemoryState<B: Backend> {
    /// Stateless, or nothing seen yet.
    Empty,
    /// minGRU / minLSTM / GRU hidden state.
    Hidden(Tensor<B, 2>),
    /// LSTM hidden and cell state.
    Lstm(LstmState<B>),
}

impl<B: Backend> MemoryState<B> {
    /// The same state cut from the autodiff graph (push-forward training carries it on
    /// without a gradient through the calls that made it).
    pub fn detach(self) -> Self {
        match self {
            MemoryState::Empty => MemoryState::Empty,
            MemoryState::Hidden(h) => MemoryState::Hidden(h.detach()),
            MemoryState::Lstm(s) => MemoryState::Lstm(LstmState {
                h: s.h.detach(),
                c: s.c.detach(),
            }),
        }
    }

    /// Rows (particles times scenes) the state holds, `None` when empty.
    pub fn rows(&self) -> Option<usize> {
        match self {
            MemoryState::Empty => None,
            MemoryState::Hidden(h) => Some(h.dims()[0]),
            MemoryState::Lstm(s) => Some(s.h.dims()[0]),
        }
    }
}

/// The memory cell (exactly one field is set, except for `none`).
#[derive(Module, Debug)]
pub struct Memory<B: Backend> {
    mingru: Option<MinGru<B>>,
    minlstm: Option<MinLstm<B>>,
    gru: Option<Gru<B>>,
    lstm: Option<Lstm<B>>,
}

impl<B: NetOps> Memory<B> {
    /// A cell of kind `kind` reading `d_in` features per particle with `hidden` state values.
    pub fn new(kind: MemoryKind, d_in: usize, hidden: usize, device: &B::Device) -> Self {
        Self {
            mingru: (kind == MemoryKind::MinGru).then(|| MinGru::new(d_in, hidden, hidden, device)),
            minlstm: (kind == MemoryKind::MinLstm)
                .then(|| MinLstm::new(d_in, hidden, hidden, device)),
            gru: (kind == MemoryKind::Gru).then(|| Gru::new(d_in, hidden, device)),
            lstm: (kind == MemoryKind::Lstm).then(|| Lstm::new(d_in, hidden, device)),
        }
    }

    /// One step for every particle: the output features (`[B N, H]`, `None` when stateless)
    /// and the new state.
    ///
    /// # Shapes
    /// - `u`: `[B N, d_in]` (one row per particle)
    pub fn step(
        &self,
        u: Tensor<B, 2>,
        state: MemoryState<B>,
    ) -> (Option<Tensor<B, 2>>, MemoryState<B>) {
        let (hidden, previous) = match state {
            MemoryState::Hidden(h) => (Some(h), None),
            MemoryState::Lstm(s) => (None, Some(s)),
            MemoryState::Empty => (None, None),
        };
        if let Some(cell) = &self.mingru {
            let (out, h) = cell.step(u, hidden);
            return (Some(out), MemoryState::Hidden(h));
        }
        if let Some(cell) = &self.minlstm {
            let (out, h) = cell.step(u, hidden);
            return (Some(out), MemoryState::Hidden(h));
        }
        if let Some(cell) = &self.gru {
            let h = cell.step(u, hidden);
            return (Some(h.clone()), MemoryState::Hidden(h));
        }
        if let Some(cell) = &self.lstm {
            let s = cell.step(u, previous);
            return (Some(s.h.clone()), MemoryState::Lstm(s));
        }
        (None, MemoryState::Empty)
    }
}
