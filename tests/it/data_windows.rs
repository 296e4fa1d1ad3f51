//! Windows and batches: counts per segment, batch contents equal to the scaled (and physical)
//! frames at the right frame indices for T = 1, 2, 3, no window across a gap, deterministic
//! shuffling per (seed, epoch), mixed particle counts batched separately, and the grid
//! trainer's layout of physical frames.

use std::collections::HashMap;

use crate::data_support::{same_bits, simulate, state_of, synthetic, write_bag};
use minflow::data::{self, DataError, Layout, Scaler, Trajectory, WindowIndex};
use minflow::msgs::ParticleFrame;

/// Scene 6 whole (12 frames) and scene 7 without frame 6 (segments of 6 and 5 frames), loaded
/// from a bag; plus the written frames by (scene, frame_index).
fn dataset() -> (Vec<Trajectory>, HashMap<(String, u32), ParticleFrame>) {
    let mut written = simulate(6, 12);
    written.extend(simulate(7, 12).into_iter().filter(|f| f.frame_index != 6));
    let dir = crate::tmp::tempdir().expect("tempdir");
    let bag = dir.path().join("d.mcap");
    write_bag(&bag, &written);
    let (trajs, report) = data::load(&[bag], None).expect("load");
    assert_eq!(report.gaps.len(), 1);
    let by_index = written
        .into_iter()
        .map(|f| ((f.scene.clone(), f.frame_index), f))
        .collect();
    (trajs, by_index)
}

fn index(trajs: &[Trajectory], t: usize) -> WindowIndex {
    let refs: Vec<&Trajectory> = trajs.iter().collect();
    WindowIndex::new(trajs.to_vec(), t, Scaler::fit(&refs)).expect("index")
}

fn order(index: &WindowIndex, seed: Option<u64>, epoch: u64) -> Vec<(u32, u32)> {
    index.batches(4, seed, epoch).flat_map(|b| b.ids).collect()
}

#[test]
fn one_window_per_frame_beyond_t_in_each_segment() {
    let (trajs, _) = dataset();
    let frames: Vec<usize> = trajs.iter().map(|t| t.frames).collect();
    let mut sorted = frames.clone();
    sorted.sort_unstable();
    assert_eq!(sorted, [5, 6, 12]);
    for (t, expected) in [(1, 20), (2, 17), (3, 14)] {
        let index = index(&trajs, t);
        assert_eq!(index.len(), expected);
        assert_eq!(index.len(), frames.iter().map(|f| f - t).sum::<usize>());
    }
    let index = index(&trajs, 12);
    assert!(index.is_empty());
    assert_eq!(index.batches(8, None, 0).count(), 0);
}

#[test]
fn batches_hold_the_scaled_frames_at_the_right_indices() {
    let (trajs, written) = dataset();
    for t in 1..=3 {
        let index = index(&trajs, t);
        let scaler = *index.scaler();
        let batches: Vec<_> = index.batches(5, None, 0).collect();
        let sizes: Vec<usize> = batches.iter().map(|b| b.b).collect();
        assert_eq!(
            sizes.iter().sum::<usize>(),
            index.len(),
            "the partial last batch is kept"
        );
        assert!(sizes[..sizes.len() - 1].iter().all(|&s| s == 5));
        let ids: Vec<_> = batches.iter().flat_map(|b| b.ids.clone()).collect();
        assert_eq!(ids, index.window_ids(), "unshuffled: index order");
        for batch in &batches {
            let (n, row) = (batch.n, batch.n * 4);
            assert_eq!(
                (batch.t, n, batch.inputs.len()),
                (t, 2500, batch.b * t * n * 5)
            );
            for (b, &(traj, start)) in batch.ids.iter().enumerate() {
                let traj = &trajs[traj as usize];
                let first = traj.start_index + start;
                // Looked up among the frames written: a window over the gap would miss one.
                let frame = |fi: u32| &written[&(traj.scene.clone(), fi)];
                for k in 0..t {
                    let f = frame(first + k as u32);
                    let mut expect = Vec::new();
                    scaler.scale_into(&state_of(f), &f.material, &mut expect);
                    let at = (b * t + k) * n * 5;
                    assert!(
                        same_bits(&batch.inputs[at..at + n * 5], &expect),
                        "input {k}"
                    );
                }
                let target = frame(first + t as u32);
                let last = frame(first + t as u32 - 1);
                let mut expect = Vec::new();
                scaler.scale_state_into(&state_of(target), &mut expect);
                let span = b * row..(b + 1) * row;
                assert!(same_bits(&batch.targets[span.clone()], &expect));
                assert!(same_bits(
                    &batch.target_phys[span.clone()],
                    &state_of(target)
                ));
                assert!(same_bits(&batch.last[span], &state_of(last)));
                assert_eq!(batch.dt[b], target.dt);
                assert_eq!(&batch.material[b * n..(b + 1) * n], &target.material[..]);
                // The reference positions: the segment's first frame.
                let at_start = state_of(frame(traj.start_index));
                let pos0: Vec<f32> = (at_start.chunks_exact(4))
                    .flat_map(|r| [r[0], r[1]])
                    .collect();
                assert!(same_bits(
                    &batch.first_pos[b * n * 2..(b + 1) * n * 2],
                    &pos0
                ));
            }
        }
    }
}

