//! `eval`: rollout metrics, tables, plots and renders of surrogates against the ground truth
//! (docs/design.md, "Metrics"; the paper's Tables 2 and 3 and Figures 1, 4, 7, 8, 9).
//!
//! - [`metrics`]: [`FrameMetrics`] of one predicted frame (MSE over scaled x, y, vx, vy, per
//!   channel, per material, physical units, physics diagnostics) and the density map.
//! - [`predictor`]: the [`Predictor`] trait, the baselines [`Persist`] and [`ConstVel`], and
//!   [`ModelPredictor`] (a run folder on the CPU backend).
//! - [`rollout`]: direct evaluation: every predictor rolled out from ground-truth seeds of
//!   each trajectory ([`evaluate`]).
//! - [`replay`]: scoring a bag of predicted frames (from a running surrogate node) against the
//!   ground truth, matched by scene and `frame_index` ([`read_predictions`],
//!   [`score_predictions`]).
//! - [`table`]: the Markdown and CSV tables (Tables 2/3 layout and the detailed metrics).
//! - [`render`]: particle renders (PNG grid and animated GIF) and the per-scene MSE curves.
//! - [`output`]: writes all of them into one folder ([`output::write_all`]).
//! - [`save_pred`]: each rollout's predicted frames as an MCAP bag (`eval --save-pred`).
//! - [`plausibility`]: what the MSE hides, at probe steps ([`plausibility::Plausibility`]:
//!   Sinkhorn divergence, strain error, kinetic energy, and the two below, per material).
//! - [`structure`]: volume ratio, intact fraction and connectivity of a predicted frame, and
//!   the solids' rest neighbours ([`structure::Neighbours`]).
//! - [`conservation`]: each body's centre-of-mass error and the momentum drift.
//! - [`probe_table`]: the plausibility tables (`table.md`'s sections, `plausibility.csv`).
//! - [`front`]: the liquid's surge front against time and the step it reaches the far wall.
//!
//! Both ways of evaluating produce one [`Evaluation`]: per scene and per predictor a
//! [`Curve`] of per-step metrics, step `k` = the k-th predicted frame (k = 1 is the frame
//! right after the seed frames). Scaling rule, the same everywhere: the first model's stored
//! scaler when a model is given, otherwise a scaler fitted on the training split (seeded
//! 80:10:10 split, as `minflow train`) of the ground-truth data. Used by `minflow eval` and
//! `minflow report`.

pub mod conservation;
pub mod front;
pub mod metrics;
pub mod output;
pub mod plausibility;
pub mod predictor;
pub mod probe_table;
pub mod render;
pub mod replay;
pub mod rollout;
pub mod save_pred;
pub mod structure;
pub mod table;

use std::path::PathBuf;

pub use metrics::{
    density_map, frame_metrics, metric_names, FrameMetrics, MATERIALS, METRIC_COUNT,
};
pub use plausibility::Plausibility;
pub use predictor::{ConstVel, CpuInfer, ModelPredictor, Persist, Predictor, ReferenceFrom};
pub use replay::{read_predictions, score_predictions, Predictions, ReplayOptions};
pub use rollout::{evaluate, start_offsets, RolloutOptions};

use crate::data::Scaler;

/// Every way evaluating can fail.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A run folder could not be loaded.
    #[error("loading model {dir}: {what}")]
    Model {
        /// Run folder.
        dir: PathBuf,
        /// What failed.
        what: String,
    },
    /// A model refused a trajectory (particle count, shapes).
    #[error("{predictor} on scene {scene:?}: {what}")]
    Rollout {
        /// Predictor (column) name.
        predictor: String,
        /// Scene id.
        scene: String,
        /// What failed.
        what: String,
    },
    /// Reading bags failed.
    #[error(transparent)]
    Data(#[from] crate::data::DataError),
    /// Reading a predictions bag failed.
    #[error(transparent)]
    Bag(#[from] crate::bag::BagError),
    /// Predicted and true frames of a scene do not fit together.
    #[error("scene {scene:?}, frame {frame}: {what}")]
    Mismatch {
        /// Scene id.
        scene: String,
        /// `frame_index`.
        frame: u32,
        /// What differs.
        what: String,
    },
    /// Nothing could be scored (no trajectory long enough, no matching frames).
    #[error("nothing to evaluate: {0}")]
    Empty(String),
    /// Writing an output file failed.
    #[error("{path}: {what}")]
    Output {
        /// File.
        path: PathBuf,
        /// What failed.
        what: String,
    },
}

/// Per-step metrics of one predictor on one scene, averaged over the scene's rollouts.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Curve {
    /// Step `k` (1-based) at index `k - 1`; `None` where nothing was scored (frame missing
    /// from a predictions bag, no ground truth, trajectory too short).
    pub steps: Vec<Option<FrameMetrics>>,
}

impl Curve {
    /// Mean over the scored steps (the paper's `avg20` for a 20-step horizon); `None` when no
    /// step was scored. Missing steps are left out, never counted as zero error.
    pub fn avg(&self) -> Option<FrameMetrics> {
        let present: Vec<FrameMetrics> = self.steps.iter().flatten().copied().collect();
        FrameMetrics::mean(&present)
    }

    /// The last step of the horizon (the paper's `f20`); `None` when it was not scored.
    pub fn last(&self) -> Option<FrameMetrics> {
        self.steps.last().copied().flatten()
    }

