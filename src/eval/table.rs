//! The tables of an [`Evaluation`]: the paper's Tables 2 and 3 layout as Markdown and CSV
//! (rows = scenes and their average, column blocks `avgH` (mean MSE over steps 1..H) and `fH`
//! (MSE at step H), one column per model and baseline, the lowest value of each row and block
//! in bold), a detailed Markdown summary (per channel, per material, physical units, physics
//! diagnostics, missing frames, notes) and `metrics.csv`, every metric at every step in long
//! format. MSE values are dimensionless (scaled features); see [`super::metrics`] for the
//! units of the others. Used by `minflow eval` and `minflow report`.

use std::fmt::Write;

use super::{metric_names, Evaluation, FrameMetrics};
use crate::material;

/// Block names for a horizon H: `avgH` and `fH` (the paper's `avg20` and `f20`).
pub fn block_names(horizon: usize) -> (String, String) {
    (format!("avg{horizon}"), format!("f{horizon}"))
}

/// One table row: (label, the `avg` block's values, the `f` block's values), per predictor.
type Row = (String, Vec<Option<f64>>, Vec<Option<f64>>);

/// Rows of the main table for `metric`: one per scene, then "Average".
fn rows(eval: &Evaluation, metric: &dyn Fn(&FrameMetrics) -> f64) -> Vec<Row> {
    let mut out: Vec<Row> = eval
        .scenes
        .iter()
        .map(|s| {
            (
                s.scene.clone(),
                s.curves
                    .iter()
                    .map(|c| c.avg().map(|m| metric(&m)))
                    .collect(),
                s.curves
                    .iter()
                    .map(|c| c.last().map(|m| metric(&m)))
                    .collect(),
            )
        })
        .collect();
    let averages = eval.averages();
    out.push((
        "Average".into(),
        averages
            .iter()
            .map(|(a, _)| a.map(|m| metric(&m)))
            .collect(),
        averages
            .iter()
            .map(|(_, f)| f.map(|m| metric(&m)))
            .collect(),
    ));
    out
}

