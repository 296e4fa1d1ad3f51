//! What a [`Surrogate`](super::Surrogate) carries between frames, per batch of
//! trajectories: [`State`] (the network's state, the scenes' constraint data, the frame
//! count), [`NetState`] (the paper core's layer states or a grid model's [`GridState`]) and
//! [`GridState`], the grid model's per-scene fields, which knows how to start, restart,
//! stack, split, fit and mirror itself. A new carried field of a grid model is one change
//! here: its declaration and one line in each of `GridState`'s methods below. The stacking
//! of the pieces ([`Rows`]) lives in `stack.rs`, the constraint data in `constrained.rs`.

use std::sync::Arc;

use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

use crate::model::grid::{mirror_rows, MemoryState, NeighbourTensors};
use crate::model::LayerState;

use super::constrained::ConstraintState;
use super::stack::{shape, Rows, StackError};
use super::StoreError;

/// Per-trajectory state (one batch row per trajectory).
#[derive(Clone)]
pub struct State<B: Backend> {
    /// The network's state.
    pub(super) net: NetState<B>,
    /// Per trajectory: its constraint data, and the rest frames it is built from.
    pub(super) constraints: ConstraintState,
    /// Frames consumed since the state was reset.
    pub frames: usize,
}

/// What each architecture carries between frames.
#[derive(Clone)]
pub(super) enum NetState<B: Backend> {
    /// The paper core's layer states.
    Paper(Vec<LayerState<B>>),
    /// The grid model's per-particle state.
    Grid(GridState<B>),
    /// One scene's rows of a batch state, not cut out yet ([`State::split`]).
    Row(Row<B>),
}

/// One scene of a batch state split lazily: [`State::split`] into one scene each hands out
/// rows that share the batch ([`Home`]) instead of cutting every tensor per scene, and
/// [`State::stack`] of rows of one batch gathers them in one operation a tensor (all of a
/// batch's rows, in order: the batch itself, no operation at all). A surrogate node steps
/// the same streams call after call, so its batch stays whole between calls: cutting and
/// stacking 256 scenes' states recorded thousands of slices and concatenations a call
/// (docs/scale.md). A restarted row (a gap in its stream) stays a row of its batch, marked
/// `fresh`: the call it next steps in starts its memory, velocity history and F afresh
/// ([`GridState::fresh`]), so restarted and continuing streams of one batch still share one
/// call. A row used any other way is cut out first ([`NetState::owned`]). A row keeps its
/// whole batch alive until it is stepped, dropped or cut out by [`State::compact`] once most
/// of its batch has moved on.
#[derive(Clone)]
pub(super) struct Row<B: Backend> {
    /// The batch state the row belongs to.
    home: Arc<Home<B>>,
    /// The scene's index in the batch.
    index: usize,
    /// The scene's stream restarted since the batch was made ([`State::restart`]): its
    /// network state is the batch's row with [`GridState::fresh`] set.
    fresh: bool,
}

/// The batch state of lazily split [`Row`]s.
pub(super) struct Home<B: Backend> {
    /// The batch state (never a row itself).
    net: NetState<B>,
    /// The batch's scenes.
    of: usize,
    /// Copies of each scene in the batch's rows (2 for a mirror ensemble; `stack.rs`).
    copies: usize,
}

impl<B: Backend> Home<B> {
    fn new(net: NetState<B>, of: usize, copies: usize) -> Arc<Self> {
        Arc::new(Home { net, of, copies })
    }

    /// The rows of `scenes` as one state ([`Rows::select_rows`]; the batch itself when they
    /// are all its scenes in order), those whose `fresh` is true marked as restarting
    /// ([`GridState::fresh`]: one value per row, copy by copy).
    fn select(&self, scenes: &[usize], fresh: &[bool]) -> NetState<B> {
        let (of, copies) = (self.of, self.copies);
        let whole = scenes.len() == of && scenes.iter().enumerate().all(|(i, &s)| i == s);
        let net = match &self.net {
            net if whole => net.clone(),
            NetState::Paper(layers) => NetState::Paper(layers.select_rows(scenes, of, copies)),
            NetState::Grid(grid) => NetState::Grid(grid.select_rows(scenes, of, copies)),
            NetState::Row(_) => unreachable!("a batch of rows is not a row"),
        };
        match net {
            NetState::Grid(mut grid) if fresh.contains(&true) => {
                let mask: Vec<f32> = (0..copies)
                    .flat_map(|_| fresh.iter().map(|&f| f32::from(u8::from(f))))
                    .collect();
                let device = grid.device();
                grid.fresh =
                    device.map(|d| crate::model::upload::<B, 1>(mask, [copies * scenes.len()], &d));
                NetState::Grid(grid)
            }
            net => net,
        }
    }
}

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
    /// (None: no row restarts). Set on rows of a batch that restart in place ([`Row`]); the
    /// next call starts their memory at zero, their velocity history from the input frame
    /// and their F from the fit (`grid_step.rs`), as it starts a state restarted whole
    /// ([`GridState::restart`]), and returns a state without it. Not part of the stacking
    /// key: a missing one stacks as zeros.
    pub(super) fresh: Option<Tensor<B, 1>>,
}

