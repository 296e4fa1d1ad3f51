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
//! e_ij  = silu(A h_i + B h_j + C d_ij)                            (edge, [R, k, W])
//! h_i  += N2 silu(N1 [h_i, M (sum_j e_ij) / k])                   (node, each round)
//! u_i  += O h_i                                                   (O starts at zero)
//! ```
//!
//! (the edge MLP's second layer `M` applied after the sum, which it commutes with). The
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
use crate::ops::{linear, silu, NetOps};

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

/// Each particle's `k` nearest neighbours within the radius in one batch: rows index the
/// batch's `B N` particles scene by scene.
#[derive(Debug, Clone)]
pub struct Graph<B: Backend> {
    /// `[R k]` the neighbours' rows; a particle with fewer than `k` points at itself.
    index: Tensor<B, 1, Int>,
    /// `[R, k, 1]` 1 for a real neighbour, 0 for padding.
    mask: Tensor<B, 3>,
    /// `[R, k, 3]` edge features (the module doc), 0 for padding.
    edges: Tensor<B, 3>,
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

    /// Rounds of message passing.
    pub fn rounds(&self) -> usize {
        self.rounds.len()
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
                roofline::count_dense(rows, width, 5 * width);
                roofline::count_dense(rows * k, EDGE_FEATURES, width);
                roofline::count(
                    3.0 * (rows * k * width) as f64,
                    8.0 * (rows * k * width) as f64,
                );
            }
        }
        let mut h = silu(linear(&self.encode, u));
        for round in &self.rounds {
            let own = linear(&round.receiver, h.clone()).unsqueeze_dim::<3>(1);
            let other = linear(&round.sender, h.clone())
                .select(0, graph.index.clone())
                .reshape([rows, k, width]);
            let edge = silu(own + other + linear(&round.offset, graph.edges.clone()));
            let sum = (edge * graph.mask.clone())
                .sum_dim(1)
                .reshape([rows, width]);
            let message = linear(&round.message, sum.div_scalar(k as f32));
            let node = silu(linear(
                &round.node_a,
                Tensor::cat(vec![h.clone(), message], 1),
            ));
            h = h + linear(&round.node_b, node);
        }
        linear(&self.out, h)
    }
}

impl<B: Backend> Graph<B> {
    /// The `k` nearest neighbours within `radius` (domain units) of every particle of
    /// `pos` (`[B, N, 2]`), each scene its own; the search on the host (positions read
    /// back), scenes in parallel. Ties in distance go to the lower index.
    pub fn build(pos: &Tensor<B, 3>, radius: f32, k: usize) -> Self {
        let [b, n, _] = pos.dims();
        let device = pos.device();
        let host: Vec<f32> = pos
            .clone()
            .into_data()
            .convert::<f32>()
            .to_vec()
            .unwrap_or_default();
        let (rows, e) = (b * n, EDGE_FEATURES);
        let mut index = vec![0i64; rows * k];
        let mut mask = vec![0f32; rows * k];
        let mut edges = vec![0f32; rows * k * e];
        host.par_chunks(2 * n)
            .zip(index.par_chunks_mut(n * k))
            .zip(mask.par_chunks_mut(n * k))
            .zip(edges.par_chunks_mut(n * k * e))
            .enumerate()
            .for_each(|(scene, (((xy, index), mask), edges))| {
                let out = Rows { index, mask, edges };
                scene_graph(xy, (scene * n) as i64, (radius, k), out);
            });
        Self {
            index: Tensor::from_data(TensorData::new(index, [rows * k]), &device),
            mask: Tensor::from_data(TensorData::new(mask, [rows, k, 1]), &device),
            edges: Tensor::from_data(TensorData::new(edges, [rows, k, EDGE_FEATURES]), &device),
        }
    }
}

/// One scene's share of a [`Graph`]'s host buffers: `[N k]` rows, `[N k]` mask, `[N k 3]`
/// edge features.
struct Rows<'a> {
    index: &'a mut [i64],
    mask: &'a mut [f32],
    edges: &'a mut [f32],
}

/// One scene's neighbour rows (offset by `base`), mask and edge features into `out` from its
/// `[N, 2]` positions `xy`: each particle's candidates are the 3 x 3 cells of a cell list at
/// least `radius` wide ([`Bins::for_radius`]); the `k` nearest within `radius` are kept,
/// nearest first, ties to the lower index; the rest of a particle's `k` slots point at itself
/// with mask and features 0.
fn scene_graph(xy: &[f32], base: i64, (radius, k): (f32, usize), out: Rows) {
    let n = xy.len() / 2;
    let ids: Vec<u32> = (0..n as u32).collect();
    let bins = Bins::for_radius(xy, 2, &ids, radius);
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
        for slot in 0..k {
            let at = i * k + slot;
            let edge = &mut out.edges[EDGE_FEATURES * at..EDGE_FEATURES * (at + 1)];
            match near.get(slot) {
                Some(&(d2, j)) => {
                    let j = j as usize;
                    out.index[at] = base + j as i64;
                    out.mask[at] = 1.0;
                    let (dx, dy) = (xy[2 * j] - x, xy[2 * j + 1] - y);
                    edge.copy_from_slice(&[dx / radius, dy / radius, d2 / reach]);
                }
                None => out.index[at] = base + i as i64,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    type Nd = NdArray<f32>;

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
    /// each scene's own rows.
    #[test]
    fn graph_joins_the_nearest_within_the_radius() {
        let xy = [[0.5, 0.5], [0.51, 0.5], [0.5, 0.53], [0.9, 0.9]];
        let g = Graph::build(&positions(&xy, 2), 0.05, 3);
        let index: Vec<i64> = g.index.into_data().convert::<i64>().to_vec().unwrap();
        let mask: Vec<f32> = g.mask.into_data().to_vec().unwrap();
        // Scene 0: particle 0 sees 1 then 2; particle 3 nobody. Scene 1 the same, rows + 4.
        assert_eq!(&index[..3], &[1, 2, 0]);
        assert_eq!(&index[9..12], &[3, 3, 3]);
        assert_eq!(&index[12..15], &[5, 6, 4]);
        assert_eq!(&mask[..3], &[1.0, 1.0, 0.0]);
        assert_eq!(&mask[9..12], &[0.0; 3]);
        let edges: Vec<f32> = g.edges.into_data().to_vec().unwrap();
        // Particle 0 -> 1: (0.01, 0) / 0.05 = (0.2, 0), squared length 0.04.
        assert!((edges[0] - 0.2).abs() < 1e-5 && edges[1].abs() < 1e-6);
        assert!((edges[2] - 0.04).abs() < 1e-5);
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