/// `Layout::Frames` (the grid trainer's): each window's input frames and target, physical,
/// written frame by frame, where the scaled layout has them only as scaled inputs, `last` and
/// `target_phys`; the rest of the batch is the scaled layout's, in the same order.
#[test]
fn the_frames_layout_holds_the_physical_frames_of_each_window() {
    let (trajs, written) = dataset();
    for t in 1..=3 {
        let scaled = index(&trajs, t);
        let framed = index(&trajs, t).with_layout(Layout::Frames);
        for (a, b) in scaled
            .batches(5, Some(3), 1)
            .zip(framed.batches(5, Some(3), 1))
        {
            let (n, per) = (b.n, (t + 1) * b.n * 4);
            assert_eq!(b.frames.len(), b.b * per);
            assert!(b.inputs.is_empty() && b.targets.is_empty());
            assert!(b.last.is_empty() && b.target_phys.is_empty() && a.frames.is_empty());
            assert_eq!(
                (&a.ids, &a.dt, &a.material, &a.first_pos, &a.solver_grid),
                (&b.ids, &b.dt, &b.material, &b.first_pos, &b.solver_grid)
            );
            for (w, &(traj, start)) in b.ids.iter().enumerate() {
                let traj = &trajs[traj as usize];
                for k in 0..=t {
                    let f = &written[&(traj.scene.clone(), traj.start_index + start + k as u32)];
                    let at = w * per + k * n * 4;
                    assert!(
                        same_bits(&b.frames[at..at + n * 4], &state_of(f)),
                        "frame {k}"
                    );
                }
                let span = w * n * 4..(w + 1) * n * 4;
                let last = w * per + (t - 1) * n * 4;
                assert!(same_bits(
                    &b.frames[last..last + n * 4],
                    &a.last[span.clone()]
                ));
                assert!(same_bits(
                    &b.frames[last + n * 4..(w + 1) * per],
                    &a.target_phys[span]
                ));
            }
        }
    }
}

