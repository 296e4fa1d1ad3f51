//! Message passing between neighbouring particles ([`super::GridConfig::interaction`],
//! `train --interaction ROUNDS`; issue 81's lever "a few rounds of message passing over each
//! particle's neighbours within a radius after G2P, feeding the per-particle minGRU/minLSTM",
//! the paper's own next step, "graph-based neural networks to better capture local particle
//! neighborhoods").
//!
//! The graph and the processor follow GNS (Sanchez-Gonzalez et al. 2020, "Learning to
//! simulate complex physics with graph networks", section 2 and appendix C.1): each particle
//! is joined to its neighbours within a connectivity radius `r` at its current position (here
//! the `k` nearest, [`Graph::build`]), an edge reads the receiver's and the sender's latent
//! and their displacement `(x_j - x_i) / r` with its squared length, and each round updates
//! every node's latent residually from the sum of its edges' messages:
//!
//! ```text
//! h_i   = silu(E u_i)                                             (encoder, [R, W])
//! e_ij  = silu(A h_i + B h_j + C d_ij)                            (edge, [R, W] a slot)
//! h_i  += N2 silu(N1 [h_i, M mean_j e_ij])                        (node, each round)
//! u_i  += O h_i                                                   (O starts at zero)
//! ```
//!
//! (the edge MLP's second layer `M` applied after the mean over the particle's real
//! neighbours, which it commutes with). A neighbour slot's `B h_j` and `x_j` are read with
//! the particle-grid transfers' gather ([`crate::ops::gather`], 9 entries of which the slot's
//! alone weighs 1): its gradient is their scatter-add kernel, where burn's `select` would
//! take `select_assign`, a serial loop on CUDA. The
//! output is added to the particle's input row `u_i = [g_i, own_i]`, so it feeds the memory
//! and the head through their first layers; `O` starts at zero, so a model given message
//! passing (`--init-from` one without) predicts what it did until it is trained further.
//! The radius is in domain units: about 2.5 particle spacings of the generated 2,500-particle
//! scenes at its default, 0.02. The neighbour search runs on the host (the cell list of
//! [`crate::neighbours::Bins`]) on the call's input positions; the rounds run as tensors on
//! the model's device.

use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};
use rayon::prelude::*;

use crate::model::roofline;
use crate::neighbours::Bins;
use crate::ops::{gather, linear, silu, NetOps, STENCIL_NODES as STENCIL};

/// Edge features per neighbour: the displacement over the radius and its squared length.
const EDGE_FEATURES: usize = 3;

/// One round of message passing (the module doc's edge and node updates).
#[derive(Module, Debug)]
pub struct Round<B: Backend> {
    receiver: Linear<B>,
    sender: Linear<B>,
    offset: Linear<B>,
    message: Linear<B>,
    node_a: Linear<B>,
    node_b: Linear<B>,
}

/// The processor: the encoder, `rounds` rounds and the output layer (the module doc).
#[derive(Module, Debug)]
pub struct Interaction<B: Backend> {
    encode: Linear<B>,
    rounds: Vec<Round<B>>,
    out: Linear<B>,
    /// Connectivity radius, domain units.
    radius: f32,
    /// Neighbours per particle, k.
    neighbours: usize,
}

/// Each particle's `k` nearest neighbours within the radius in one batch, as stencils of
/// [`crate::ops::gather`] (9 slots a chunk: one gather per neighbour slot, whose backward is
/// the scatter-add kernel where burn's `select` would take `select_assign`, a serial loop on
/// CUDA; `model::grid::transfer`'s module doc).
#[derive(Debug, Clone)]
pub struct Graph<B: Backend> {
    /// `ceil(k / 9)` chunks of `[B N 9]` neighbour rows (`b N + j`, into the batch's `[B N]`
    /// particles): slot s is chunk `s / 9`'s entry `s % 9`; a missing neighbour points at the
    /// particle itself.
    chunks: Vec<Tensor<B, 1, Int>>,
    /// `[B, N, k]` 1 for a real neighbour, 0 for padding.
    mask: Tensor<B, 3>,
    /// `[B, N, 2]` the positions the graph was built on, domain units.
    pos: Tensor<B, 3>,
    /// The connectivity radius it was built with, domain units.
    radius: f32,
}

