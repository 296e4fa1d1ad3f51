//! What a grid model's `Surrogate` carries between calls, per scene:
//! [`GridState`] (the per-particle memory, velocity history, reference positions, rest
//! neighbourhoods, advected F and restart marks), which knows how to start, restart, stack,
//! split, fit and mirror itself. A new carried field of a grid model is one change here: its
//! declaration and one line in each of `GridState`'s methods below. The per-batch `State`
//! that holds it, and the lazily split rows of a batch, live in `state.rs`; the stacking of
//! the pieces ([`Rows`]) in `stack.rs`.

use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use crate::model::grid::{mirror_rows, MemoryState, NeighbourTensors};

use super::stack::{shape, Rows, StackError};

/// What a grid model carries between calls, per particle of each trajectory (batch row).
#[derive(Clone)]
pub(super) struct GridState<B: Backend> {
    /// The per-particle memory (`[B N, H]` rows).
    pub(super) memory: MemoryState<B>,
    /// The velocities of the last T - 1 frames (`[B, N, 2 (T - 1)]`, oldest first; `None`
    /// before the first frame or when T = 1).
    pub(super) history: Option<Tensor<B, 3>>,
    /// The reference positions (`[B, N, 2]`: the first frame's, unless set by
    /// [`GridState::set_reference`]; read only by a model with `reference`).
    pub(super) reference: Option<Tensor<B, 3>>,
    /// The rest neighbourhoods of the reference positions (built on the first step of a
    /// model with `rest_shape`: the scene's physical state beside its memory, kept across a
    /// restart).
    pub(super) rest: Option<NeighbourTensors<B>>,
    /// The advected deformation gradient (`[B, N, 4]`, a model with `Deformation::Advect`:
    /// the F of the frame the next step reads; `None` before the first step and after a
    /// restart, when the step starts it from the fit to the rest neighbourhoods).
    pub(super) deformation: Option<Tensor<B, 3>>,
    /// `[copies B]`: 1 for the rows restarted since the state's last call, 0 for the others
    /// (None: no row restarts). Set on rows of a batch that restart in place (a `Row`,
    /// `state.rs`); the next call starts their memory at zero, their velocity history from
    /// the input frame and their F from the fit (`grid_step.rs`), as it starts a state
    /// restarted whole
    /// ([`GridState::restart`]), and returns a state without it. Not part of the stacking
    /// key: a missing one stacks as zeros.
    pub(super) fresh: Option<Tensor<B, 1>>,
}

impl<B: Backend> GridState<B> {
    /// Nothing carried yet.
    pub(super) fn new() -> Self {
        GridState {
            memory: MemoryState::Empty,
            history: None,
            reference: None,
            rest: None,
            deformation: None,
            fresh: None,
        }
    }

    /// The device of the state's tensors, None when it carries none.
    pub(super) fn device(&self) -> Option<B::Device> {
        let memory = match &self.memory {
            MemoryState::Hidden(h) => Some(h.device()),
            MemoryState::Lstm(s) => Some(s.h.device()),
            MemoryState::Empty => None,
        };
        memory
            .or_else(|| self.history.as_ref().map(Tensor::device))
            .or_else(|| self.reference.as_ref().map(Tensor::device))
    }

    /// This state reset as at the start of a stream, but for the reference positions and
    /// rest neighbourhoods (the scene's physical state: what the node keeps over a gap in a
    /// stream that goes on). The advected F is fitted again from the next frame.
    pub(super) fn restart(self) -> Self {
        GridState {
            reference: self.reference,
            rest: self.rest,
            ..GridState::new()
        }
    }

    /// This state restarting in its next call, every row marked ([`GridState::fresh`]):
    /// the call starts it as [`GridState::restart`] would, but its stacking key stays that
    /// of the streams going on, so it shares their call. (Restarted whole, an owned state
    /// went through a call of its own every frame: a stream that keeps restarting, as every
    /// stream does under overload, never joined the others' call again.) Restarted whole
    /// when it has neither reference positions nor a velocity history yet (nothing carried
    /// to mark).
    pub(super) fn restart_marked(self) -> Self {
        match self.marks(1.0) {
            Some(fresh) => GridState {
                fresh: Some(fresh),
                ..self
            },
            None => self.restart(),
        }
    }