/// `Layout::Shares(k)` (the grid trainer's on k devices): each share's vector holds the
/// `Layout::Frames` batch's rows of the windows of its range, bit for bit, and nothing else of
/// the batch differs.
#[test]
fn the_shares_layout_cuts_the_frames_into_the_shares() {
    let (trajs, _) = dataset();
    let t = 2;
    let framed = index(&trajs, t).with_layout(Layout::Frames);
    for k in [2, 3, 8] {
        let shared = index(&trajs, t).with_layout(Layout::frames_for(k));
        for (a, b) in framed
            .batches(5, Some(3), 1)
            .zip(shared.batches(5, Some(3), 1))
        {
            let per = (t + 1) * a.n * 4;
            let ranges = a.share_ranges(k);
            assert!(b.frames.is_empty() && b.inputs.is_empty());
            assert_eq!(b.frame_shares.len(), ranges.len());
            for (range, share) in ranges.into_iter().zip(&b.frame_shares) {
                assert!(same_bits(
                    share,
                    &a.frames[range.start * per..range.end * per]
                ));
            }
            assert_eq!(
                (&a.ids, &a.dt, &a.material, &a.first_pos, &a.solver_grid),
                (&b.ids, &b.dt, &b.material, &b.first_pos, &b.solver_grid)
            );
            let cut = |x: &data::Batch| x.shards(k).into_iter().map(|s| s.frames);
            assert!(
                cut(&a).eq(cut(&b)),
                "a Shares batch cuts as its Frames batch does"
            );
        }
    }
}

#[test]
fn no_window_spans_the_gap() {
    let (trajs, _) = dataset();
    let index = index(&trajs, 3);
    let gapped = &trajs
        .iter()
        .find(|t| t.start_index == 7)
        .expect("second segment")
        .scene;
    for (traj, start) in index.window_ids() {
        let t = &trajs[traj as usize];
        let frames: Vec<u32> = (0..=3).map(|k| t.frame_index(start as usize + k)).collect();
        assert!(start as usize + 3 < t.frames);
        if &t.scene == gapped {
            assert!(
                !frames.contains(&6),
                "window {frames:?} spans the missing frame 6"
            );
        }
    }
}

#[test]
fn shuffling_is_deterministic_per_seed_and_epoch() {
    let (trajs, _) = dataset();
    let index = index(&trajs, 2);
    let mut sorted = index.window_ids();
    sorted.sort_unstable();
    let a = order(&index, Some(1), 0);
    assert_eq!(
        a,
        order(&index, Some(1), 0),
        "same (seed, epoch), same order"
    );
    assert_ne!(a, order(&index, Some(1), 1), "epochs differ");
    assert_ne!(a, order(&index, Some(2), 0), "seeds differ");
    assert_ne!(a, sorted, "shuffled");
    for (seed, epoch) in [(1, 0), (1, 1), (2, 0), (7, 99)] {
        let mut o = order(&index, Some(seed), epoch);
        o.sort_unstable();
        assert_eq!(o, sorted, "every window once per epoch");
    }
    assert_eq!(order(&index, None, 3), index.window_ids());
}

#[test]
fn mixed_particle_counts_are_batched_separately() {
    let (mut trajs, _) = dataset();
    let small: Vec<_> = (0..10).map(|k| synthetic("small/000", k, 50, 1)).collect();
    let dir = crate::tmp::tempdir().expect("tempdir");
    let bag = dir.path().join("small.mcap");
    write_bag(&bag, &small);
    trajs.extend(data::load(&[bag], None).expect("load").0);
    let index = index(&trajs, 2);
    assert_eq!(index.particle_counts(), [50, 2500]);
    let batches: Vec<_> = index.batches(3, Some(4), 0).collect();
    assert_eq!(batches.len(), index.num_batches(3));
    assert_eq!(batches.len(), 8usize.div_ceil(3) + 17usize.div_ceil(3));
    let mut seen = Vec::new();
    for b in &batches {
        assert!(b.ids.iter().all(|&(t, _)| trajs[t as usize].n == b.n));
        assert_eq!(
            (b.inputs.len(), b.material.len()),
            (b.b * 2 * b.n * 5, b.b * b.n)
        );
        seen.extend(b.ids.iter().copied());
    }
    seen.sort_unstable();
    assert_eq!(seen, index.window_ids());
    let ns: Vec<usize> = batches.iter().map(|b| b.n).collect();
    assert!(ns.windows(2).any(|w| w[0] != w[1]));
}

#[test]
fn t_zero_is_an_error() {
    let err = WindowIndex::new(Vec::new(), 0, Scaler::default()).expect_err("T = 0");
    assert!(matches!(err, DataError::Config { .. }), "{err}");
}
