//! Writes everything an [`Evaluation`] produced into one folder: `table.md` (the Tables 2/3
//! layout of the MSE, then the detailed summary), `table.csv`, `metrics.csv` (every metric at
//! every step), `plausibility.csv` (when probed), `front.csv` and `front_<scene>.png` (the liquid's surge
//! front, [`super::front`]), `mse_curves.png` (per-scene MSE curves) and,
//! per scene with snapshots, `render_<scene>.png` and `render_<scene>.gif` (ground truth beside
//! each model). Used by `minflow eval` and `minflow report`.

use std::path::{Path, PathBuf};

use super::render::{file_stem, mse_curves, render_gif, render_grid};
use super::{front, probe_table, table, EvalError, Evaluation};

/// Writes the tables and figures of `eval` into `dir` (created if needed). The first
/// `models` predictors are rendered beside the ground truth (the baselines after them are
/// not). `title` heads `table.md`. Returns the files written.
pub fn write_all(
    dir: &Path,
    eval: &Evaluation,
    models: usize,
    title: &str,
    progress: &indicatif::ProgressBar,
) -> Result<Vec<PathBuf>, EvalError> {
    let err = |path: &Path, e: std::io::Error| EvalError::Output {
        path: path.to_path_buf(),
        what: e.to_string(),
    };
    std::fs::create_dir_all(dir).map_err(|e| err(dir, e))?;
    let mut files = Vec::new();
    let mut write = |name: &str, text: String| -> Result<(), EvalError> {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(|e| err(&path, e))?;
        files.push(path);
        Ok(())
    };
    let (avg, last) = eval.block_names();
    let steps = if eval.full {
        "mean over each rollout's steps to the scene's end".to_owned()
    } else {
        format!(
            "mean over steps 1..{h} ({avg}) and at step {h} ({last})",
            h = eval.horizon
        )
    };
    let fronts = front::fronts(eval);
    let md = format!(
        "# {title}\n\nMSE over scaled (x, y, vx, vy) ({}), {steps}; the lowest value of each \
         row and block in bold.\n\n{}\n{}{}{}",
        eval.scaler_source,
        table::markdown(eval),
        table::details(eval),
        probe_table::markdown(eval),
        front::markdown(eval, &fronts),
    );
    write("table.md", md)?;
    write("table.csv", table::csv(eval))?;
    write("metrics.csv", table::metrics_csv(eval))?;
    if eval.scenes.iter().any(|s| !s.probes.is_empty()) {
        write("plausibility.csv", probe_table::csv(eval))?;
    }
    files.extend(front::write(dir, eval, &fronts)?);
    let curves = dir.join("mse_curves.png");
    mse_curves(&curves, eval)?;
    files.push(curves);
    let rendered: Vec<_> = eval
        .scenes
        .iter()
        .filter_map(|s| s.snapshots.as_ref().map(|snap| (s, snap)))
        .collect();
    progress.set_length(rendered.len() as u64);
    progress.set_position(0);
    for (scene, snap) in rendered {
        let stem = format!("render_{}", file_stem(&scene.scene));
        let png = dir.join(format!("{stem}.png"));
        render_grid(&png, eval, snap, models)?;
        let gif = dir.join(format!("{stem}.gif"));
        render_gif(&gif, eval, snap, models)?;
        files.extend([png, gif]);
        progress.inc(1);
    }
    Ok(files)
}