    /// `[copies B]` restart marks of `value` for every row (1: all restart, 0: none), B from
    /// the reference positions or the velocity history; None when the state has neither.
    fn marks(&self, value: f32) -> Option<Tensor<B, 1>> {
        let rows = self.reference.as_ref().or(self.history.as_ref())?.dims()[0];
        Some(Tensor::full([rows], value, &self.device()?))
    }

    /// This state for a call of `b` trajectories of `n` particles, window `t`: every piece
    /// of another shape dropped (a velocity history, reference positions, rest
    /// neighbourhoods or F of another B or N; a memory of another row count), so the step
    /// starts those afresh.
    pub(super) fn fit(self, [b, n]: [usize; 2], t: usize) -> Self {
        // A restart mark of another shape is dropped, and the memory with it: a marked row
        // must not go on from its memory.
        let marked = self.fresh.is_some();
        let fresh = self.fresh.filter(|f| f.dims() == [b]);
        let marked_elsewhere = marked && fresh.is_none();
        GridState {
            memory: match self.memory.rows() {
                Some(rows) if rows != b * n || marked_elsewhere => MemoryState::Empty,
                _ => self.memory,
            },
            history: self.history.filter(|h| h.dims() == [b, n, 2 * (t - 1)]),
            reference: self.reference.filter(|r| r.dims() == [b, n, 2]),
            rest: self.rest.filter(|r| r.dims() == [b, n]),
            deformation: self.deformation.filter(|f| f.dims() == [b, n, 4]),
            fresh,
        }
    }

    /// Sets the reference positions to those of `first` (`[B, N, 4]` physical frames, `b`
    /// of them); a mirror ensemble (`mirror`) takes each frame and its mirror image as two
    /// rows ([`with_mirror_rows`]).
    pub(super) fn set_reference(
        &mut self,
        first: &[f32],
        b: usize,
        mirror: bool,
        device: &B::Device,
    ) {
        let (first, b) = match mirror {
            true => (with_mirror_rows(first), 2 * b),
            false => (first.to_vec(), b),
        };
        let n = first.len() / (4 * b);
        let frame = crate::model::upload::<B, 3>(first, [b, n, 4], device);
        self.reference = Some(frame.narrow(2, 0, 2));
    }

    /// After a projected bundle (K frames `out`, `[B, N, 4]` each): the velocity history
    /// (`[copies B, N, 2 (T - 1)]`: the T - 1 frames before the next call's input, the
    /// bundle's last) taken from the projected frames, so the next call reads the
    /// velocities a caller feeding back the projected frames sees; a mirror ensemble's
    /// second copy mirrored. Left as is when K <= T - 1.
    pub(super) fn history_from(
        &mut self,
        out: &[Vec<f32>],
        [b, n]: [usize; 2],
        device: &B::Device,
    ) {
        let Some(history) = &self.history else {
            return;
        };
        let [rows, _, width] = history.dims();
        let (t1, k) = (width / 2, out.len());
        let copies = rows / b.max(1);
        if k <= t1 || rows != copies * b || !(1..=2).contains(&copies) {
            return;
        }
        let window = &out[k - 1 - t1..k - 1];
        let mut host = vec![0.0f32; rows * n * width];
        for copy in 0..copies {
            let sign = if copy == 1 { -1.0 } else { 1.0 };
            for p in 0..b * n {
                for (w, frame) in window.iter().enumerate() {
                    let at = ((copy * b * n + p) * t1 + w) * 2;
                    host[at] = sign * frame[4 * p + 2];
                    host[at + 1] = frame[4 * p + 3];
                }
            }
        }
        self.history = Some(crate::model::upload::<B, 3>(host, [rows, n, width], device));
    }
}