impl<B: Backend> NetState<B> {
    /// This state with its own tensors: a [`Row`] cut out of its batch (still marked if it
    /// restarted), anything else as it is.
    pub(super) fn owned(self) -> Self {
        match self {
            NetState::Row(row) => row.home.select(&[row.index], &[row.fresh]),
            other => other,
        }
    }
}

impl<B: Backend> State<B> {
    /// A copy of this state whose constraint data is its own
    /// ([`ConstraintState::detached`]): a padded call's copy of a scene.
    pub(super) fn detached(&self) -> Self {
        State {
            net: self.net.clone(),
            constraints: self.constraints.detached(),
            frames: self.frames,
        }
    }

    /// A fresh state around the network state `net`: no constraint data, no frames.
    pub(super) fn new(net: NetState<B>) -> Self {
        State {
            net,
            constraints: ConstraintState::default(),
            frames: 0,
        }
    }

    /// This state reset as at the start of a stream, `fresh` the network's fresh state: a
    /// grid model keeps its reference positions and rest neighbourhoods
    /// ([`GridState::restart`]), and the constraint data is kept.
    pub(super) fn restart(self, fresh: NetState<B>) -> Self {
        let net = match (self.net, fresh) {
            (NetState::Row(row), NetState::Grid(_)) => NetState::Row(Row { fresh: true, ..row }),
            (NetState::Grid(grid), NetState::Grid(_)) => NetState::Grid(grid.restart_marked()),
            (_, fresh) => fresh,
        };
        State {
            net,
            constraints: self.constraints,
            frames: 0,
        }
    }

    /// This state with its own tensors when it is a row of a batch that most of its rows
    /// have left (fewer than a quarter still held: they were stepped on in other batches,
    /// restarted or dropped), so that batch can be freed; anything else as it is. A row
    /// holds its whole batch ([`Row`]): without this a stream that stops or falls behind
    /// would keep its last batch's memory until the stream is dropped. The node calls it
    /// on every kept state once a second.
    pub fn compact(self) -> Self {
        let abandoned = match &self.net {
            NetState::Row(row) => 4 * Arc::strong_count(&row.home) < row.home.of,
            _ => false,
        };
        match abandoned {
            true => State {
                net: self.net.owned(),
                ..self
            },
            false => self,
        }
    }

    /// What must be equal for states to stack ([`State::stack`]): each field's kind and
    /// shape. States with equal keys and frames with equal particle counts share a call.
    pub(super) fn shape_key(&self) -> Vec<usize> {
        let mut key = Vec::new();
        net_key(&self.net, 1, &mut key);
        key
    }

    /// Several scenes' states (of equal [`State::shape_key`]) as one batch state, rows in
    /// order, copy by copy (`copies` = 2 for a mirror ensemble; `stack.rs`). Frame counts
    /// are the caller's to keep. The constraint data stacks per trajectory
    /// ([`ConstraintState::stack`]).
    pub(super) fn stack(states: Vec<State<B>>, copies: usize) -> Result<State<B>, StoreError> {
        if let Some(net) = rows_of_one_batch(&states, copies) {
            return Ok(State {
                net,
                constraints: ConstraintState::stack(
                    states.into_iter().map(|s| s.constraints).collect(),
                ),
                frames: 0,
            });
        }
        let (mut paper, mut grid, mut constraints) = (vec![], vec![], vec![]);
        for state in states {
            constraints.push(state.constraints);
            match state.net.owned() {
                NetState::Paper(layers) => paper.push(layers),
                NetState::Grid(g) => grid.push(g),
                NetState::Row(_) => unreachable!("an owned state is not a row"),
            }
        }
        let net = match (paper.is_empty(), grid.is_empty()) {
            (false, true) => NetState::Paper(Rows::stack_rows(paper, copies)?),
            (true, false) => NetState::Grid(Rows::stack_rows(grid, copies)?),
            _ => return Err(shape("stack: no states, or of both kinds")),
        };
        Ok(State {
            net,
            constraints: ConstraintState::stack(constraints),
            frames: 0,
        })
    }

