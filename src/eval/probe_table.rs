//! The plausibility tables of an [`Evaluation`] ([`super::plausibility`]): per predictor and
//! probe step, the Sinkhorn divergence per material and the strain error per solid, then the
//! structure (volume ratio, intact fraction, rope connectivity, kinetic energy), the
//! conservation diagnostics (centre-of-mass error, momentum drift), each the
//! mean over the scenes that have the material, and how far each model's constraint
//! projection moved each material. Markdown for `table.md`, CSV (one row per scene,
//! predictor, probe and material) for `plausibility.csv`. Used by [`super::output`].

use std::collections::BTreeSet;
use std::fmt::Write;

use super::table::csv_field;
use super::{Evaluation, Probe};
use crate::material;
use crate::model::grid::rest::REST_NEIGHBOURS;

/// The probes any scene was scored at, in order.
fn probes(eval: &Evaluation) -> BTreeSet<Probe> {
    eval.scenes
        .iter()
        .flat_map(|s| s.probes.iter().flatten().map(|(probe, _)| *probe))
        .collect()
}

/// Mean over scenes of `value` for predictor `p` at `probe` and material `m`.
fn mean_over_scenes(
    eval: &Evaluation,
    p: usize,
    probe: Probe,
    value: impl Fn(&super::Plausibility) -> Option<f64>,
) -> Option<f64> {
    let all: Vec<f64> = eval
        .scenes
        .iter()
        .filter_map(|s| s.probes.get(p))
        .filter_map(|per| per.iter().find(|(q, _)| *q == probe))
        .filter_map(|(_, v)| value(v))
        .collect();
    (!all.is_empty()).then(|| all.iter().sum::<f64>() / all.len() as f64)
}

/// The Markdown section, empty when nothing was probed.
pub fn markdown(eval: &Evaluation) -> String {
    let probes = probes(eval);
    if probes.is_empty() {
        return String::new();
    }
    let fmt = |v: Option<f64>| v.map_or("n/a".to_owned(), |v| format!("{v:.3e}"));
    let mut s = format!(
        "\nPlausibility, order-independent (mean over scenes). Sinkhorn divergence of the \
         position clouds per material (domain units^2; blur 0.02, at most 256 particles per \
         material) and strain error of the solids (mean |d_pred / d_0 - d_true / d_0| over \
         each particle's {REST_NEIGHBOURS} nearest neighbours of the rollout's first frame; 0 \
         for a rigid motion), at step k of the rollouts (`end`: each rollout's last step):\n\n",
    );
    s.push_str("| predictor | step |");
    for m in material::names() {
        let _ = write!(s, " sinkhorn {m} |");
    }
    for m in material::names().skip(1) {
        let _ = write!(s, " strain {m} |");
    }
    s.push_str("\n| --- | --- |");
    s.push_str(&" ---: |".repeat(2 * material::COUNT - 1));
    s.push('\n');
    for (p, name) in eval.predictors.iter().enumerate() {
        for &probe in &probes {
            let _ = write!(s, "| {name} | {probe} |");
            for m in 0..material::COUNT {
                let v = mean_over_scenes(eval, p, probe, |x| x.sinkhorn[m]);
                let _ = write!(s, " {} |", fmt(v));
            }
            for m in 1..material::COUNT {
                let v = mean_over_scenes(eval, p, probe, |x| x.strain[m]);
                let _ = write!(s, " {} |", fmt(v));
            }
            s.push('\n');
        }
    }
    s.push_str(&structure_markdown(eval, &probes));
    s.push_str(&conservation_markdown(eval, &probes));
    s.push_str(&correction_markdown(eval));
    s
}

/// The projection section of [`markdown`]: per predictor that projects its frames, the mean
/// move of each material per particle and frame, in particle spacings of the scene's rest
/// frame (empty when no predictor projects).
fn correction_markdown(eval: &Evaluation) -> String {
    if eval.corrections.iter().all(Option::is_none) {
        return String::new();
    }
    let mut s = String::from(
        "\nConstraint projection: mean move per particle and predicted frame, in particle \
         spacings of the scene's rest frame (how far the network's own step was from the \
         material's constraints):\n\n| predictor |",
    );
    for m in material::names() {
        let _ = write!(s, " {m} |");
    }
    s.push_str("\n| --- |");
    s.push_str(&" ---: |".repeat(material::COUNT));
    s.push('\n');
    for (name, c) in eval.predictors.iter().zip(&eval.corrections) {
        if let Some(c) = c {
            let _ = write!(s, "| {name} |");
            for m in 0..material::COUNT {
                let v = c.mean(m).map_or("n/a".to_owned(), |v| format!("{v:.3}"));
                let _ = write!(s, " {v} |");
            }
            s.push('\n');
        }
    }
    s
}

