//! Stacking per-scene states into one batch state and splitting it back, for dynamic
//! batching (`Surrogate::step_scenes`, used by `minflow node`). Every piece a state carries
//! is [`Rows`]: tensors whose first dimension is `copies x B x m` rows (B trajectories of m
//! rows each: m = 1 for `[B, ...]` tensors, m = N for the grid memory's `[B N, H]` rows;
//! `copies` = 2 for a mirror ensemble, whose direct rows come first and its mirrored rows
//! second), optional pieces, and the architectures' recurrent states built from them. A
//! stacked piece holds the scenes' rows in order, copy by copy, so a mirror ensemble's
//! stacked state is again all direct rows, then all mirrored rows.
//!
//! `State::stack` and `State::split` (`state.rs`) take a state apart field by field and
//! call these; a new kind of piece needs a [`Rows`] impl here.

use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};

use crate::model::grid::{MemoryState, NeighbourTensors};
use crate::model::rnn::LstmState;
use crate::model::LayerState;

use super::StoreError;

/// Why pieces could not be stacked ([`StoreError::Shape`]): they differ in kind or shape.
pub(super) type StackError = StoreError;

/// A [`StoreError::Shape`] saying `reason`.
pub(super) fn shape(reason: &str) -> StoreError {
    StoreError::Shape(reason.into())
}

/// A piece of per-trajectory state that stacks along its batch rows.
pub(super) trait Rows: Sized {
    /// Appends what must be equal for two pieces to stack (kind tags and shapes) to `key`:
    /// that of one of `of` equal parts of this piece (1: the piece itself; a lazily split
    /// row of a batch, `State::split`, is one of its batch's `of` scenes).
    fn rows_key(&self, of: usize, key: &mut Vec<usize>);
    /// The pieces of several states as one, rows in order (copy by copy).
    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError>;
    /// The piece of a stacked state back as one piece per part, part i holding `sizes[i]`
    /// trajectories (the sizes sum to the stacked piece's trajectories).
    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self>;
    /// The rows of the trajectories `scenes` (indices among this piece's `of`, in that
    /// order, repeats allowed) as one piece, copy by copy: what stacking their pieces split
    /// apart would give, in one gather a tensor (`State::stack` of a batch's rows).
    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self;
}

impl<B: Backend, const D: usize, K> Rows for Tensor<B, D, K>
where
    K: burn::tensor::BasicOps<B> + burn::tensor::TensorKind<B>,
{
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        let mut dims = self.dims();
        dims[0] /= of.max(1);
        key.push(D);
        key.extend(dims);
    }

    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        if copies <= 1 || parts.len() <= 1 {
            return Ok(Tensor::cat(parts, 0));
        }
        let mut rows = Vec::with_capacity(parts.len() * copies);
        for c in 0..copies {
            for p in &parts {
                let r = p.dims()[0] / copies;
                rows.push(p.clone().narrow(0, c * r, r));
            }
        }
        Ok(Tensor::cat(rows, 0))
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        let total: usize = sizes.iter().sum();
        let copies = copies.max(1);
        let per_copy = self.dims()[0] / copies;
        let m = per_copy / total.max(1);
        let mut out = Vec::with_capacity(sizes.len());
        let mut start = 0;
        for &b in sizes {
            let pieces: Vec<_> = (0..copies)
                .map(|c| self.clone().narrow(0, c * per_copy + start * m, b * m))
                .collect();
            // Even one piece is copied: a narrow is a view (burn-ndarray; burn-cubecl at
            // aligned offsets), and a view would keep the whole batch's buffer alive for as
            // long as this part lives (a stream that stops would hold its last call's batch
            // until --idle-timeout). Without the copy the split took 39-55 % less time on a
            // GPU (docs/scale.md at 61e783e, "The split, tried and not kept"; reverted in
            // 4d5b8c3).
            out.push(Tensor::cat(pieces, 0));
            start += b;
        }
        out
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        // Viewed as one row per scene and copy (`[copies of, m ...]` flattened), the gather
        // takes `copies x scenes` indices, not one per row: m = N (K) rows a scene otherwise.
        let (copies, of) = (copies.max(1), of.max(1));
        let mut dims = self.dims();
        let groups = copies * of;
        let grouped: Tensor<B, 2, K> =
            (self.clone()).reshape([groups, self.shape().num_elements() / groups]);
        let picks: Vec<i64> = (0..copies)
            .flat_map(|c| scenes.iter().map(move |&s| (c * of + s) as i64))
            .collect();
        let len = picks.len();
        let picks = Tensor::<B, 1, Int>::from_data(TensorData::new(picks, [len]), &self.device());
        dims[0] = dims[0] / groups * len;
        grouped.select(0, picks).reshape(dims)
    }
}

