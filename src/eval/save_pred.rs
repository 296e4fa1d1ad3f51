//! `eval --save-pred DIR`: each rollout's predicted frames written as an MCAP bag on
//! `/surrogate/frames`, the node's topic and schema (docs/design.md, "Bags"), so Foxglove,
//! `eval --pred` and any MCAP reader can view and score a rollout that `eval` made offline.
//!
//! Layout: `DIR/<predictor>/<scene>_from<frame>.mcap`, the predictor's name and the scene id as
//! the other files of a scene are named (`eval`'s renders, [`crate::bag::scene_file_stem`]:
//! `multi/rope+snow/001` -> `multi_rope+snow_001`), `<frame>` the `frame_index` of the first
//! predicted frame (a scene rolled out from several starts gets one bag per start). Frames
//! carry the truth's `frame_index` and stamps (`frame_index * dt`), the scene id and its
//! materials. Used by [`super::rollout`].

use std::path::{Path, PathBuf};

use super::render::file_stem;
use super::EvalError;
use crate::bag::{scene_file_stem, BagWriter, PREDICTED_TOPIC};
use crate::data::Trajectory;
use crate::msgs::{split_rows, ParticleFrame};

/// The bag a rollout of `predictor` on `scene` whose first predicted frame is `frame_index`
/// goes to, under `dir`.
pub fn bag_path(dir: &Path, predictor: &str, scene: &str, frame_index: u32) -> PathBuf {
    dir.join(file_stem(predictor))
        .join(format!("{}_from{frame_index}.mcap", scene_file_stem(scene)))
}

/// Writes `frames` (`[N, 4]` physical each; step k predicts trajectory frame `first + k`) of
/// `predictor`'s rollout of `traj` as one bag (see the module doc). A frame that is not a
/// valid message (a non-finite value: the rollout blew up) ends the bag there, with a
/// warning; the frames before it are kept.
///
/// # Errors
/// [`EvalError::Bag`] when the folder or the bag cannot be written.
pub fn write_rollout(
    dir: &Path,
    predictor: &str,
    traj: &Trajectory,
    first: usize,
    frames: &[Vec<f32>],
) -> Result<(), EvalError> {
    let path = bag_path(dir, predictor, &traj.scene, traj.frame_index(first));
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)
            .map_err(|e| crate::bag::BagError::io(parent, "creating the --save-pred folder", e))?;
    }
    let period_ns = (f64::from(traj.dt) * 1e9).round() as u64;
    let mut writer = BagWriter::create(&path)?;
    for (k, state) in frames.iter().enumerate() {
        let (position, velocity) = split_rows(state);
        let frame = ParticleFrame::on_clock(
            traj.scene.clone(),
            traj.frame_index(first + k),
            period_ns,
            position,
            velocity,
            traj.material.clone(),
        );
        if let Err(e) = writer.write(PREDICTED_TOPIC, &frame) {
            tracing::warn!("{}: rollout ends at step {}: {e}", path.display(), k + 1);
            break;
        }
    }
    writer.finish()?;
    Ok(())
}
