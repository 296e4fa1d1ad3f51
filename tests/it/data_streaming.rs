//! Streaming a dataset larger than memory: under a frame budget smaller than the dataset, one
//! epoch yields exactly the windows (ids and contents) of the in-memory index and never holds
//! more than the budget; when everything fits, the batches are those of `WindowIndex`; the
//! streamed scaler equals the in-memory one; scenes over budget and bags changed since the
//! scan are errors.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use crate::data_support::{same_bits, simulate, write_bag};
use minflow::data::{
    self, Batch, DataError, Layout, Scaler, SceneInfo, Split, StreamingLoader, Trajectory,
    WindowIndex,
};

const T: usize = 2;

/// Scenes 10..16 (12 frames each, scene 12 without frame 4) over four bags, scene 13 split
/// across two of them: 71 frames.
fn dataset(dir: &Path) -> Vec<PathBuf> {
    let s: Vec<_> = (10..16).map(|id| simulate(id, 12)).collect();
    let interleaved: Vec<_> = s[0].iter().zip(&s[1]).flat_map(|(a, b)| [a, b]).collect();
    write_bag(&dir.join("a.mcap"), interleaved);
    let gapped = s[2].iter().filter(|f| f.frame_index != 4);
    write_bag(&dir.join("b.mcap"), gapped.chain(&s[3][..6]));
    write_bag(&dir.join("c.mcap"), s[3][6..].iter().chain(&s[4]));
    write_bag(&dir.join("d.mcap"), &s[5]);
    vec![dir.to_path_buf()]
}

fn fit(trajs: &[Trajectory]) -> Scaler {
    Scaler::fit(&trajs.iter().collect::<Vec<_>>())
}

fn epoch_ids(loader: &mut StreamingLoader, seed: Option<u64>, epoch: u64) -> Vec<(u32, u32)> {
    let batches = loader.epoch(4, seed, epoch).expect("epoch");
    batches.flat_map(|b| b.expect("batch").ids).collect()
}

fn sorted(mut ids: Vec<(u32, u32)>) -> Vec<(u32, u32)> {
    ids.sort_unstable();
    ids
}

/// Inputs and targets of every window, by id, from batches of one.
fn contents(index: &WindowIndex) -> HashMap<(u32, u32), Batch> {
    index.batches(1, None, 0).map(|b| (b.ids[0], b)).collect()
}

#[test]
fn under_budget_one_epoch_yields_the_windows_of_the_in_memory_index() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let inputs = dataset(dir.path());
    let infos = data::scan(&inputs, None).expect("scan");
    let (trajs, _) = data::load(&inputs, None).expect("load");
    let scaler = fit(&trajs);
    let memory = WindowIndex::new(trajs, T, scaler).expect("index");
    let expected = sorted(memory.window_ids());
    assert_eq!(expected.len(), 5 * 10 + 2 + 5);
    let by_id = contents(&memory);
    for budget in [12, 30, 50] {
        let mut loader =
            StreamingLoader::new(infos.clone(), None, T, scaler, budget).expect("loader");
        assert!(!loader.fits() && loader.total_frames() == 71);
        assert_eq!(
            (loader.len(), loader.particle_counts()),
            (expected.len(), vec![2500])
        );
        for epoch in 0..3 {
            let ids = epoch_ids(&mut loader, Some(11), epoch);
            assert_eq!(
                sorted(ids.clone()),
                expected,
                "budget {budget}, epoch {epoch}"
            );
            assert_eq!(
                ids,
                epoch_ids(&mut loader, Some(11), epoch),
                "deterministic"
            );
            assert_ne!(
                ids,
                epoch_ids(&mut loader, Some(11), epoch + 1),
                "epochs differ"
            );
        }
        assert_eq!(sorted(epoch_ids(&mut loader, None, 0)), expected);
        let peak = loader.peak_resident_frames();
        assert!(
            peak > 0 && peak <= budget,
            "peak {peak} frames, budget {budget}"
        );
        // Same contents as the in-memory batches, window by window.
        for batch in loader.epoch(3, Some(5), 0).expect("epoch") {
            let batch = batch.expect("batch");
            let (n, t) = (batch.n, batch.t);
            for (b, id) in batch.ids.iter().enumerate() {
                let one = &by_id[id];
                let (inp, row) = (t * n * 5, n * 4);
                assert!(same_bits(
                    &batch.inputs[b * inp..(b + 1) * inp],
                    &one.inputs
                ));
                assert!(same_bits(
                    &batch.targets[b * row..(b + 1) * row],
                    &one.targets
                ));
                assert!(same_bits(&batch.last[b * row..(b + 1) * row], &one.last));
                assert_eq!(batch.dt[b], one.dt[0]);
            }
        }
    }
}

