//! Weight averaging (`minflow::model::average`, `minflow average`): every parameter of the
//! result is the weighted mean of the sources' (against the parameters read back one by
//! one), networks of another shape are refused, and the command writes a run folder that
//! loads, with the first model's `model.json` and `split.json` and `average.json` naming the
//! sources; its bad flags are usage errors before any file is written. `train
//! --keep-epochs` keeps the epochs it averages.

use std::path::Path;
use std::process::Command;

use burn::backend::NdArray;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;
use minflow::model::average::{average, AverageError};
use minflow::model::grid::{GridModel, MemoryKind};
use minflow::model::store::{Net, RunFolder};
use minflow::train::grid::initial_grid_model;

use crate::json;
use crate::model_support::{meta, tiny_grid};

type B = NdArray<f32>;

/// Every float parameter of `net`, flattened, in visiting order.
fn params<M: Module<B>>(net: &M) -> Vec<Vec<f32>> {
    struct Flat(Vec<Vec<f32>>);
    impl<Bk: Backend> ModuleVisitor<Bk> for Flat {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<Bk, D>>) {
            self.0
                .push(p.val().into_data().convert::<f32>().to_vec().unwrap());
        }
    }
    let mut flat = Flat(Vec::new());
    net.visit(&mut flat);
    flat.0
}

/// The tiny grid network with fresh weights drawn from `seed`.
fn net(seed: u64) -> GridModel<B> {
    initial_grid_model::<B>(&tiny_grid(MemoryKind::MinGru), seed, &Default::default()).unwrap()
}

/// Asserts that `got` is `wa * a + wb * b` element by element.
fn assert_mix(got: &[Vec<f32>], a: &[Vec<f32>], b: &[Vec<f32>], wa: f32, wb: f32) {
    assert_eq!(got.len(), a.len());
    for ((g, a), b) in got.iter().zip(a).zip(b) {
        for ((g, a), b) in g.iter().zip(a).zip(b) {
            let want = wa * a + wb * b;
            assert!(
                (g - want).abs() <= 1e-6 * (1.0 + want.abs()),
                "{g} against {want}"
            );
        }
    }
}

#[test]
fn averaged_parameters_are_the_weighted_means() {
    // Each network drawn once and cloned: burn's CPU generator is one per process, so a
    // second draw of a seed may differ while other tests draw (src/train/mod.rs).
    let (one, two) = (net(1), net(2));
    let (a, b) = (params(&one), params(&two));
    assert!(a
        .iter()
        .flatten()
        .zip(b.iter().flatten())
        .any(|(x, y)| x != y));
    let mean = average(vec![one.clone(), two.clone()], None).unwrap();
    assert_mix(&params(&mean), &a, &b, 0.5, 0.5);
    // Weights are normalised: 3 and 1 are 0.75 and 0.25.
    let weighted = average(vec![one.clone(), two], Some(&[3.0, 1.0])).unwrap();
    assert_mix(&params(&weighted), &a, &b, 0.75, 0.25);
    // A network averaged with itself is itself.
    let same = average(vec![one.clone(), one.clone(), one], None).unwrap();
    assert_mix(&params(&same), &a, &a, 1.0, 0.0);
}

#[test]
fn networks_of_another_shape_or_bad_weights_are_refused() {
    let wider = (tiny_grid(MemoryKind::MinGru)).with_latent(8);
    let wider = initial_grid_model::<B>(&wider, 1, &Default::default()).unwrap();
    let err = average(vec![net(1), wider], None).unwrap_err();
    assert!(matches!(err, AverageError::Shape { index: 1, .. }), "{err}");
    let err = average(vec![net(1), net(2)], Some(&[1.0])).unwrap_err();
    assert!(matches!(err, AverageError::Input(_)), "{err}");
    let err = average(vec![net(1), net(2)], Some(&[0.0, 0.0])).unwrap_err();
    assert!(matches!(err, AverageError::Input(_)), "{err}");
    let err = average(Vec::<GridModel<B>>::new(), None).unwrap_err();
    assert!(matches!(err, AverageError::Input(_)), "{err}");
}

/// A run folder of the tiny network drawn from `seed` (its `model.json` at epoch `seed`),
/// with a `split.json`.
fn folder(dir: &Path, seed: u64, latent: usize) {
    let config = tiny_grid(MemoryKind::MinGru).with_latent(latent);
    let model = initial_grid_model::<B>(&config, seed, &Default::default()).unwrap();
    let meta = minflow::model::store::ModelMeta {
        epoch: seed as usize,
        ..meta(config)
    };
    RunFolder::new(dir).save(&model, &meta).unwrap();
    let split = r#"{"train": ["a"], "val": ["b"], "test": ["c"]}"#;
    std::fs::write(dir.join("split.json"), split).unwrap();
}

