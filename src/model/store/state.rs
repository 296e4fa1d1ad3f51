//! What a [`Surrogate`](super::Surrogate) carries between frames, per batch of
//! trajectories: [`State`] (the network's state, the scenes' constraint data, the frame
//! count), [`NetState`] (the paper core's layer states or a grid model's [`GridState`]) and
//! the lazily split rows of a batch ([`Row`]), with the stacking and splitting of states for
//! dynamic batching. [`GridState`], the grid model's per-scene fields, lives in
//! `grid_state.rs` (a new carried field of a grid model is one change there); the stacking
//! of the pieces ([`Rows`]) lives in `stack.rs`, the constraint data in `constrained.rs`.

use std::sync::Arc;

use burn::tensor::backend::Backend;

use crate::model::LayerState;

use super::constrained::ConstraintState;
use super::grid_state::GridState;
use super::stack::{shape, Rows};
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::grid::MemoryState;
    use burn::backend::NdArray;
    use burn::tensor::Tensor;

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