impl<T: Rows> Rows for Option<T> {
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        key.push(usize::from(self.is_some()));
        if let Some(t) = self {
            t.rows_key(of, key);
        }
    }

    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        if parts.iter().all(Option::is_none) {
            return Ok(None);
        }
        let some: Option<Vec<T>> = parts.into_iter().collect();
        let some = some.ok_or_else(|| shape("stack: a piece some states lack"))?;
        Ok(Some(T::stack_rows(some, copies)?))
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        match self {
            None => sizes.iter().map(|_| None).collect(),
            Some(t) => t.split_rows(sizes, copies).into_iter().map(Some).collect(),
        }
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        self.as_ref().map(|t| t.select_rows(scenes, of, copies))
    }
}

impl<B: Backend> Rows for LstmState<B> {
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        self.h.rows_key(of, key);
        self.c.rows_key(of, key);
    }

    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        let (h, c): (Vec<_>, Vec<_>) = parts.into_iter().map(|s| (s.h, s.c)).unzip();
        Ok(LstmState {
            h: Rows::stack_rows(h, copies)?,
            c: Rows::stack_rows(c, copies)?,
        })
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        let h = self.h.split_rows(sizes, copies);
        let c = self.c.split_rows(sizes, copies);
        h.into_iter()
            .zip(c)
            .map(|(h, c)| LstmState { h, c })
            .collect()
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        LstmState {
            h: self.h.select_rows(scenes, of, copies),
            c: self.c.select_rows(scenes, of, copies),
        }
    }
}

/// The three shapes of a recurrent state (the grid's [`MemoryState`] and the paper core's
/// [`LayerState`] both have them): nothing, a hidden state, an LSTM's hidden and cell state.
enum Recurrent<B: Backend> {
    Empty,
    Hidden(Tensor<B, 2>),
    Lstm(LstmState<B>),
}

impl<B: Backend> Recurrent<B> {
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        match self {
            Recurrent::Empty => key.push(0),
            Recurrent::Hidden(h) => {
                key.push(1);
                h.rows_key(of, key);
            }
            Recurrent::Lstm(s) => {
                key.push(2);
                s.rows_key(of, key);
            }
        }
    }

    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        let mut hidden = Vec::new();
        let mut lstm = Vec::new();
        let mut empty = 0;
        for p in parts {
            match p {
                Recurrent::Empty => empty += 1,
                Recurrent::Hidden(h) => hidden.push(h),
                Recurrent::Lstm(s) => lstm.push(s),
            }
        }
        match (empty, hidden.is_empty(), lstm.is_empty()) {
            (_, true, true) => Ok(Recurrent::Empty),
            (0, false, true) => Ok(Recurrent::Hidden(Rows::stack_rows(hidden, copies)?)),
            (0, true, false) => Ok(Recurrent::Lstm(Rows::stack_rows(lstm, copies)?)),
            _ => Err(shape("stack: recurrent states of different kinds")),
        }
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        match self {
            Recurrent::Empty => sizes.iter().map(|_| Recurrent::Empty).collect(),
            Recurrent::Hidden(h) => h
                .split_rows(sizes, copies)
                .into_iter()
                .map(Recurrent::Hidden)
                .collect(),
            Recurrent::Lstm(s) => s
                .split_rows(sizes, copies)
                .into_iter()
                .map(Recurrent::Lstm)
                .collect(),
        }
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        match self {
            Recurrent::Empty => Recurrent::Empty,
            Recurrent::Hidden(h) => Recurrent::Hidden(h.select_rows(scenes, of, copies)),
            Recurrent::Lstm(s) => Recurrent::Lstm(s.select_rows(scenes, of, copies)),
        }
    }
}

