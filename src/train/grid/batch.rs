//! A batch of training windows on the device for the grid architecture's loss: the frames
//! as physical values (mirrored where drawn so), the material one-hot, the time steps, the
//! reference positions and the neighbourhoods the model and the structure terms need
//! ([`BatchTensors`]). Prepared on the host by [`prepare_whole`], [`prepare_packed`] or
//! [`prepare_batch`] (the trainer's prefetch thread), then uploaded ([`HostBatch::upload`]).
//! Read by `rollout_loss.rs`.

use std::ops::Range;

use burn::tensor::backend::Backend;
use burn::tensor::Tensor;
use rayon::prelude::*;

use crate::data::Batch;
use crate::model::grid::{mirror_rows, one_hot, GridConfig, NeighbourTensors, Neighbourhood};
use crate::model::upload;

/// What a `Rollout` (`rollout_loss.rs`) reads of one batch, on the device, physical units.
pub(super) struct BatchTensors<B: Backend> {
    /// `[B, S, N, 4]`: the window's frames and its target frame.
    pub(super) frames: Tensor<B, 4>,
    /// `[B, N, 4]`: material one-hot.
    pub(super) material: Tensor<B, 3>,
    /// `[B]`: frame spacing.
    pub(super) dt: Tensor<B, 1>,
    /// `[B, N, 2]`: positions in the trajectory's first frame (the reference positions).
    pub(super) first_pos: Tensor<B, 3>,
    /// The solids' rest neighbourhoods in `first_pos`, when a model or the strain loss needs
    /// them, with the number of rest-neighbour pairs.
    pub(super) rest: Option<(NeighbourTensors<B>, f32)>,
    /// The liquid's neighbourhoods in the first input frame, for the volume loss, with the
    /// number of liquid particles that have neighbours.
    pub(super) liquid: Option<(NeighbourTensors<B>, f32)>,
    /// On the host, for the constraint projection.
    pub(super) host: HostRows,
}

/// What the constraint projection of a `Rollout` (`rollout_loss.rs`) reads of a batch on the
/// host.
pub(super) struct HostRows {
    /// `[B, N, 2]` positions in the trajectory's first frame.
    pub(super) first_pos: Vec<f32>,
    /// `[B N]` material ids.
    pub(super) material: Vec<u8>,
    /// `[B]` frame spacings.
    pub(super) dt: Vec<f32>,
    /// `[B]` the solver grid of each window's scene, when known.
    pub(super) solver_grid: Vec<Option<u32>>,
}

/// Which neighbourhoods [`prepare_batch`] and [`prepare_packed`] build.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Needs {
    /// The solids' rest neighbourhoods (rest-shape features, strain loss).
    pub rest: bool,
    /// The liquid's neighbourhoods in this frame of the window (volume loss): `T - 1`.
    pub liquid_at: Option<usize>,
    /// The model's material one-hot width ([`GridConfig::materials`]).
    pub materials: usize,
}

/// A batch of windows prepared on the host, ready to upload ([`HostBatch::upload`]): the
/// frames packed and mirrored, the neighbourhoods built. Made by [`prepare_whole`],
/// [`prepare_packed`] or [`prepare_batch`], on the trainer's prefetch thread while the
/// previous batch's step runs (`train_epoch`).
pub(super) struct HostBatch {
    /// `[B, S, N, 4]` frames, the target last, physical units.
    frames: Vec<f32>,
    /// B, the window's input frames T, and N.
    dims: [usize; 3],
    /// The windows that count toward the batch: B, or 0 for a padding share
    /// ([`HostBatch::padding`]).
    counted: usize,
    /// The model's material one-hot width.
    materials: usize,
    /// The solids' rest neighbourhoods and the liquid's, with their counts (see
    /// [`BatchTensors`]).
    rest: Option<(Neighbourhood, f32)>,
    liquid: Option<(Neighbourhood, f32)>,
    /// First positions, materials and frame spacings.
    host: HostRows,
}

/// The tensors of a batch of windows built with the identity scaler (inputs then hold
/// physical values); the windows `w` with `mirror[w]` are mirrored ([`mirror_rows`]);
/// `needs` says which neighbourhoods to build and the model's one-hot width. [`prepare_batch`]
/// then [`HostBatch::upload`].
#[cfg(test)]
pub(super) fn upload_batch<B: Backend>(
    batch: Batch,
    mirror: &[bool],
    needs: Needs,
    device: &B::Device,
) -> BatchTensors<B> {
    prepare_batch(&batch, 0..batch.b, mirror, needs).upload(device)
}