    /// A stacked state back as one state per scene, scene i of `sizes[i]` trajectories (1
    /// for a node's scene): the inverse of [`State::stack`]. Frame counts are 0.
    pub(super) fn split(self, sizes: &[usize], copies: usize) -> Vec<State<B>> {
        let lazy = sizes.len() > 1 && sizes.iter().all(|&s| s == 1);
        let net: Vec<NetState<B>> = match self.net.owned() {
            net if lazy => {
                let home = Home::new(net, sizes.len(), copies);
                (0..sizes.len())
                    .map(|index| {
                        NetState::Row(Row {
                            home: Arc::clone(&home),
                            index,
                            fresh: false,
                        })
                    })
                    .collect()
            }
            NetState::Paper(layers) => layers
                .split_rows(sizes, copies)
                .into_iter()
                .map(NetState::Paper)
                .collect(),
            NetState::Grid(grid) => grid
                .split_rows(sizes, copies)
                .into_iter()
                .map(NetState::Grid)
                .collect(),
            NetState::Row(_) => unreachable!("an owned state is not a row"),
        };
        net.into_iter()
            .zip(self.constraints.split(sizes))
            .map(|(net, constraints)| State {
                net,
                constraints,
                frames: 0,
            })
            .collect()
    }
}

/// Appends the stacking key of `net` ([`State::shape_key`]) as one of `of` equal parts to
/// `key`: a [`Row`]'s is that of one scene of its batch, the key the row has once cut out.
fn net_key<B: Backend>(net: &NetState<B>, of: usize, key: &mut Vec<usize>) {
    match net {
        NetState::Paper(layers) => layers.rows_key(of, key),
        NetState::Grid(grid) => {
            key.push(usize::MAX);
            grid.rows_key(of, key);
        }
        NetState::Row(row) => net_key(&row.home.net, of * row.home.of, key),
    }
}

/// The stacked network state of `states` when they are all rows of one batch with `copies`
/// copies of each scene ([`Row`]): one gather a tensor, or the batch itself.
fn rows_of_one_batch<B: Backend>(states: &[State<B>], copies: usize) -> Option<NetState<B>> {
    let NetState::Row(first) = &states.first()?.net else {
        return None;
    };
    if first.home.copies != copies {
        return None;
    }
    let rows: Option<Vec<(usize, bool)>> = (states.iter())
        .map(|s| match &s.net {
            NetState::Row(row) if Arc::ptr_eq(&row.home, &first.home) => {
                Some((row.index, row.fresh))
            }
            _ => None,
        })
        .collect();
    let (scenes, fresh): (Vec<usize>, Vec<bool>) = rows?.into_iter().unzip();
    Some(first.home.select(&scenes, &fresh))
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
    fn device(&self) -> Option<B::Device> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type B = NdArray<f32>;

    /// A grid state of `scenes` scenes, two memory rows each: scene s holds `10 s` and
    /// `10 s + 1`.
    fn batch(scenes: usize) -> State<B> {
        let values: Vec<f32> = (0..scenes)
            .flat_map(|s| [10.0 * s as f32, 10.0 * s as f32 + 1.0])
            .collect();
        let memory = Tensor::<B, 1>::from_floats(values.as_slice(), &Default::default());
        let mut grid = GridState::new();
        grid.memory = MemoryState::Hidden(memory.reshape([2 * scenes, 1]));
        State::new(NetState::Grid(grid))
    }

    fn memory(state: &State<B>) -> Vec<f32> {
        let NetState::Grid(GridState {
            memory: MemoryState::Hidden(h),
            ..
        }) = &state.net
        else {
            panic!("an owned grid state with a hidden memory")
        };
        h.clone().into_data().to_vec().unwrap()
    }

    #[test]
    fn rows_stack_back_and_are_cut_out_once_their_batch_is_left() {
        let rows = batch(8).split(&[1; 8], 1);
        assert!(matches!(rows[5].net, NetState::Row(_)));
        // Some rows, out of order: one gather.
        let picked = vec![rows[6].clone(), rows[1].clone()];
        assert_eq!(
            memory(&State::stack(picked, 1).unwrap()),
            [60.0, 61.0, 10.0, 11.0]
        );
        // All of them, in order: the batch itself.
        let whole = State::stack(rows.clone(), 1).unwrap();
        assert_eq!(memory(&whole).len(), 16);
        // A row kept while the others are dropped is cut out by `compact`.
        let mut rows = rows;
        let kept = rows.swap_remove(3);
        drop(rows);
        let kept = kept.compact();
        assert_eq!(memory(&kept), [30.0, 31.0]);
        // A row of a batch still mostly held is left as it is.
        let rows = batch(4).split(&[1; 4], 1);
        assert!(matches!(rows[0].clone().compact().net, NetState::Row(_)));
    }
}