/// [`Rows`] for a type that converts to and from [`Recurrent`].
macro_rules! recurrent_rows {
    ($ty:ident, $empty:ident) => {
        impl<B: Backend> Rows for $ty<B> {
            fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
                Recurrent::from(self.clone()).rows_key(of, key);
            }
            fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
                let parts = parts.into_iter().map(Recurrent::from).collect();
                Ok(Recurrent::stack_rows(parts, copies)?.into())
            }
            fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
                let parts = Recurrent::from(self).split_rows(sizes, copies);
                parts.into_iter().map(Into::into).collect()
            }
            fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
                Recurrent::from(self.clone())
                    .select_rows(scenes, of, copies)
                    .into()
            }
        }
        impl<B: Backend> From<$ty<B>> for Recurrent<B> {
            fn from(s: $ty<B>) -> Self {
                match s {
                    $ty::$empty => Recurrent::Empty,
                    $ty::Hidden(h) => Recurrent::Hidden(h),
                    $ty::Lstm(s) => Recurrent::Lstm(s),
                }
            }
        }
        impl<B: Backend> From<Recurrent<B>> for $ty<B> {
            fn from(s: Recurrent<B>) -> Self {
                match s {
                    Recurrent::Empty => $ty::$empty,
                    Recurrent::Hidden(h) => $ty::Hidden(h),
                    Recurrent::Lstm(s) => $ty::Lstm(s),
                }
            }
        }
    };
}

recurrent_rows!(MemoryState, Empty);
recurrent_rows!(LayerState, None);

impl<B: Backend> Rows for NeighbourTensors<B> {
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        key.extend([self.dims[0] / of.max(1), self.dims[1]]);
    }

    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        let n = parts.first().map_or(0, |p| p.dims[1]);
        let scenes = parts.iter().map(|p| p.dims[0]).sum();
        let field = |f: fn(&Self) -> Tensor<B, 3>| {
            Rows::stack_rows(parts.iter().map(f).collect::<Vec<_>>(), copies)
        };
        let index = Rows::stack_rows(parts.iter().map(|p| p.index.clone()).collect(), copies)?;
        Ok(NeighbourTensors {
            index,
            offset: field(|p| p.offset.clone())?,
            weight: field(|p| p.weight.clone())?,
            binv: field(|p| p.binv.clone())?,
            inv_d0: field(|p| p.inv_d0.clone())?,
            dims: [scenes, n],
        })
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        let per_scene = copies.max(1);
        let n = self.dims[1];
        let mut index = self.index.split_rows(sizes, copies).into_iter();
        let mut offset = self.offset.split_rows(sizes, copies).into_iter();
        let mut weight = self.weight.split_rows(sizes, copies).into_iter();
        let mut binv = self.binv.split_rows(sizes, copies).into_iter();
        let mut inv_d0 = self.inv_d0.split_rows(sizes, copies).into_iter();
        sizes
            .iter()
            .filter_map(|&b| {
                Some(NeighbourTensors {
                    index: index.next()?,
                    offset: offset.next()?,
                    weight: weight.next()?,
                    binv: binv.next()?,
                    inv_d0: inv_d0.next()?,
                    dims: [b * per_scene, n],
                })
            })
            .collect()
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        let pick = |t: &Tensor<B, 3>| t.select_rows(scenes, of, copies);
        NeighbourTensors {
            index: self.index.select_rows(scenes, of, copies),
            offset: pick(&self.offset),
            weight: pick(&self.weight),
            binv: pick(&self.binv),
            inv_d0: pick(&self.inv_d0),
            dims: [scenes.len() * copies.max(1), self.dims[1]],
        }
    }
}

impl<T: Rows> Rows for Vec<T> {
    fn rows_key(&self, of: usize, key: &mut Vec<usize>) {
        key.push(self.len());
        for t in self {
            t.rows_key(of, key);
        }
    }