/// The structure section of [`markdown`]: per predictor and probe, the volume ratio of each
/// material, the intact fraction of each solid and the share of the rope in its largest
/// piece, the truth's own value in brackets ([`super::structure`]).
fn structure_markdown(eval: &Evaluation, probes: &BTreeSet<Probe>) -> String {
    let fmt = |v: Option<f64>| v.map_or("n/a".to_owned(), |v| format!("{v:.3}"));
    let mut s = format!(
        "\nStructure (mean over scenes): volume = area covered on a 64 x 64 grid, prediction / \
         truth; intact = share of the solids' rest-neighbour pairs ({REST_NEIGHBOURS} nearest of \
         the rollout's first frame) within 1.5x their rest distance, rope connected = share of \
         the rope in its largest intact piece, prediction (truth); energy = kinetic energy \
         summed over the rollout's frames up to the step, prediction / truth:\n\n| predictor \
         | step |",
    );
    for m in material::names() {
        let _ = write!(s, " volume {m} |");
    }
    for m in material::names().skip(1) {
        let _ = write!(s, " intact {m} |");
    }
    s.push_str(" rope connected | energy |\n| --- | --- |");
    s.push_str(&" ---: |".repeat(2 * material::COUNT + 1));
    s.push('\n');
    let rope = usize::from(material::Material::Rope.id());
    s.push_str(&probe_rows(eval, probes, |mean| {
        let mut row = String::new();
        for m in 0..material::COUNT {
            let _ = write!(row, " {} |", fmt(mean(&|x| x.volume[m])));
        }
        let pair = |pred: Option<f64>, truth: Option<f64>| match (pred, truth) {
            (Some(_), _) => format!("{} ({})", fmt(pred), fmt(truth)),
            _ => "n/a".to_owned(),
        };
        for m in 1..material::COUNT {
            let v = pair(mean(&|x| x.intact[m]), mean(&|x| x.intact_truth[m]));
            let _ = write!(row, " {v} |");
        }
        let v = pair(
            mean(&|x| x.connected[rope]),
            mean(&|x| x.connected_truth[rope]),
        );
        let _ = write!(row, " {v} | {} |", fmt(mean(&|x| x.energy_all)));
        row
    }));
    s
}

/// The mean over scenes of a plausibility value, for one predictor at one probe.
type Mean<'a> = dyn Fn(&dyn Fn(&super::Plausibility) -> Option<f64>) -> Option<f64> + 'a;

/// One Markdown row per predictor and probe: `| predictor | probe |` and the cells `cells`
/// writes from that predictor's [`Mean`] at that probe.
fn probe_rows(
    eval: &Evaluation,
    probes: &BTreeSet<Probe>,
    cells: impl Fn(&Mean<'_>) -> String,
) -> String {
    let mut s = String::new();
    for (p, name) in eval.predictors.iter().enumerate() {
        for &probe in probes {
            let mean = |f: &dyn Fn(&super::Plausibility) -> Option<f64>| {
                mean_over_scenes(eval, p, probe, f)
            };
            let _ = writeln!(s, "| {name} | {probe} |{}", cells(&mean));
        }
    }
    s
}

/// The conservation section of [`markdown`]: per predictor and probe, the centre-of-mass
/// error of each material's bodies and the momentum drift, the truth's own in brackets
/// ([`super::conservation`]).
fn conservation_markdown(eval: &Evaluation, probes: &BTreeSet<Probe>) -> String {
    let fmt = |v: Option<f64>| v.map_or("n/a".to_owned(), |v| format!("{v:.3e}"));
    let mut s = String::from(
        "\nConservation (mean over scenes): com = distance between the predicted and the true \
         centre of mass of each body of the rollout's first frame, mean over the material's \
         bodies (domain units); momentum drift = mean over the frames with no particle within \
         0.08 of a wall (per free axis) of |change of the mean velocity - g dt| (domain units \
         per time unit per frame; MPM conserves momentum there), prediction (truth):\n\n\
         | predictor | step |",
    );
    for m in material::names() {
        let _ = write!(s, " com {m} |");
    }
    s.push_str(" momentum drift |\n| --- | --- |");
    s.push_str(&" ---: |".repeat(material::COUNT + 1));
    s.push('\n');
    s.push_str(&probe_rows(eval, probes, |mean| {
        let mut row = String::new();
        for m in 0..material::COUNT {
            let _ = write!(row, " {} |", fmt(mean(&|x| x.com[m])));
        }
        let (pred, truth) = (mean(&|x| x.momentum), mean(&|x| x.momentum_truth));
        let _ = write!(row, " {} ({}) |", fmt(pred), fmt(truth));
        row
    }));
    s
}

/// `scene,predictor,probe,material,sinkhorn,strain,volume,intact,intact_truth,connected,
/// connected_truth,energy,com,momentum,momentum_truth`, one row per scored material (empty
/// cells where a value does not apply; `momentum` and `momentum_truth` are the scene's,
/// repeated on each of its rows).
pub fn csv(eval: &Evaluation) -> String {
    let mut s = String::from(
        "scene,predictor,probe,material,sinkhorn,strain,volume,intact,intact_truth,connected,\
         connected_truth,energy,com,momentum,momentum_truth\n",
    );
    let cell = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:e}"));
    for scene in &eval.scenes {
        for (name, per) in eval.predictors.iter().zip(&scene.probes) {
            for (probe, v) in per {
                for (m, material) in material::names().enumerate() {
                    if v.sinkhorn[m].is_none() && v.strain[m].is_none() {
                        continue;
                    }
                    let _ = writeln!(
                        s,
                        "{},{},{probe},{material},{},{},{},{},{},{},{},{},{},{},{}",
                        csv_field(&scene.scene),
                        csv_field(name),
                        cell(v.sinkhorn[m]),
                        cell(v.strain[m]),
                        cell(v.volume[m]),
                        cell(v.intact[m]),
                        cell(v.intact_truth[m]),
                        cell(v.connected[m]),
                        cell(v.connected_truth[m]),
                        cell(v.energy[m]),
                        cell(v.com[m]),
                        cell(v.momentum),
                        cell(v.momentum_truth),
                    );
                }
            }
        }
    }
    s
}
