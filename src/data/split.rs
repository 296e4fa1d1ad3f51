//! The train / validation / test partition of a dataset, by scene id (the paper's 80:10:10).
//!
//! Input: scene ids (duplicates, e.g. the segments of a scene split at a gap, count once) and a
//! seed. The ids are sorted, shuffled with `ChaCha8Rng::seed_from_u64(seed)`, and cut in
//! order into train, val and test with sizes `round(n * fraction)`; with 3 or more scenes, val
//! and test get at least one scene each (when their fraction is not zero) and train keeps at
//! least one. With fewer than 3 scenes everything is training data (logged). The result
//! depends only on the set of ids and the seed, never on the order they were given in, and
//! all segments of a scene land in the same part. Used by `minflow train` (to fit the scaler on
//! train, stop early on val) and `minflow eval` (to roll out the test scenes).

use std::collections::BTreeSet;

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{DataError, SceneInfo, Trajectory};

/// Fractions of the scenes in each part; normalised by their sum, so `8:1:1` works too.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SplitFractions {
    /// Training fraction (0.8 by default).
    pub train: f64,
    /// Validation fraction (0.1 by default).
    pub val: f64,
    /// Test fraction (0.1 by default).
    pub test: f64,
}

impl Default for SplitFractions {
    fn default() -> Self {
        Self {
            train: 0.8,
            val: 0.1,
            test: 0.1,
        }
    }
}

/// One of the three parts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Part {
    /// Training scenes.
    Train,
    /// Validation scenes (early stopping).
    Val,
    /// Test scenes (metrics).
    Test,
}

/// Scene ids per part, each list sorted.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Split {
    /// Training scene ids.
    pub train: Vec<String>,
    /// Validation scene ids.
    pub val: Vec<String>,
    /// Test scene ids.
    pub test: Vec<String>,
}

impl Split {
    /// The default 80:10:10 split of `scenes` for `seed`.
    pub fn new<S: AsRef<str>>(scenes: impl IntoIterator<Item = S>, seed: u64) -> Split {
        Self::with_fractions(scenes, seed, SplitFractions::default())
            .unwrap_or_else(|_| unreachable!("the default fractions are valid"))
    }

    /// The split of `scenes` for `seed` with the given fractions. Negative, non-finite or
    /// all-zero fractions are an error.
    pub fn with_fractions<S: AsRef<str>>(
        scenes: impl IntoIterator<Item = S>,
        seed: u64,
        fractions: SplitFractions,
    ) -> Result<Split, DataError> {
        let SplitFractions { train, val, test } = fractions;
        let sum = train + val + test;
        if [train, val, test]
            .iter()
            .any(|f| !f.is_finite() || *f < 0.0)
            || sum <= 0.0
        {
            return Err(DataError::config(
                "split fractions",
                format!("{train}:{val}:{test}; each must be >= 0 and their sum > 0"),
            ));
        }
        let ids: BTreeSet<String> = scenes.into_iter().map(|s| s.as_ref().to_owned()).collect();
        let mut ids: Vec<String> = ids.into_iter().collect();
        let n = ids.len();
        if n < 3 {
            tracing::warn!(
                "only {n} scene(s): all are used for training, none for validation or test"
            );
            return Ok(Split {
                train: ids,
                ..Split::default()
            });
        }
        let (n_val, n_test) = part_sizes(n, train / sum, val / sum, test / sum);
        ids.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
        let mut test_ids = ids.split_off(n - n_test);
        let mut val_ids = ids.split_off(n - n_test - n_val);
        ids.sort();
        val_ids.sort();
        test_ids.sort();
        Ok(Split {
            train: ids,
            val: val_ids,
            test: test_ids,
        })
    }