fn minflow(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn average_command_writes_a_model_that_loads() {
    let tmp = crate::tmp::tempdir().unwrap();
    let dir = |name: &str| tmp.path().join(name);
    let s = |p: &Path| p.to_str().unwrap().to_string();
    folder(&dir("a"), 1, 4);
    folder(&dir("b"), 2, 4);
    folder(&dir("wide"), 3, 8);
    let (a, b, out) = (s(&dir("a")), s(&dir("b")), s(&dir("out")));
    let o = minflow(&[
        "average", "--model", &a, "--model", &b, "--weight", "1", "--weight", "3", "--out", &out,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let load = |d: &Path| match RunFolder::new(d).load::<B>(&Default::default()).unwrap().0 {
        Net::Grid(m) => params(&m),
        Net::Paper(_) => panic!("a grid model was saved"),
    };
    assert_mix(
        &load(&dir("out")),
        &load(&dir("a")),
        &load(&dir("b")),
        0.25,
        0.75,
    );
    assert_eq!(
        json(&dir("out").join("split.json")),
        json(&dir("a").join("split.json"))
    );
    // The first model's model.json (its epoch), not the second's.
    assert_eq!(json(&dir("out").join("model.json"))["epoch"], 1);
    let sources = json(&dir("out").join("average.json"));
    assert_eq!(sources["averaged"][1]["weight"], 0.75);
    assert_eq!(sources["averaged"][0]["model"], a.as_str());
    // Bad flags: usage errors (exit 2) before anything is written.
    let refused = s(&dir("refused"));
    for args in [
        vec!["average", "--model", &a, "--out", &refused],
        vec![
            "average", "--model", &a, "--model", &b, "--weight", "1", "--out", &refused,
        ],
        vec![
            "average",
            "--model",
            &a,
            "--model",
            &b,
            "--weight=-1",
            "--weight",
            "1",
            "--out",
            &refused,
        ],
        vec![
            "average", "--model", &a, "--model", &b, "--weight", "0", "--weight", "0", "--out",
            &refused,
        ],
        vec!["average", "--model", &a, "--model", &b, "--out", &a],
    ] {
        let o = minflow(&args);
        assert_eq!(
            o.status.code(),
            Some(2),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    // Another network: an error naming the folder.
    let wide = s(&dir("wide"));
    let o = minflow(&[
        "average", "--model", &a, "--model", &wide, "--out", &refused,
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("latent: 4 in the first, 8 here"), "{err}");
    assert!(
        !dir("refused").exists(),
        "a refused average wrote its folder"
    );
    let kept = json(&dir("a").join("split.json"));
    assert_eq!(kept["val"][0], "b", "--out a touched a's split.json");
}

/// `train --keep-epochs 2` keeps the last two epochs as run folders `epochs/NNNN` (each
/// with its epoch's `model.json` and the run's `split.json`, its weights those of that
/// epoch's checkpoint), `minflow average` takes them, and a resumed run with
/// `--keep-epochs 1` keeps only its last.
#[test]
fn kept_epochs_are_run_folders_that_average() {
    let tmp = crate::tmp::tempdir().unwrap();
    let run = tmp.path().join("run");
    let kept = run.join("epochs");
    let names = || {
        let mut names: Vec<String> = (std::fs::read_dir(&kept).unwrap())
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        names
    };
    let args = ["--epochs", "3", "--model", "mingru", "--keep-epochs", "2"];
    let o = crate::cli_train::train_grid(&run, &args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(names(), ["0002", "0003"]);
    let weights = |dir: &Path| std::fs::read(dir.join("model.mpk")).unwrap();
    for (name, epoch, checkpoint) in [("0002", 2, "checkpoint.old"), ("0003", 3, "checkpoint")] {
        assert_eq!(json(&kept.join(name).join("model.json"))["epoch"], epoch);
        assert_eq!(
            json(&kept.join(name).join("split.json")),
            json(&run.join("split.json"))
        );
        assert_eq!(
            weights(&kept.join(name)),
            weights(&run.join(checkpoint)),
            "{name}"
        );
    }
    let out = tmp.path().join("mean");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (a, b) = (s(&kept.join("0002")), s(&kept.join("0003")));
    let o = minflow(&["average", "--model", &a, "--model", &b, "--out", &s(&out)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(RunFolder::new(&out).load::<B>(&Default::default()).is_ok());
    let args = [
        "--epochs",
        "4",
        "--model",
        "mingru",
        "--keep-epochs",
        "1",
        "--resume",
    ];
    let o = crate::cli_train::train_grid(&run, &args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(names(), ["0004"]);
}