/// Each field of a grid state stacks as its own piece: one line per field in each method.
impl<B: Backend> Rows for GridState<B> {
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        self.memory.rows_key(of, key);
        self.history.rows_key(of, key);
        self.reference.rows_key(of, key);
        self.rest.rows_key(of, key);
        self.deformation.rows_key(of, key);
        // `fresh` is not part of the key: it stacks as zeros where missing.
    }

    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        let fresh = fresh_or_zeros(&parts)?;
        let (mut memory, mut history, mut reference) = (vec![], vec![], vec![]);
        let (mut rest, mut deformation) = (vec![], vec![]);
        for p in parts {
            memory.push(p.memory);
            history.push(p.history);
            reference.push(p.reference);
            rest.push(p.rest);
            deformation.push(p.deformation);
        }
        Ok(GridState {
            memory: Rows::stack_rows(memory, copies)?,
            history: Rows::stack_rows(history, copies)?,
            reference: Rows::stack_rows(reference, copies)?,
            rest: Rows::stack_rows(rest, copies)?,
            deformation: Rows::stack_rows(deformation, copies)?,
            fresh: Rows::stack_rows(fresh, copies)?,
        })
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        let mut history = self.history.split_rows(sizes, copies).into_iter();
        let mut reference = self.reference.split_rows(sizes, copies).into_iter();
        let mut rest = self.rest.split_rows(sizes, copies).into_iter();
        let mut deformation = self.deformation.split_rows(sizes, copies).into_iter();
        let mut fresh = self.fresh.split_rows(sizes, copies).into_iter();
        let mut grid = |memory| -> Option<GridState<B>> {
            Some(GridState {
                memory,
                history: history.next()?,
                reference: reference.next()?,
                rest: rest.next()?,
                deformation: deformation.next()?,
                fresh: fresh.next()?,
            })
        };
        self.memory
            .split_rows(sizes, copies)
            .into_iter()
            .filter_map(|m| grid(m))
            .collect()
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        GridState {
            memory: self.memory.select_rows(scenes, of, copies),
            history: self.history.select_rows(scenes, of, copies),
            reference: self.reference.select_rows(scenes, of, copies),
            rest: self.rest.select_rows(scenes, of, copies),
            deformation: self.deformation.select_rows(scenes, of, copies),
            fresh: self.fresh.select_rows(scenes, of, copies),
        }
    }
}

/// The `fresh` marks of grid states about to stack ([`GridState::fresh`]): all None when
/// none has any, otherwise each part's own or zeros for its rows (`[copies B]`, B from its
/// reference positions or velocity history).
fn fresh_or_zeros<B: Backend>(
    parts: &[GridState<B>],
) -> Result<Vec<Option<Tensor<B, 1>>>, StackError> {
    if parts.iter().all(|p| p.fresh.is_none()) {
        return Ok(parts.iter().map(|_| None).collect());
    }
    parts
        .iter()
        .map(|p| match &p.fresh {
            Some(f) => Ok(Some(f.clone())),
            None => (p.marks(0.0))
                .map(Some)
                .ok_or_else(|| shape("stack: a restarted row beside a state of unknown rows")),
        })
        .collect()
}

/// `frames` (`[B, N, 4]`) followed by their mirror images: `[2B, N, 4]`.
pub(super) fn with_mirror_rows(frames: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(2 * frames.len());
    out.extend_from_slice(frames);
    out.extend_from_slice(frames);
    mirror_rows(&mut out[frames.len()..], 4);
    out
}

/// The mean of the first half of `out` (`[2B, N, 4]`) and its second half mirrored back.
pub(super) fn mean_of_mirror_rows(out: &[f32]) -> Vec<f32> {
    let (direct, mirrored) = out.split_at(out.len() / 2);
    let mut back = mirrored.to_vec();
    mirror_rows(&mut back, 4);
    direct
        .iter()
        .zip(&back)
        .map(|(a, b)| 0.5 * (a + b))
        .collect()
}