/// The host's part of the tensors of the windows `windows` of `batch` (all of them, or one
/// data-parallel share): the frames packed and mirrored (the share's window `w` where
/// `mirror[w]`, [`mirror_rows`]) on rayon's threads, a window each, the neighbourhoods
/// `needs` asks for built. A `Layout::Frames` batch's rows are copied out and go to
/// [`prepare_packed`].
pub(super) fn prepare_batch(
    batch: &Batch,
    windows: Range<usize>,
    mirror: &[bool],
    needs: Needs,
) -> HostBatch {
    let (b, t, n) = (windows.len(), batch.t, batch.n);
    assert!(
        batch.frame_shares.is_empty(),
        "a batch of Layout::Shares is prepared share by share (prepare_packed)"
    );
    let per = (t + 1) * n * 4;
    // A batch of `Layout::Frames` holds each window's rows packed already.
    if !batch.frames.is_empty() {
        let frames = batch.frames[windows.start * per..windows.end * per].to_vec();
        return prepare_packed(batch, windows, frames, mirror, needs);
    }
    let mut frames = vec![0.0f32; b * per];
    let mut first_pos = batch.first_pos[windows.start * n * 2..windows.end * n * 2].to_vec();
    // A `Layout::Scaled` batch (the identity scaler's) holds its inputs' first four columns,
    // then the target.
    let per_window = frames.par_chunks_mut(per.max(1));
    (per_window
        .zip(first_pos.par_chunks_mut((n * 2).max(1)))
        .enumerate())
    .for_each(|(w, (packed, first))| {
        // The window's place in the whole batch.
        let at = windows.start + w;
        let input = &batch.inputs[at * t * n * 5..(at + 1) * t * n * 5];
        for (to, row) in packed.chunks_exact_mut(4).zip(input.chunks_exact(5)) {
            to.copy_from_slice(&row[..4]);
        }
        packed[t * n * 4..].copy_from_slice(&batch.target_phys[at * n * 4..(at + 1) * n * 4]);
        if mirror.get(w).copied().unwrap_or(false) {
            mirror_rows(packed, 4);
            mirror_rows(first, 2);
        }
    });
    finish(batch, windows, frames, first_pos, needs)
}

/// The whole of `batch` prepared as [`prepare_batch`] prepares `0..batch.b` (the feed's one
/// share, one device), its frames moved rather than copied where it holds them packed
/// ([`crate::data::Layout::Frames`]).
pub(super) fn prepare_whole(mut batch: Batch, mirror: &[bool], needs: Needs) -> HostBatch {
    if batch.frames.is_empty() {
        return prepare_batch(&batch, 0..batch.b, mirror, needs);
    }
    let frames = std::mem::take(&mut batch.frames);
    prepare_packed(&batch, 0..batch.b, frames, mirror, needs)
}

/// The windows `windows` of `batch` prepared as [`prepare_batch`] prepares them, from their
/// frames already packed `[B_s, T + 1, N, 4]` (a share of [`Batch::frame_shares`], or the
/// whole [`Batch::frames`]), which it takes: the flagged windows (`mirror[w]`) mirrored in
/// place.
pub(super) fn prepare_packed(
    batch: &Batch,
    windows: Range<usize>,
    mut frames: Vec<f32>,
    mirror: &[bool],
    needs: Needs,
) -> HostBatch {
    let (t, n) = (batch.t, batch.n);
    assert_eq!(
        frames.len(),
        windows.len() * (t + 1) * n * 4,
        "packed frames of the windows"
    );
    let mut first_pos = batch.first_pos[windows.start * n * 2..windows.end * n * 2].to_vec();
    (frames.par_chunks_mut(((t + 1) * n * 4).max(1)))
        .zip(first_pos.par_chunks_mut((n * 2).max(1)))
        .enumerate()
        .filter(|(w, _)| mirror.get(*w).copied().unwrap_or(false))
        .for_each(|(_, (packed, first))| {
            mirror_rows(packed, 4);
            mirror_rows(first, 2);
        });
    finish(batch, windows, frames, first_pos, needs)
}

