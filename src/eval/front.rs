//! The liquid's surge front over a rollout, prediction beside truth: the dam-break measure of
//! the solver's own check 5 (docs/mpm.md; Martin & Moyce 1952, "An experimental study of the
//! collapse of liquid columns on a rigid horizontal plane"), taken on every scene with
//! liquid. A collapsing column or splash spreads along the floor; its front is how far the
//! liquid has got towards the far wall, the wall farther from the liquid's centre of mass in
//! the rollout's first frame. The front is the [`FRONT_RANK`]-th most advanced liquid
//! particle along that axis (a few splashed droplets are not the front), in domain units
//! from the start wall.
//!
//! The liquid has reached the far wall at the first step its front comes within
//! [`REACH_SLACK`] of the truth's furthest front over the rollout (the liquid against the
//! wall, wherever the solver's walls stop it). A prediction reaches it at its own step, or
//! never. Computed on each scene's first rollout (the whole scene under `--horizon full`) by
//! [`super::rollout`], written by [`write`] as `front.csv` (the front at every step) and
//! `front_<scene>.png` (the front against time), and summarised by [`markdown`] in
//! `table.md`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::render::file_stem;
use super::table::csv_field;
use super::{EvalError, Evaluation};
use crate::material::Material;
use crate::plot::{line_chart, Series};

/// The front is the k-th most advanced liquid particle (as the solver's dam-break check).
pub const FRONT_RANK: usize = 5;
/// A front within this distance of the truth's furthest one has reached the far wall
/// (domain units): one cell of the 64 x 64 grid.
pub const REACH_SLACK: f32 = 1.0 / 64.0;

/// The direction a scene's liquid spreads in: towards the wall at x = 1 (`+1`) or x = 0
/// (`-1`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Towards(pub i8);

impl Towards {
    /// The far wall of `frame` (`[N, 4]` physical): the one farther from the liquid's centre
    /// of mass; None without liquid.
    pub fn far_wall(frame: &[f32], material: &[u8]) -> Option<Self> {
        let liquid = Material::Liquid.id();
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (row, &m) in frame.chunks_exact(4).zip(material) {
            if m == liquid {
                sum += f64::from(row[0]);
                n += 1;
            }
        }
        (n > 0).then(|| Towards(if sum / n as f64 <= 0.5 { 1 } else { -1 }))
    }

    /// The front of `frame`: the [`FRONT_RANK`]-th largest distance of a liquid particle
    /// from the start wall (domain units); the farthest particle when fewer; None without
    /// liquid.
    pub fn front(self, frame: &[f32], material: &[u8]) -> Option<f32> {
        let liquid = Material::Liquid.id();
        let mut d: Vec<f32> = frame
            .chunks_exact(4)
            .zip(material)
            .filter(|(_, &m)| m == liquid)
            .map(|(row, _)| if self.0 > 0 { row[0] } else { 1.0 - row[0] })
            .collect();
        if d.is_empty() {
            return None;
        }
        let k = (FRONT_RANK - 1).min(d.len() - 1);
        d.select_nth_unstable_by(k, |a, b| b.total_cmp(a));
        Some(d[k])
    }

    /// The fronts of a rollout: `start` (`[N, 4]`, step 0) then `frames` (steps 1..).
    pub fn series<'a>(
        self,
        start: &'a [f32],
        frames: impl Iterator<Item = &'a [f32]>,
        material: &[u8],
    ) -> Vec<Option<f32>> {
        std::iter::once(start)
            .chain(frames)
            .map(|f| self.front(f, material))
            .collect()
    }
}

/// One scene's fronts: per step, the truth's and each predictor's (None where a frame is
/// missing).
#[derive(Clone, Debug, PartialEq)]
pub struct Fronts {
    /// The scene.
    pub scene: String,
    /// Where the liquid spreads.
    pub towards: Towards,
    /// `[H + 1]` the truth's front at steps 0..=H.
    pub truth: Vec<Option<f32>>,
    /// Per predictor, `[H + 1]`.
    pub preds: Vec<Vec<Option<f32>>>,
}

impl Fronts {
    /// The front at which the far wall counts as reached: the truth's furthest less
    /// [`REACH_SLACK`].
    pub fn wall(&self) -> Option<f32> {
        let max = self.truth.iter().flatten().copied().reduce(f32::max)?;
        Some(max - REACH_SLACK)
    }

    /// The first step at which `series` reaches [`Fronts::wall`]; None when it never does.
    pub fn reach(&self, series: &[Option<f32>]) -> Option<usize> {
        let wall = self.wall()?;
        series.iter().position(|f| f.is_some_and(|f| f >= wall))
    }
}

/// The fronts of every scene of `eval` with liquid (its first rollout's).
pub fn fronts(eval: &Evaluation) -> Vec<Fronts> {
    eval.scenes
        .iter()
        .filter_map(|s| s.fronts.clone())
        .collect()
}