    /// Element-wise: element j of the result stacks element j of every part (the paper
    /// core's layers).
    fn stack_rows(parts: Vec<Self>, copies: usize) -> Result<Self, StackError> {
        let len = parts.first().map_or(0, Vec::len);
        if parts.iter().any(|p| p.len() != len) {
            return Err(shape("stack: states with different numbers of layers"));
        }
        let mut columns: Vec<Vec<T>> = (0..len).map(|_| Vec::new()).collect();
        for part in parts {
            for (column, t) in columns.iter_mut().zip(part) {
                column.push(t);
            }
        }
        columns
            .into_iter()
            .map(|c| T::stack_rows(c, copies))
            .collect()
    }

    fn split_rows(self, sizes: &[usize], copies: usize) -> Vec<Self> {
        let mut out: Vec<Vec<T>> = sizes.iter().map(|_| Vec::new()).collect();
        for t in self {
            for (o, piece) in out.iter_mut().zip(t.split_rows(sizes, copies)) {
                o.push(piece);
            }
        }
        out
    }

    fn select_rows(&self, scenes: &[usize], of: usize, copies: usize) -> Self {
        self.iter()
            .map(|t| t.select_rows(scenes, of, copies))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type B = NdArray<f32>;

    fn rows(values: &[f32], width: usize) -> Tensor<B, 2> {
        let t = Tensor::<B, 1>::from_floats(values, &Default::default());
        t.reshape([values.len() / width, width])
    }

    #[test]
    fn mirror_rows_stack_copy_by_copy_and_split_back() {
        // Two scenes, one trajectory each, mirror ensemble: [direct; mirrored] rows each.
        let a = rows(&[1.0, 2.0], 1); // a direct, a mirrored
        let b = rows(&[3.0, 4.0], 1);
        let stacked = Rows::stack_rows(vec![a, b], 2).unwrap();
        // All direct rows first, then all mirrored ones.
        let got: Vec<f32> = stacked.clone().into_data().to_vec().unwrap();
        assert_eq!(got, [1.0, 3.0, 2.0, 4.0]);
        let back = stacked.split_rows(&[1, 1], 2);
        let a: Vec<f32> = back[0].clone().into_data().to_vec().unwrap();
        let b: Vec<f32> = back[1].clone().into_data().to_vec().unwrap();
        assert_eq!((a, b), (vec![1.0, 2.0], vec![3.0, 4.0]));
    }

    #[test]
    fn selected_rows_equal_the_stack_of_the_split_pieces() {
        // Three scenes of m = 2 rows each, mirror ensemble (copies = 2).
        let scenes: Vec<_> = (0..3)
            .map(|s| {
                let v = 10.0 * s as f32;
                MemoryState::Hidden(rows(&[v, v + 1.0, v + 2.0, v + 3.0], 1))
            })
            .collect();
        let stacked = Rows::stack_rows(scenes.clone(), 2).unwrap();
        for pick in [vec![2, 0], vec![1], vec![0, 1, 2], vec![2, 2]] {
            let parts = pick.iter().map(|&i| scenes[i].clone()).collect();
            let want = Rows::stack_rows(parts, 2).unwrap();
            let got = stacked.select_rows(&pick, 3, 2);
            let (MemoryState::Hidden(want), MemoryState::Hidden(got)) = (want, got) else {
                panic!("hidden")
            };
            let want: Vec<f32> = want.into_data().to_vec().unwrap();
            let got: Vec<f32> = got.into_data().to_vec().unwrap();
            assert_eq!(got, want, "scenes {pick:?}");
        }
    }

    #[test]
    fn memory_of_several_rows_per_trajectory_splits_by_trajectory() {
        // m = 2 rows (particles) per trajectory; scenes of 1 and 2 trajectories.
        let a = MemoryState::Hidden(rows(&[1.0, 2.0], 1));
        let b = MemoryState::Hidden(rows(&[3.0, 4.0, 5.0, 6.0], 1));
        let stacked = Rows::stack_rows(vec![a, b], 1).unwrap();
        let back = stacked.split_rows(&[1, 2], 1);
        let MemoryState::Hidden(b) = &back[1] else {
            panic!("hidden")
        };
        let b: Vec<f32> = b.clone().into_data().to_vec().unwrap();
        assert_eq!(b, [3.0, 4.0, 5.0, 6.0]);
        let mixed = Rows::stack_rows(vec![MemoryState::<B>::Empty, back[1].clone()], 1);
        assert!(mixed.is_err());
    }
}