/// The rest of a [`HostBatch`] of the windows `windows` of `batch`, given their packed
/// `frames` `[B, T + 1, N, 4]` and reference positions `first_pos` `[B, N, 2]`: the
/// neighbourhoods `needs` asks for and the rows the projection reads.
fn finish(
    batch: &Batch,
    windows: Range<usize>,
    frames: Vec<f32>,
    first_pos: Vec<f32>,
    needs: Needs,
) -> HostBatch {
    let (b, t, n) = (windows.len(), batch.t, batch.n);
    let rows = |per: usize| windows.start * per..windows.end * per;
    let material = &batch.material[rows(n)];
    let rest = needs.rest.then(|| {
        let nb = Neighbourhood::build(&first_pos, material, [b, n], |m| m != 0);
        let pairs = nb.weight.iter().sum::<f32>();
        (nb, pairs.max(1.0))
    });
    let liquid = needs.liquid_at.map(|k| {
        let pos: Vec<f32> = (0..b)
            .flat_map(|w| {
                let at = (w * (t + 1) + k) * n * 4;
                frames[at..at + n * 4]
                    .chunks_exact(4)
                    .flat_map(|r| [r[0], r[1]])
                    .collect::<Vec<f32>>()
            })
            .collect();
        let nb = Neighbourhood::build(&pos, material, [b, n], |m| m == 0);
        let particles = nb.inv_d0.iter().filter(|&&v| v > 0.0).count() as f32;
        (nb, particles.max(1.0))
    });
    HostBatch {
        frames,
        dims: [b, t, n],
        counted: b,
        materials: needs.materials,
        rest,
        liquid,
        host: HostRows {
            first_pos,
            material: material.to_vec(),
            dt: batch.dt[rows(1)].to_vec(),
            solver_grid: batch.solver_grid[rows(1)].to_vec(),
        },
    }
}

impl HostBatch {
    /// The windows that count toward the batch: B, or 0 for a padding share.
    pub(super) fn b(&self) -> usize {
        self.counted
    }

    /// This share as a padding share: a data-parallel rank whose batch had fewer windows
    /// than devices still takes the step (every rank must, for the all-reduce and to keep the
    /// replicas equal), on a copy of a window of the batch whose loss counts 0 (its gradient
    /// is zero); the samples seen and the batch's size leave it out.
    pub(super) fn padding(mut self) -> Self {
        self.counted = 0;
        self
    }

    /// The batch on `device` (see [`BatchTensors`]).
    pub(super) fn upload<B: Backend>(self, device: &B::Device) -> BatchTensors<B> {
        let [b, t, n] = self.dims;
        let host = self.host;
        BatchTensors {
            frames: upload(self.frames, [b, t + 1, n, 4], device),
            material: one_hot(&host.material, self.materials, b, n, device),
            dt: upload(host.dt.clone(), [b], device),
            first_pos: upload(host.first_pos.clone(), [b, n, 2], device),
            rest: self.rest.map(|(nb, count)| (nb.upload(device), count)),
            liquid: self.liquid.map(|(nb, count)| (nb.upload(device), count)),
            host,
        }
    }
}

impl<B: Backend> BatchTensors<B> {
    /// `[B, N, 4]`: frame `k` of the window (the target frame last).
    pub(super) fn truth(&self, k: usize) -> Tensor<B, 3> {
        let [b, _, n, _] = self.frames.dims();
        self.frames.clone().narrow(1, k, 1).reshape([b, n, 4])
    }