/// One neighbour slot of a [`Graph`], as the rounds read it ([`Graph::slots`]).
struct Slot<B: Backend> {
    /// `[B, N, 9]` gather weights: the real-neighbour mask at the slot's entry of its chunk,
    /// 0 elsewhere.
    pick: Tensor<B, 3>,
    /// `[B N, 3]` edge features: `(x_j - x_i) / radius` and its squared length, 0 for
    /// padding; differentiable in the positions.
    edge: Tensor<B, 2>,
    /// `[B N, 1]` 1 where the slot holds a real neighbour.
    real: Tensor<B, 2>,
}

impl<B: NetOps> Interaction<B> {
    /// A processor of `rounds` rounds of width `width` on particle rows of `inputs` values,
    /// joining each particle to its `neighbours` nearest within `radius` (domain units); the
    /// output layer starts at zero.
    pub fn new(
        inputs: usize,
        width: usize,
        [rounds, neighbours]: [usize; 2],
        radius: f32,
        device: &B::Device,
    ) -> Self {
        let dense =
            |i: usize, o: usize, bias: bool| LinearConfig::new(i, o).with_bias(bias).init(device);
        let round = |_| Round {
            receiver: dense(width, width, true),
            sender: dense(width, width, false),
            offset: dense(EDGE_FEATURES, width, false),
            message: dense(width, width, true),
            node_a: dense(2 * width, width, true),
            node_b: dense(width, width, true),
        };
        Self {
            encode: dense(inputs, width, true),
            rounds: (0..rounds).map(round).collect(),
            out: LinearConfig::new(width, inputs)
                .with_initializer(Initializer::Zeros)
                .init(device),
            radius,
            neighbours,
        }
    }

    /// The graph of positions `pos` (`[B, N, 2]`, domain units) at this processor's radius
    /// and neighbour count ([`Graph::build`]).
    pub fn graph(&self, pos: &Tensor<B, 3>) -> Graph<B> {
        Graph::build(pos, self.radius, self.neighbours)
    }

    /// `[R, D]`: the change to the particle rows `u` (`[R, D]`, `R = B N`) from the rounds of
    /// message passing over `graph` (the module doc).
    pub fn forward(&self, u: Tensor<B, 2>, graph: &Graph<B>) -> Tensor<B, 2> {
        let [rows, inputs] = u.dims();
        let k = self.neighbours;
        let width = self.encode.weight.dims()[1];
        if roofline::on() {
            roofline::count_dense(rows, inputs, width);
            roofline::count_dense(rows, width, inputs);
            for _ in &self.rounds {
                // receiver, sender, message, node_b; node_a; each slot's edge layer, its
                // 9-entry gather and the edge's sums.
                roofline::count_dense(rows, width, 4 * width);
                roofline::count_dense(rows, 2 * width, width);
                roofline::count_dense(rows * k, EDGE_FEATURES, width);
                let edges = (rows * k * width) as f64;
                roofline::count(22.0 * edges, 4.0 * (STENCIL as f64 + 4.0) * edges);
            }
        }
        let mut h = silu(linear(&self.encode, u));
        let slots = graph.slots();
        let [b, n, _] = graph.pos.dims();
        // The mean over each particle's real neighbours (1 for a particle without any).
        let count = graph
            .mask
            .clone()
            .sum_dim(2)
            .clamp_min(1.0)
            .reshape([rows, 1]);
        for round in &self.rounds {
            let own = linear(&round.receiver, h.clone());
            let other = linear(&round.sender, h.clone()).reshape([b, n, width]);
            let mut sum = Tensor::<B, 2>::zeros([rows, width], &h.device());
            for (k, slot) in slots.iter().enumerate() {
                let near = gather(other.clone(), graph.chunk(k), slot.pick.clone());
                let offset = linear(&round.offset, slot.edge.clone());
                let edge = silu(own.clone() + near.reshape([rows, width]) + offset);
                sum = sum + edge * slot.real.clone();
            }
            let message = linear(&round.message, sum / count.clone());
            let node = silu(linear(
                &round.node_a,
                Tensor::cat(vec![h.clone(), message], 1),
            ));
            h = h + linear(&round.node_b, node);
        }
        linear(&self.out, h)
    }
}