/// `table.md`'s section: per scene with liquid, the step the truth's front reaches the far
/// wall and each predictor's, with its ratio to the truth's. Empty without such scenes.
pub fn markdown(eval: &Evaluation, all: &[Fronts]) -> String {
    if all.is_empty() {
        return String::new();
    }
    let mut s = String::from(
        "\n## Surge front\n\nStep at which the liquid's front (its 5th most advanced particle) \
         reaches the far wall, prediction (over the truth's step); `never` when it does not \
         within the rollout (`front.csv`, `front_<scene>.png`).\n\n| scene | truth |",
    );
    for p in &eval.predictors {
        let _ = write!(s, " {p} |");
    }
    s.push_str("\n| --- | ---: |");
    s.push_str(&" ---: |".repeat(eval.predictors.len()));
    for f in all {
        let truth = f.reach(&f.truth);
        let cell = |k: Option<usize>| k.map_or("never".to_owned(), |k| k.to_string());
        let _ = write!(s, "\n| {} | {} |", f.scene, cell(truth));
        for p in &f.preds {
            let k = f.reach(p);
            let ratio = match (k, truth) {
                (Some(k), Some(t)) if t > 0 => format!(" ({:.2})", k as f64 / t as f64),
                _ => String::new(),
            };
            let _ = write!(s, " {}{ratio} |", cell(k));
        }
    }
    s.push('\n');
    s
}

/// Writes `front.csv` (`scene,predictor,step,front`: the truth as predictor `truth`) and one
/// `front_<scene>.png` per scene into `dir` (each series drawn while its front is inside the
/// box, 0..=1); returns the files written.
pub fn write(dir: &Path, eval: &Evaluation, all: &[Fronts]) -> Result<Vec<PathBuf>, EvalError> {
    let mut files = Vec::new();
    if all.is_empty() {
        return Ok(files);
    }
    let mut csv = String::from("scene,predictor,step,front\n");
    let names = std::iter::once("truth").chain(eval.predictors.iter().map(String::as_str));
    for f in all {
        let series = std::iter::once(&f.truth).chain(&f.preds);
        for (name, values) in names.clone().zip(series) {
            for (k, v) in values.iter().enumerate() {
                if let Some(v) = v {
                    let _ = writeln!(csv, "{},{},{k},{v}", csv_field(&f.scene), csv_field(name));
                }
            }
        }
    }
    let path = dir.join("front.csv");
    std::fs::write(&path, csv).map_err(|e| EvalError::Output {
        path: path.clone(),
        what: e.to_string(),
    })?;
    files.push(path);
    for f in all {
        let series: Vec<Series> = names
            .clone()
            .zip(std::iter::once(&f.truth).chain(&f.preds))
            .map(|(name, values)| Series {
                name: name.to_owned(),
                points: values
                    .iter()
                    .enumerate()
                    // A front outside the box (`constvel` flies through the walls) would
                    // stretch the axis over the box's own fronts: drawn while inside.
                    .filter_map(|(k, v)| {
                        v.filter(|v| (0.0..=1.0).contains(v))
                            .map(|v| (k as f64, f64::from(v)))
                    })
                    .collect(),
            })
            .collect();
        let path = dir.join(format!("front_{}.png", file_stem(&f.scene)));
        let title = format!("{}: surge front", f.scene);
        line_chart(
            &path,
            &title,
            "step",
            "front (domain units from the start wall)",
            &series,
            false,
            (900, 520),
        )
        .map_err(|e| EvalError::Output {
            path: path.clone(),
            what: e.to_string(),
        })?;
        files.push(path);
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Liquid particles at the given x (y 0.1), `[N, 4]` rows.
    fn row(xs: &[f32]) -> Vec<f32> {
        xs.iter().flat_map(|&x| [x, 0.1, 0.0, 0.0]).collect()
    }

    #[test]
    fn the_front_is_the_fifth_most_advanced_particle_towards_the_far_wall() {
        let xs: Vec<f32> = (0..10).map(|i| 0.1 + 0.05 * i as f32).collect();
        let frame = row(&xs);
        let material = vec![0u8; 10];
        let t = Towards::far_wall(&frame, &material).unwrap();
        assert_eq!(t, Towards(1), "mean x 0.325: the far wall is at x = 1");
        assert!((t.front(&frame, &material).unwrap() - 0.35).abs() < 1e-6);
        let mirrored: Vec<f32> = xs.iter().map(|x| 1.0 - x).collect();
        let m = row(&mirrored);
        let t = Towards::far_wall(&m, &material).unwrap();
        assert_eq!(t, Towards(-1));
        assert!((t.front(&m, &material).unwrap() - 0.35).abs() < 1e-6);
        assert_eq!(Towards::far_wall(&frame, &[1; 10]), None, "no liquid");
    }

    #[test]
    fn reach_is_the_first_step_within_a_cell_of_the_truths_furthest_front() {
        let f = Fronts {
            scene: "s".into(),
            towards: Towards(1),
            truth: [0.3, 0.6, 0.9, 0.95, 0.94].map(Some).to_vec(),
            preds: vec![
                [0.3, 0.5, 0.7, 0.8, 0.94].map(Some).to_vec(),
                [0.3, 0.4, 0.5, 0.5, 0.5].map(Some).to_vec(),
            ],
        };
        assert_eq!(f.reach(&f.truth), Some(3), "0.9 is short of 0.95 - 1/64");
        assert_eq!(f.reach(&f.preds[0]), Some(4));
        assert_eq!(f.reach(&f.preds[1]), None);
    }
}