    /// The loss's units: `dv_scale` (`[1, 1, 2]`) for velocities, `dv_scale dt` (`[B, 1, 2]`)
    /// for positions.
    pub(super) fn scales(&self, config: &GridConfig) -> (Tensor<B, 3>, Tensor<B, 3>) {
        let device = self.frames.device();
        let b = self.frames.dims()[0];
        let dv = Tensor::<B, 1>::from_floats(config.dv_scale, &device).reshape([1, 1, 2]);
        let pos = dv.clone() * self.dt.clone().reshape([b, 1, 1]);
        (dv, pos)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;

    /// `--mirror`: a flagged window's frames and reference positions are mirrored about x =
    /// 1/2 (x -> 1 - x, vx -> -vx, y and vy kept); an unflagged one is uploaded as it is.
    #[test]
    fn mirrored_windows_are_uploaded_mirrored() {
        let (b, t, n) = (2, 2, 3);
        let value = |i: usize| 0.01 * i as f32 + 0.1;
        let batch = Batch {
            b,
            t,
            n,
            inputs: (0..b * t * n * 5).map(value).collect(),
            targets: vec![0.0; b * n * 4],
            last: vec![0.0; b * n * 4],
            target_phys: (0..b * n * 4).map(|i| value(i + 7)).collect(),
            frames: Vec::new(),
            frame_shares: Vec::new(),
            dt: vec![0.016; b],
            material: vec![0; b * n],
            ids: vec![(0, 0); b],
            first_pos: (0..b * n * 2).map(|i| value(i + 3)).collect(),
            solver_grid: vec![None; b],
        };
        let device = Default::default();
        let none = Needs {
            materials: 4,
            ..Needs::default()
        };
        let plain = upload_batch::<NdArray<f32>>(batch.clone(), &[false, false], none, &device);
        let mirrored = upload_batch::<NdArray<f32>>(batch, &[false, true], none, &device);
        let host = |t: Tensor<NdArray<f32>, 4>| t.into_data().to_vec::<f32>().unwrap();
        let (p, m) = (host(plain.frames), host(mirrored.frames));
        let per_window = (t + 1) * n * 4;
        assert_eq!(p[..per_window], m[..per_window], "window 0 is not flagged");
        for (i, (x, y)) in p.iter().zip(&m).enumerate().skip(per_window) {
            let want = match i % 4 {
                0 => 1.0 - x,
                2 => -x,
                _ => *x,
            };
            assert_eq!(*y, want, "value {i}");
        }
        let host3 = |t: Tensor<NdArray<f32>, 3>| t.into_data().to_vec::<f32>().unwrap();
        let (p, m) = (host3(plain.first_pos), host3(mirrored.first_pos));
        assert_eq!(p[..n * 2], m[..n * 2]);
        for (i, (x, y)) in p.iter().zip(&m).enumerate().skip(n * 2) {
            assert_eq!(*y, if i % 2 == 0 { 1.0 - x } else { *x }, "reference {i}");
        }
    }

    /// A data-parallel share prepared in place from the whole batch's rows (the feed's way)
    /// is the share cut out first (`Batch::shards`) and prepared whole: the same frames,
    /// mirroring, rows and neighbourhoods; and a batch of `Layout::Frames`, the same windows
    /// packed, gives the same frames, in place, cut, from each share's own packed frames and
    /// moved whole.
    #[test]
    fn a_share_prepared_in_place_is_the_shard_prepared() {
        let (b, t, n) = (5, 2, 4);
        let (batch, framed) = sample(b, t, n);
        let needs = NEEDS;
        let mirror = [true, false, true, true, false];
        let per = (t + 1) * n * 4;
        let ranges = batch.share_ranges(2);
        assert_eq!(ranges, [0..3, 3..5]);
        let framed_shards = framed.shards(2);
        for ((range, shard), framed_shard) in
            ranges.into_iter().zip(batch.shards(2)).zip(framed_shards)
        {
            let flips = &mirror[range.clone()];
            let in_place = prepare_batch(&batch, range.clone(), flips, needs);
            let cut = prepare_batch(&shard, 0..shard.b, flips, needs);
            let packed = prepare_batch(&framed, range, flips, needs);
            assert_eq!(in_place.dims, cut.dims);
            assert_eq!(in_place.frames, cut.frames);
            assert_eq!(in_place.frames, packed.frames);
            let framed_cut = prepare_batch(&framed_shard, 0..framed_shard.b, flips, needs);
            assert_eq!(in_place.frames, framed_cut.frames);
            assert_eq!(in_place.host.first_pos, packed.host.first_pos);
            assert_same(&in_place, &cut);
        }
        // Each share from its own packed frames (`Layout::Shares`), and the whole batch with
        // its packed frames moved (one share, `prepare_whole`): the same again.
        for range in batch.share_ranges(2) {
            let frames = framed.frames[range.start * per..range.end * per].to_vec();
            let flips = &mirror[range.clone()];
            let share = prepare_packed(&batch, range.clone(), frames, flips, needs);
            let rows = prepare_batch(&batch, range, flips, needs);
            assert_eq!(share.frames, rows.frames);
            assert_same(&share, &rows);
        }
        let whole = prepare_whole(framed, &mirror, needs);
        let rows = prepare_batch(&batch, 0..b, &mirror, needs);
        assert_eq!(whole.frames, rows.frames);
        assert_same(&whole, &rows);
    }

    /// Every neighbourhood and the model's one-hot width of 4.
    const NEEDS: Needs = Needs {
        rest: true,
        liquid_at: Some(1),
        materials: 4,
    };

    /// A batch of `b` windows of `t` frames of `n` particles in the scaled layout (the
    /// identity scaler's: the inputs' first four columns physical), and the same windows in
    /// `Layout::Frames`.
    fn sample(b: usize, t: usize, n: usize) -> (Batch, Batch) {
        let value = |i: usize| ((i * 37) % 101) as f32 * 0.009 + 0.02;
        let batch = Batch {
            b,
            t,
            n,
            inputs: (0..b * t * n * 5).map(value).collect(),
            targets: vec![0.0; b * n * 4],
            last: vec![0.0; b * n * 4],
            target_phys: (0..b * n * 4).map(|i| value(i + 11)).collect(),
            frames: Vec::new(),
            frame_shares: Vec::new(),
            dt: (0..b).map(|w| 0.01 * (w + 1) as f32).collect(),
            material: (0..b * n).map(|i| (i % 3) as u8).collect(),
            ids: (0..b as u32).map(|w| (w, w)).collect(),
            first_pos: (0..b * n * 2).map(|i| value(i + 5)).collect(),
            solver_grid: (0..b as u32).map(Some).collect(),
        };
        let mut framed = batch.clone();
        framed.frames = (0..b)
            .flat_map(|w| {
                let input = &batch.inputs[w * t * n * 5..(w + 1) * t * n * 5];
                let target = &batch.target_phys[w * n * 4..(w + 1) * n * 4];
                (input.chunks_exact(5).flat_map(|r| r[..4].to_vec())).chain(target.to_vec())
            })
            .collect();
        (framed.inputs, framed.target_phys) = (Vec::new(), Vec::new());
        (batch, framed)
    }

    /// The feed's shares of a `Layout::Shares` batch (`prepare_shares`: each share's own
    /// packed frames, its windows' flips) are the scaled batch's shares prepared from its
    /// rows; a batch of fewer windows than devices gets padding shares of its first window,
    /// which count 0.
    #[test]
    fn the_feeds_shares_are_the_rows_prepared() {
        let (t, n) = (2, 4);
        for (b, devices) in [(5, 2), (7, 3), (1, 2), (2, 4)] {
            let (batch, mut shared) = sample(b, t, n);
            let per = (t + 1) * n * 4;
            let ranges = batch.share_ranges(devices);
            shared.frame_shares = (ranges.iter())
                .map(|r| shared.frames[r.start * per..r.end * per].to_vec())
                .collect();
            shared.frames = Vec::new();
            let flips: Vec<bool> = (0..b).map(|w| w % 3 != 1).collect();
            let hosts = super::super::feed::prepare_shares(shared, &flips, devices, NEEDS);
            assert_eq!(hosts.len(), devices);
            for (k, host) in hosts.iter().enumerate() {
                let range = ranges.get(k).cloned().unwrap_or(0..1);
                let rows = prepare_batch(&batch, range.clone(), &flips[range], NEEDS);
                assert_eq!(host.frames, rows.frames, "share {k} of {b} windows");
                assert_same(host, &rows);
                assert_eq!(host.b(), if k < ranges.len() { rows.b() } else { 0 });
            }
        }
    }

    /// `a` and `c` have the same dimensions, host rows and neighbourhoods.
    fn assert_same(a: &HostBatch, c: &HostBatch) {
        assert_eq!(a.dims, c.dims);
        let (a_rows, c_rows) = (&a.host, &c.host);
        assert_eq!(
            (&a_rows.first_pos, &a_rows.material, &a_rows.dt),
            (&c_rows.first_pos, &c_rows.material, &c_rows.dt)
        );
        assert_eq!(a_rows.solver_grid, c_rows.solver_grid);
        for (x, y) in [(&a.rest, &c.rest), (&a.liquid, &c.liquid)] {
            let (x, y) = (x.as_ref().unwrap(), y.as_ref().unwrap());
            assert_eq!(
                (&x.0.index, &x.0.weight, x.1),
                (&y.0.index, &y.0.weight, y.1)
            );
        }
    }
}