impl<B: NetOps> Graph<B> {
    /// The `k` nearest neighbours within `radius` (domain units) of every particle of
    /// `pos` (`[B, N, 2]`), each scene its own; the search on the host (positions read
    /// back), scenes in parallel. Ties in distance go to the lower index.
    ///
    /// # Panics
    /// The positions cannot be read back.
    pub fn build(pos: &Tensor<B, 3>, radius: f32, k: usize) -> Self {
        let [b, n, _] = pos.dims();
        let device = pos.device();
        let host: Vec<f32> = pos
            .clone()
            .into_data()
            .convert::<f32>()
            .to_vec()
            .expect("positions");
        let chunks = k.div_ceil(STENCIL);
        let mut mask = vec![0f32; b * n * k];
        let scenes: Vec<Vec<i64>> = match n {
            0 => Vec::new(),
            _ => host
                .par_chunks(2 * n)
                .zip(mask.par_chunks_mut(n * k))
                .enumerate()
                .map(|(scene, (xy, mask))| scene_graph(xy, (scene * n) as i64, (radius, k), mask))
                .collect(),
        };
        // Chunk-major: each chunk holds every scene's rows in order.
        let chunk = |c: usize| {
            let rows: Vec<i64> = scenes
                .iter()
                .flat_map(|rows| rows[c * n * STENCIL..(c + 1) * n * STENCIL].iter().copied())
                .collect();
            Tensor::from_data(TensorData::new(rows, [b * n * STENCIL]), &device)
        };
        Self {
            chunks: (0..chunks).map(chunk).collect(),
            mask: Tensor::from_data(TensorData::new(mask, [b, n, k]), &device),
            pos: pos.clone(),
            radius,
        }
    }

    /// The stencil rows of neighbour slot `slot` (its chunk, `[B N 9]`).
    fn chunk(&self, slot: usize) -> Tensor<B, 1, Int> {
        self.chunks[slot / STENCIL].clone()
    }

    /// Every neighbour slot's gather weights, edge features and mask ([`Slot`]), once a
    /// forward pass.
    fn slots(&self) -> Vec<Slot<B>> {
        let [b, n, _] = self.pos.dims();
        let device = self.pos.device();
        (0..self.mask.dims()[2])
            .map(|slot| {
                let real = self.mask.clone().narrow(2, slot, 1);
                let mut one = [0f32; STENCIL];
                one[slot % STENCIL] = 1.0;
                let one =
                    Tensor::from_data(TensorData::new(one.to_vec(), [1, 1, STENCIL]), &device);
                let pick = real.clone() * one;
                let near = gather(self.pos.clone(), self.chunk(slot), pick.clone());
                let d = (near - self.pos.clone() * real.clone()).div_scalar(self.radius);
                let d2 = d.clone().powi_scalar(2).sum_dim(2);
                Slot {
                    pick,
                    edge: Tensor::cat(vec![d, d2], 2).reshape([b * n, EDGE_FEATURES]),
                    real: real.reshape([b * n, 1]),
                }
            })
            .collect()
    }
}