/// Index of the smallest finite value.
fn best(values: &[Option<f64>]) -> Option<usize> {
    values
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.filter(|v| v.is_finite()).map(|v| (i, v)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

fn cell(v: Option<f64>, bold: bool) -> String {
    match v {
        Some(v) if bold => format!("**{v:.3e}**"),
        Some(v) => format!("{v:.3e}"),
        None => "n/a".into(),
    }
}

/// The Tables 2/3 layout of the MSE over scaled (x, y, vx, vy) as Markdown.
pub fn markdown(eval: &Evaluation) -> String {
    markdown_of(eval, &|m| m.mse)
}

/// The Tables 2/3 layout of any per-frame `metric` as Markdown.
pub fn markdown_of(eval: &Evaluation, metric: &dyn Fn(&FrameMetrics) -> f64) -> String {
    let (avg, last) = eval.block_names();
    let mut s = String::from("| Scene |");
    for block in [&avg, &last] {
        for p in &eval.predictors {
            let _ = write!(s, " {block} {p} |");
        }
    }
    s.push_str("\n| --- |");
    s.push_str(&" ---: |".repeat(2 * eval.predictors.len()));
    s.push('\n');
    for (label, a, f) in rows(eval, metric) {
        let label = if label == "Average" {
            "**Average**".to_owned()
        } else {
            format!("`{label}`")
        };
        let _ = write!(s, "| {label} |");
        for values in [&a, &f] {
            let b = best(values);
            for (i, v) in values.iter().enumerate() {
                let _ = write!(s, " {} |", cell(*v, b == Some(i)));
            }
        }
        s.push('\n');
    }
    s
}

/// The Tables 2/3 layout as CSV: `scene,avgH_<p>...,fH_<p>...`, full precision, empty where
/// not scored; the last row is `Average`.
pub fn csv(eval: &Evaluation) -> String {
    let (avg, last) = eval.block_names();
    let mut s = String::from("scene");
    for block in [&avg, &last] {
        for p in &eval.predictors {
            let _ = write!(s, ",{}", csv_field(&format!("{block}_{p}")));
        }
    }
    s.push('\n');
    for (label, a, f) in rows(eval, &|m| m.mse) {
        s.push_str(&csv_field(&label));
        for v in a.iter().chain(&f) {
            s.push(',');
            if let Some(v) = v {
                let _ = write!(s, "{v:e}");
            }
        }
        s.push('\n');
    }
    s
}

/// Quotes a CSV field when it holds a comma or a quote.
pub(super) fn csv_field(s: &str) -> String {
    if s.contains([',', '"']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_owned()
    }
}

/// Every metric at every step, long format:
/// `scene,predictor,step,rollouts,<metric_names()...>`; steps not scored are left out.
pub fn metrics_csv(eval: &Evaluation) -> String {
    let mut s = String::from("scene,predictor,step,rollouts");
    for name in metric_names() {
        let _ = write!(s, ",{name}");
    }
    s.push('\n');
    for scene in &eval.scenes {
        for (p, curve) in eval.predictors.iter().zip(&scene.curves) {
            for (k, m) in curve.steps.iter().enumerate() {
                let Some(m) = m else { continue };
                let _ = write!(
                    s,
                    "{},{},{},{}",
                    csv_field(&scene.scene),
                    csv_field(p),
                    k + 1,
                    scene.rollouts
                );
                for v in m.values() {
                    if v.is_finite() {
                        let _ = write!(s, ",{v:e}");
                    } else {
                        s.push(',');
                    }
                }
                s.push('\n');
            }
        }
    }
    s
}

/// The detailed summary: per predictor, the `avgH` of every metric averaged over scenes,
/// then missing frames per scene and the notes.
pub fn details(eval: &Evaluation) -> String {
    let (avg, _) = eval.block_names();
    let mut s = String::new();
    let averages = eval.averages();
    let fmt = |v: f64| {
        if v.is_finite() {
            format!("{v:.3e}")
        } else {
            "n/a".into()
        }
    };
    let _ = writeln!(
        s,
        "Per channel, per material and in physical units ({avg}, mean over scenes; MSE of \
         scaled features unless marked phys):\n"
    );
    let _ = write!(s, "| predictor | pos | vel |");
    for m in material::names() {
        let _ = write!(s, " {m} |");
    }
    s.push_str(" phys pos (domain units^2) | phys vel ((units/time)^2) |\n| --- |");
    s.push_str(&" ---: |".repeat(4 + material::COUNT));
    s.push('\n');
    for (p, (a, _)) in eval.predictors.iter().zip(&averages) {
        let v = a.unwrap_or_else(FrameMetrics::absent);
        let _ = write!(s, "| {p} | {} | {} |", fmt(v.mse_pos), fmt(v.mse_vel));
        for m in v.mse_material {
            let _ = write!(s, " {} |", fmt(m.unwrap_or(f64::NAN)));
        }
        let _ = writeln!(s, " {} | {} |", fmt(v.phys_pos), fmt(v.phys_vel));
    }
    let _ = writeln!(
        s,
        "\nPhysics diagnostics ({avg}, mean over scenes): kinetic-energy error |KE - KE*| \
         (KE = 1/2 mean |v|^2), centre-of-mass error (domain units), density-map MSE \
         (G x G tent splat, `--density-grid`, default 32; mean 1), particles outside the \
         unit square per frame:\n"
    );
    s.push_str("| predictor | KE error | CoM error | density error | outside |\n");
    s.push_str("| --- | ---: | ---: | ---: | ---: |\n");
    for (p, (a, _)) in eval.predictors.iter().zip(&averages) {
        let v = a.unwrap_or_else(FrameMetrics::absent);
        let _ = writeln!(
            s,
            "| {p} | {} | {} | {} | {:.1} |",
            fmt(v.ke_err),
            fmt(v.com_err),
            fmt(v.density_err),
            v.outside
        );
    }
    s.push_str(&missing_and_notes(eval));
    s
}

/// The summary's last part: missing predicted frames per scene and the notes.
fn missing_and_notes(eval: &Evaluation) -> String {
    let mut s = String::new();
    let missing: Vec<String> = eval
        .scenes
        .iter()
        .filter(|sc| sc.missing.iter().any(|&m| m > 0) || sc.unmatched > 0)
        .map(|sc| {
            format!(
                "| `{}` | {} | {} |",
                sc.scene,
                sc.missing.iter().sum::<usize>(),
                sc.unmatched
            )
        })
        .collect();
    if !missing.is_empty() {
        s.push_str(
            "\nMissing predicted frames (excluded from every score) and predicted frames \
             without ground truth:\n\n| scene | missing | unmatched |\n| --- | ---: | ---: |\n",
        );
        for line in missing {
            let _ = writeln!(s, "{line}");
        }
    }
    if !eval.notes.is_empty() {
        s.push_str("\nNotes:\n\n");
        for n in &eval.notes {
            let _ = writeln!(s, "- {n}");
        }
    }
    s
}
