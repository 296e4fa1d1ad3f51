//! `eval`'s figures (issue 4): the per-scene MSE curves, the render grid (ground truth beside
//! each model at steps 0, 5, 10, 15, 20) and the animated GIF decode, with the documented
//! sizes and one GIF frame per step 0..=H; particles are drawn in their material colours.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use indicatif::ProgressBar;
use minflow::data::{Scaler, Trajectory};
use minflow::eval::render::{gif_size, grid_size, grid_steps, CELL};
use minflow::eval::{evaluate, output, ConstVel, Evaluation, Persist, Predictor, RolloutOptions};
use minflow::material::Material;

/// Two scenes of 400 particles (liquid and snow), 30 frames of a slow drift.
fn trajectories() -> Vec<Trajectory> {
    (0..2)
        .map(|s| {
            let n = 400;
            let mut states = Vec::new();
            for k in 0..30 {
                for p in 0..n {
                    let (x, y) = (0.2 + 0.03 * (p % 20) as f32, 0.2 + 0.03 * (p / 20) as f32);
                    let v = 0.3 + 0.1 * s as f32;
                    states.extend_from_slice(&[x + v * 0.016 * k as f32, y, v, -0.1 * k as f32]);
                }
            }
            Trajectory {
                scene: format!("test/drift/{s:03}"),
                dt: 0.016,
                material: (0..n).map(|p| if p < n / 2 { 0 } else { 2 }).collect(),
                start_index: 0,
                states,
                frames: 30,
                n,
                solver_grid: None,
            }
        })
        .collect()
}

fn png_size(path: &Path) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(BufReader::new(File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// `preds` over [`trajectories`], 20-step rollouts.
fn evaluated(preds: &[&dyn Predictor]) -> Evaluation {
    let trajs = trajectories();
    let opts = RolloutOptions {
        horizon: 20,
        ..RolloutOptions::default()
    };
    let scaler = Scaler::fit(&trajs.iter().collect::<Vec<_>>());
    evaluate(
        &trajs,
        preds,
        &scaler,
        "test",
        &opts,
        &ProgressBar::hidden(),
    )
    .unwrap()
}

#[test]
fn curves_renders_and_gifs_decode_with_the_expected_sizes() {
    // Both baselines rendered as "models" beside the truth: 3 rows.
    let eval = evaluated(&[&Persist, &ConstVel]);
    let dir = crate::tmp::tempdir().unwrap();
    let files = output::write_all(dir.path(), &eval, 2, "test", &ProgressBar::hidden()).unwrap();
    // table.md, table.csv, metrics.csv, plausibility.csv, front.csv, mse_curves.png; a
    // render PNG, its GIF and a surge-front PNG per scene.
    assert_eq!(files.len(), 6 + 3 * 2, "{files:?}");
    assert!(dir.path().join("plausibility.csv").is_file());
    assert!(dir.path().join("front.csv").is_file());

    // Two panels side by side, 520 x 380 each.
    let (w, h, _) = png_size(&dir.path().join("mse_curves.png"));
    assert_eq!((w, h), (1040, 380));

    assert_eq!(grid_steps(20), [0, 5, 10, 15, 20]);
    for scene in ["test_drift_000", "test_drift_001"] {
        let (w, h, pixels) = png_size(&dir.path().join(format!("render_{scene}.png")));
        assert_eq!((w, h), grid_size(2, 20));
        assert_eq!((w, h), (110 + 5 * CELL, 28 + 3 * CELL));
        // Liquid and snow particles are drawn in their colours.
        for [r, g, b] in [Material::Liquid.colour(), Material::Snow.colour()] {
            let hits = pixels.chunks_exact(3).filter(|p| p == &[r, g, b]).count();
            assert!(hits > 1000, "colour {:?}: {hits} pixels", (r, g, b));
        }

        let file = File::open(dir.path().join(format!("render_{scene}.gif"))).unwrap();
        let mut options = gif::DecodeOptions::new();
        options.set_color_output(gif::ColorOutput::RGBA);
        let mut decoder = options.read_info(BufReader::new(file)).unwrap();
        assert_eq!(
            (u32::from(decoder.width()), u32::from(decoder.height())),
            gif_size(2)
        );
        let mut frames = 0;
        while let Some(frame) = decoder.read_next_frame().unwrap() {
            assert_eq!(
                (u32::from(frame.width), u32::from(frame.height)),
                gif_size(2)
            );
            frames += 1;
        }
        assert_eq!(frames, 21, "steps 0..=20");
    }
    let md = std::fs::read_to_string(dir.path().join("table.md")).unwrap();
    assert!(
        md.contains("| `test/drift/000` |") && md.contains("| **Average** |"),
        "{md}"
    );
}

/// `persist` under the name an ablation column gets (`eval --constraints A,B`): a name
/// with commas, as `NAME[setting]`.
struct Ablated;

impl Predictor for Ablated {
    fn name(&self) -> &str {
        "m[rope,jelly]"
    }

    fn window(&self) -> usize {
        1
    }

    fn rollout(
        &self,
        traj: &Trajectory,
        first: usize,
        steps: usize,
    ) -> Result<Vec<Vec<f32>>, minflow::eval::EvalError> {
        Persist.rollout(traj, first, steps)
    }
}

/// Splits a CSV line into fields, a quoted field (RFC 4180, `""` for a quote) kept whole.
fn csv_fields(line: &str) -> Vec<String> {
    let (mut fields, mut field, mut quoted) = (Vec::new(), String::new(), false);
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '"' if quoted && chars.peek() == Some(&'"') => field.push(chars.next().unwrap()),
            '"' => quoted = !quoted,
            ',' if !quoted => fields.push(std::mem::take(&mut field)),
            c => field.push(c),
        }
    }
    fields.push(field);
    fields
}

#[test]
fn every_csv_keeps_an_ablation_name_with_commas_in_one_field() {
    let eval = evaluated(&[&Ablated, &Persist]);
    let dir = crate::tmp::tempdir().unwrap();
    output::write_all(dir.path(), &eval, 0, "test", &ProgressBar::hidden()).unwrap();
    for file in ["table.csv", "metrics.csv", "plausibility.csv", "front.csv"] {
        let text = std::fs::read_to_string(dir.path().join(file)).unwrap();
        let mut lines = text.lines();
        let header = csv_fields(lines.next().unwrap());
        for line in lines {
            let fields = csv_fields(line);
            assert_eq!(fields.len(), header.len(), "{file}: {line}");
        }
        assert!(text.contains("m[rope,jelly]"), "{file}");
    }
    let table = std::fs::read_to_string(dir.path().join("table.csv")).unwrap();
    assert!(csv_fields(table.lines().next().unwrap()).contains(&"avg20_m[rope,jelly]".into()));
}