/// One scene's neighbour rows (offset by `base`; chunk-major, `[ceil(k / 9), N, 9]`, a missing
/// neighbour pointing at the particle itself) and its `[N, k]` real-neighbour `mask`, from
/// its `[N, 2]` positions `xy`: each particle's candidates are the 3 x 3 cells of a cell list
/// at least `radius` wide ([`Bins::for_radius`]); the `k` nearest within `radius` are kept,
/// nearest first, ties to the lower index.
fn scene_graph(xy: &[f32], base: i64, (radius, k): (f32, usize), mask: &mut [f32]) -> Vec<i64> {
    let n = xy.len() / 2;
    let ids: Vec<u32> = (0..n as u32).collect();
    let bins = Bins::for_radius(xy, 2, &ids, radius);
    let mut rows = vec![0i64; k.div_ceil(STENCIL) * n * STENCIL];
    let (reach, mut near) = (radius * radius, Vec::<(f32, u32)>::with_capacity(64));
    let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    for i in 0..n {
        let (x, y) = (xy[2 * i], xy[2 * i + 1]);
        near.clear();
        bins.around(x, y, |j| {
            let d2 = (xy[2 * j] - x).powi(2) + (xy[2 * j + 1] - y).powi(2);
            if j != i && d2 <= reach {
                near.push((d2, j as u32));
            }
        });
        if near.len() > k {
            near.select_nth_unstable_by(k - 1, order);
            near.truncate(k);
        }
        near.sort_unstable_by(order);
        for slot in 0..k.div_ceil(STENCIL) * STENCIL {
            let at = (slot / STENCIL) * n * STENCIL + i * STENCIL + slot % STENCIL;
            rows[at] = base + near.get(slot).map_or(i, |&(_, j)| j as usize) as i64;
            if slot < k {
                mask[i * k + slot] = f32::from(u8::from(slot < near.len()));
            }
        }
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type Nd = NdArray<f32>;

    /// A chunk's neighbour rows, as integers.
    fn rows(chunk: &Tensor<Nd, 1, Int>) -> Vec<i64> {
        chunk.clone().into_data().convert::<i64>().to_vec().unwrap()
    }

    fn positions(xy: &[[f32; 2]], scenes: usize) -> Tensor<Nd, 3> {
        let flat: Vec<f32> = (0..scenes)
            .flat_map(|_| xy.iter().flatten().copied())
            .collect();
        Tensor::from_data(
            TensorData::new(flat, [scenes, xy.len(), 2]),
            &Default::default(),
        )
    }

    /// The nearest within the radius, nearest first, padded with the particle itself, in
    /// each scene's own rows; the edge features of each slot.
    #[test]
    fn graph_joins_the_nearest_within_the_radius() {
        let xy = [[0.5, 0.5], [0.51, 0.5], [0.5, 0.53], [0.9, 0.9]];
        let g = Graph::build(&positions(&xy, 2), 0.05, 3);
        assert_eq!(g.chunks.len(), 1);
        let index = rows(&g.chunks[0]);
        let mask: Vec<f32> = g.mask.clone().into_data().to_vec().unwrap();
        // Scene 0: particle 0 sees 1 then 2, the rest of its 9 entries itself; particle 3
        // nobody. Scene 1 the same, rows + 4.
        assert_eq!(&index[..4], &[1, 2, 0, 0]);
        assert_eq!(&index[27..30], &[3, 3, 3]);
        assert_eq!(&index[36..39], &[5, 6, 4]);
        assert_eq!(&mask[..3], &[1.0, 1.0, 0.0]);
        assert_eq!(&mask[9..12], &[0.0; 3]);
        let slots = g.slots();
        let pick: Vec<f32> = slots[1].pick.clone().into_data().to_vec().unwrap();
        assert_eq!(&pick[..9], &[0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        let first: Vec<f32> = slots[0].edge.clone().into_data().to_vec().unwrap();
        let third: Vec<f32> = slots[2].edge.clone().into_data().to_vec().unwrap();
        // Particle 0 -> 1: (0.01, 0) / 0.05 = (0.2, 0), squared length 0.04; no third.
        assert!((first[0] - 0.2).abs() < 1e-5 && first[1].abs() < 1e-6);
        assert!((first[2] - 0.04).abs() < 1e-5);
        assert_eq!(&third[..3], &[0.0; 3]);
    }

    /// 12 neighbours take two chunks of 9: slot 10 is the second chunk's entry 1.
    #[test]
    fn more_than_nine_neighbours_take_a_second_chunk() {
        let xy: Vec<[f32; 2]> = (0..16).map(|i| [0.5 + 0.002 * i as f32, 0.5]).collect();
        let g = Graph::build(&positions(&xy, 1), 0.05, 12);
        assert_eq!(g.chunks.len(), 2);
        let second = rows(&g.chunks[1]);
        // Particle 0's neighbours by distance are 1, 2, ..., so slot 10 is particle 11.
        assert_eq!(second[1], 11);
        assert_eq!(second[3], 0, "slots past k point at the particle itself");
    }

    /// The slots' gathers compute the module doc's formula: one round against it written out
    /// particle by particle, each particle's neighbours listed by hand (nearest first; the
    /// last particle has none, so its message is the message layer's bias).
    #[test]
    fn one_round_is_the_formula() {
        let device = Default::default();
        let xy = [[0.5, 0.5], [0.51, 0.5], [0.5, 0.53], [0.9, 0.9]];
        let near: [&[usize]; 4] = [&[1, 2], &[0, 2], &[0, 1], &[]];
        let mut net = Interaction::<Nd>::new(3, 4, [1, 3], 0.05, &device);
        net.out = LinearConfig::new(4, 3).init(&device);
        let u = Tensor::<Nd, 2>::random([4, 3], burn::tensor::Distribution::Default, &device);
        let got: Vec<f32> = net
            .forward(u.clone(), &net.graph(&positions(&xy, 1)))
            .into_data()
            .to_vec()
            .unwrap();
        let row = |t: &Tensor<Nd, 2>, i: usize| t.clone().narrow(0, i, 1);
        let h = silu(net.encode.forward(u));
        let r = &net.rounds[0];
        let (own, other) = (r.receiver.forward(h.clone()), r.sender.forward(h.clone()));
        let mut rows = Vec::new();
        for (i, list) in near.iter().enumerate() {
            let mut sum = Tensor::<Nd, 2>::zeros([1, 4], &device);
            for &j in list.iter() {
                let (dx, dy) = ((xy[j][0] - xy[i][0]) / 0.05, (xy[j][1] - xy[i][1]) / 0.05);
                let d = TensorData::new(vec![dx, dy, dx * dx + dy * dy], [1, 3]);
                let offset = r.offset.forward(Tensor::from_data(d, &device));
                sum = sum + silu(row(&own, i) + row(&other, j) + offset);
            }
            let message = r.message.forward(sum.div_scalar(list.len().max(1) as f32));
            let node = silu(r.node_a.forward(Tensor::cat(vec![row(&h, i), message], 1)));
            rows.push(row(&h, i) + r.node_b.forward(node));
        }
        let want: Vec<f32> = net
            .out
            .forward(Tensor::cat(rows, 0))
            .into_data()
            .to_vec()
            .unwrap();
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-5, "{got:?} against {want:?}");
        }
    }

    /// The output layer starts at zero; once it is not, a particle's change depends on its
    /// neighbours' rows and not on particles outside its radius.
    #[test]
    fn messages_come_from_neighbours_only() {
        let device = Default::default();
        let xy = [[0.5, 0.5], [0.51, 0.5], [0.9, 0.9]];
        let mut net = Interaction::<Nd>::new(4, 8, [2, 4], 0.05, &device);
        let g = net.graph(&positions(&xy, 1));
        let u = |v: f32| {
            Tensor::<Nd, 2>::from_data(
                TensorData::new(
                    vec![0.1, 0.2, 0.3, 0.4, v, 0.1, 0.0, 0.2, 0.3, 0.3, 0.1, 0.0],
                    [3, 4],
                ),
                &device,
            )
        };
        let zero: Vec<f32> = net.forward(u(0.0), &g).into_data().to_vec().unwrap();
        assert!(zero.iter().all(|v| *v == 0.0));
        net.out = LinearConfig::new(8, 4).init(&device);
        let a: Vec<f32> = net.forward(u(0.0), &g).into_data().to_vec().unwrap();
        let b: Vec<f32> = net.forward(u(1.0), &g).into_data().to_vec().unwrap();
        // Particle 1's row changed: particle 0's output (its neighbour) with it, particle 2's
        // (outside the radius) not.
        assert!((0..4).any(|c| (a[c] - b[c]).abs() > 1e-6));
        assert_eq!(&a[8..12], &b[8..12]);
    }
}