    /// The split of `scenes` that keeps `saved`'s held-out scenes held out: a scene of
    /// `saved.val` (`saved.test`) is a validation (test) scene, every other scene of `scenes` is
    /// a training scene (`train --split-from`: more training data for a model whose validation
    /// and test scenes must stay unseen). Held-out scenes of `saved` that `scenes` lacks are
    /// left out; duplicates count once.
    pub fn keeping_held_out<S: AsRef<str>>(
        saved: &Split,
        scenes: impl IntoIterator<Item = S>,
    ) -> Split {
        let ids: BTreeSet<String> = scenes.into_iter().map(|s| s.as_ref().to_owned()).collect();
        let mut split = Split::default();
        for id in ids {
            match saved.part_of(&id) {
                Some(Part::Val) => split.val.push(id),
                Some(Part::Test) => split.test.push(id),
                _ => split.train.push(id),
            }
        }
        split
    }

    /// Scenes that `self` holds out (validation or test) but `other` trains on: what a model
    /// trained with `other` has seen of this split's held-out scenes.
    pub fn held_out_trained_in(&self, other: &Split) -> Vec<String> {
        self.val
            .iter()
            .chain(&self.test)
            .filter(|s| other.part_of(s) == Some(Part::Train))
            .cloned()
            .collect()
    }

    /// The scene ids of `part`.
    pub fn scenes(&self, part: Part) -> &[String] {
        match part {
            Part::Train => &self.train,
            Part::Val => &self.val,
            Part::Test => &self.test,
        }
    }

    /// Which part `scene` is in, if any.
    pub fn part_of(&self, scene: &str) -> Option<Part> {
        [Part::Train, Part::Val, Part::Test].into_iter().find(|&p| {
            self.scenes(p)
                .binary_search_by(|s| s.as_str().cmp(scene))
                .is_ok()
        })
    }

    /// The trajectories of `part`, in their order in `trajs`.
    pub fn select<'a>(&self, part: Part, trajs: &'a [Trajectory]) -> Vec<&'a Trajectory> {
        trajs
            .iter()
            .filter(|t| self.part_of(&t.scene) == Some(part))
            .collect()
    }

    /// The scenes of `infos` (a scan's index) in `part`, in their order in `infos`.
    pub fn select_infos(&self, part: Part, infos: &[SceneInfo]) -> Vec<SceneInfo> {
        infos
            .iter()
            .filter(|s| self.part_of(&s.scene) == Some(part))
            .cloned()
            .collect()
    }

    /// Moves `trajs` into (train, val, test), keeping their order. Trajectories of scenes in
    /// no part (a split made for another dataset) are dropped with a warning.
    pub fn partition(
        &self,
        trajs: Vec<Trajectory>,
    ) -> (Vec<Trajectory>, Vec<Trajectory>, Vec<Trajectory>) {
        let (mut train, mut val, mut test) = (Vec::new(), Vec::new(), Vec::new());
        for t in trajs {
            match self.part_of(&t.scene) {
                Some(Part::Train) => train.push(t),
                Some(Part::Val) => val.push(t),
                Some(Part::Test) => test.push(t),
                None => tracing::warn!("scene {:?} is in no part of the split; dropped", t.scene),
            }
        }
        (train, val, test)
    }
}

/// (val, test) sizes for `n >= 3` scenes and normalised fractions: rounded, at least one each
/// when the fraction is positive, leaving at least one training scene when train's is.
fn part_sizes(n: usize, train: f64, val: f64, test: f64) -> (usize, usize) {
    let size = |f: f64| {
        let k = (n as f64 * f).round() as usize;
        if f > 0.0 {
            k.max(1)
        } else {
            k
        }
    };
    let (mut n_val, mut n_test) = (size(val), size(test));
    let min_train = usize::from(train > 0.0);
    let floor = |f: f64| usize::from(f > 0.0);
    while n_val + n_test + min_train > n {
        if n_val >= n_test && n_val > floor(val) {
            n_val -= 1;
        } else if n_test > floor(test) {
            n_test -= 1;
        } else {
            n_val -= 1;
        }
    }
    (n_val, n_test)
}