#[test]
fn when_everything_fits_it_behaves_like_the_window_index() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let inputs = dataset(dir.path());
    let infos = data::scan(&inputs, None).expect("scan");
    let (trajs, _) = data::load(&inputs, None).expect("load");
    let scaler = fit(&trajs);
    let memory = WindowIndex::new(trajs, T, scaler).expect("index");
    // In each layout: the paper's, and the grid trainer's on one device and on two.
    for layout in [Layout::Scaled, Layout::Frames, Layout::Shares(2)] {
        let memory = memory.clone().with_layout(layout);
        let mut loader = (StreamingLoader::new(infos.clone(), None, T, scaler, 71))
            .expect("loader")
            .with_layout(layout);
        assert!(loader.fits());
        for epoch in 0..2 {
            let streamed: Vec<Batch> = (loader.epoch(4, Some(3), epoch).expect("epoch"))
                .collect::<Result<_, _>>()
                .expect("batches");
            let direct: Vec<Batch> = memory.batches(4, Some(3), epoch).collect();
            assert!(
                streamed == direct,
                "{layout:?}, epoch {epoch}: batches differ"
            );
        }
        assert_eq!(loader.peak_resident_frames(), 71);
    }
}

#[test]
fn training_scenes_only_with_a_streamed_scaler() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let inputs = dataset(dir.path());
    let infos = data::scan(&inputs, None).expect("scan");
    let (trajs, _) = data::load(&inputs, None).expect("load");
    let split = Split::new(infos.iter().map(|i| &i.scene), 2);
    assert_eq!(
        (split.train.len(), split.val.len(), split.test.len()),
        (4, 1, 1)
    );
    let train_infos: Vec<SceneInfo> = infos
        .into_iter()
        .filter(|i| split.train.contains(&i.scene))
        .collect();
    let (train, _, _) = split.partition(trajs);
    let scaler = StreamingLoader::fit_scaler(train_infos.clone(), None, 24).expect("fit");
    assert_eq!(scaler, fit(&train));
    let memory = WindowIndex::new(train, T, scaler).expect("index");
    let mut loader = StreamingLoader::new(train_infos, None, T, scaler, 24).expect("loader");
    assert_eq!(
        sorted(epoch_ids(&mut loader, Some(1), 0)),
        sorted(memory.window_ids())
    );
    assert!(loader.peak_resident_frames() <= 24);
}

#[test]
fn a_scene_over_budget_is_an_error() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let infos = data::scan(&dataset(dir.path()), None).expect("scan");
    let err = StreamingLoader::new(infos, None, T, Scaler::default(), 11).expect_err("too small");
    match &err {
        DataError::SceneTooLarge {
            frames: 12,
            budget: 11,
            ..
        } => {}
        other => panic!("wrong error: {other}"),
    }
    assert!(err.to_string().contains("at least 12"), "{err}");
}

#[test]
fn bags_changed_since_the_scan_are_reported() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let inputs = dataset(dir.path());
    let infos = data::scan(&inputs, None).expect("scan");
    let frames = simulate(15, 12);
    write_bag(
        &dir.path().join("d.mcap"),
        frames.iter().filter(|f| f.frame_index != 5),
    );
    let mut loader = StreamingLoader::new(infos, None, T, Scaler::default(), 30).expect("loader");
    let results: Vec<_> = loader.epoch(4, Some(1), 0).expect("epoch").collect();
    let err = results
        .last()
        .expect("something")
        .as_ref()
        .expect_err("the last item is the error");
    match err {
        DataError::Changed { scene, .. } => assert_eq!(scene, &frames[0].scene),
        other => panic!("wrong error: {other}"),
    }
    assert_eq!(results.iter().filter(|r| r.is_err()).count(), 1);
}

/// An epoch started after `skip` batches yields the rest of the full epoch's batches, in its
/// order, for every skip (chunks wholly before it unread); an epoch iterator dropped early
/// and continued from where it stopped yields the same; with the next chunk read ahead the
/// loader still holds at most its budget.
#[test]
fn an_epoch_resumes_at_any_batch() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let infos = data::scan(&dataset(dir.path()), None).expect("scan");
    for budget in [12, 30, 71] {
        let mut loader = StreamingLoader::new(infos.clone(), None, T, Scaler::default(), budget)
            .expect("loader");
        let full: Vec<Vec<(u32, u32)>> = (loader.epoch(3, Some(9), 2).expect("epoch"))
            .map(|b| b.expect("batch").ids)
            .collect();
        for skip in 0..=full.len() {
            let tail: Vec<Vec<(u32, u32)>> = (loader.epoch_from(3, Some(9), 2, skip))
                .expect("epoch")
                .map(|b| b.expect("batch").ids)
                .collect();
            assert_eq!(tail, full[skip..], "budget {budget}, skip {skip}");
        }
        // Taken in stretches of 2 batches, each a new iterator continuing the last.
        let mut stretches = Vec::new();
        for start in (0..full.len()).step_by(2) {
            let batches = loader.epoch_from(3, Some(9), 2, start).expect("epoch");
            stretches.extend(batches.take(2).map(|b| b.expect("batch").ids));
        }
        assert_eq!(stretches, full, "budget {budget}: continued in stretches");
        let peak = loader.peak_resident_frames();
        assert!(
            peak > 0 && peak <= budget,
            "peak {peak} frames, budget {budget}"
        );
    }
}