    /// Steps scored.
    pub fn scored(&self) -> usize {
        self.steps.iter().flatten().count()
    }
}

/// Frames kept for the renders of one scene: step 0 (the last seed frame) to the horizon.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Snapshots {
    /// N material ids.
    pub material: Vec<u8>,
    /// Ground truth `[N, 4]` at steps 0..=H (`None` where absent).
    pub truth: Vec<Option<Vec<f32>>>,
    /// Per predictor (in [`Evaluation::predictors`] order), `[N, 4]` at steps 0..=H; step 0
    /// is the seed frame itself.
    pub preds: Vec<Vec<Option<Vec<f32>>>>,
}

/// The results of one scene (a table row, a plot panel).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SceneResult {
    /// Scene id.
    pub scene: String,
    /// Rollouts averaged into the curves (start frames x segments).
    pub rollouts: usize,
    /// One curve per predictor, in [`Evaluation::predictors`] order.
    pub curves: Vec<Curve>,
    /// Per predictor: steps with ground truth but no predicted frame (predictions bags
    /// only), excluded from the scores.
    pub missing: Vec<usize>,
    /// Predicted frames with no ground-truth frame to compare with, excluded.
    pub unmatched: usize,
    /// Predicted frames past the horizon, not scored.
    pub beyond: usize,
    /// Frames for the renders (the first rollout).
    pub snapshots: Option<Snapshots>,
    /// The liquid's surge front over the first rollout, truth and each predictor (None
    /// without liquid; [`front::Fronts`]).
    pub fronts: Option<front::Fronts>,
    /// Per predictor: the mean plausibility at each probe of its rollouts (empty when not
    /// scored: predictions bags, `--no-plausibility`).
    pub probes: Vec<Vec<(Probe, Plausibility)>>,
}

/// Where a rollout's plausibility is probed: after a fixed number of steps, or at the
/// rollout's last step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Probe {
    /// Step k (1-based).
    Step(usize),
    /// The rollout's last step (the scene's end with `--horizon full`).
    End,
}

impl std::fmt::Display for Probe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Probe::Step(k) => write!(f, "{k}"),
            Probe::End => f.write_str("end"),
        }
    }
}

/// Everything an evaluation measured.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// Predictor (column) names: models first, then `persist` and `constvel`.
    pub predictors: Vec<String>,
    /// Steps predicted per rollout (H; with `full`, the longest rollout's).
    pub horizon: usize,
    /// Rolled out to each trajectory's end (`--horizon full`): the blocks are `avg_full` and
    /// `f_full`, each scene's last step its own.
    pub full: bool,
    /// The scaler defining the scaled features.
    pub scaler: Scaler,
    /// Where the scaler comes from (for the report).
    pub scaler_source: String,
    /// Per scene, sorted by scene id.
    pub scenes: Vec<SceneResult>,
    /// Things worth telling (short trajectories, missing frames, skipped scenes).
    pub notes: Vec<String>,
    /// Per predictor: how far its constraint projection moved each material over the
    /// rollouts (None for predictors without one).
    pub corrections: Vec<Option<crate::model::constraints::Correction>>,
}

impl Evaluation {
    /// The table's block names: `avgH` and `fH` (the paper's `avg20` and `f20`), or
    /// `avg_full` and `f_full` for whole-scene rollouts.
    pub fn block_names(&self) -> (String, String) {
        if self.full {
            ("avg_full".into(), "f_full".into())
        } else {
            table::block_names(self.horizon)
        }
    }

    /// Total steps missing from predictions, over scenes and predictors.
    pub fn missing(&self) -> usize {
        self.scenes.iter().flat_map(|s| &s.missing).sum()
    }

    /// The same evaluation restricted to the scenes `keep` accepts (the report's Table 2
    /// keeps `fluid/` scenes, Table 3 `multi/` ones); the "Average" row follows.
    pub fn subset(&self, keep: impl Fn(&str) -> bool) -> Evaluation {
        let mut out = self.clone();
        out.scenes.retain(|s| keep(&s.scene));
        out
    }

    /// Per predictor, the mean over scenes of each scene's mean over steps (`avg` block,
    /// "Average" row) and of its last step (`f` block); scenes where it was not scored are
    /// left out.
    pub fn averages(&self) -> Vec<(Option<FrameMetrics>, Option<FrameMetrics>)> {
        (0..self.predictors.len())
            .map(|p| {
                let avgs: Vec<_> = self
                    .scenes
                    .iter()
                    .filter_map(|s| s.curves[p].avg())
                    .collect();
                let lasts: Vec<_> = self
                    .scenes
                    .iter()
                    .filter_map(|s| s.curves[p].last())
                    .collect();
                (FrameMetrics::mean(&avgs), FrameMetrics::mean(&lasts))
            })
            .collect()
    }
}

/// Per-step accumulator: all scored frames of one predictor on one scene.
#[derive(Debug, Clone, Default)]
pub(crate) struct StepSums {
    pub steps: Vec<Vec<FrameMetrics>>,
}

impl StepSums {
    pub fn new(horizon: usize) -> Self {
        Self {
            steps: vec![Vec::new(); horizon],
        }
    }

    pub fn curve(&self) -> Curve {
        Curve {
            steps: self.steps.iter().map(|s| FrameMetrics::mean(s)).collect(),
        }
    }
}
