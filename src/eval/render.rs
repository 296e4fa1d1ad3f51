//! Pictures of an [`Evaluation`]: per-scene MSE curves (the paper's Figures 4, 8, 9) and
//! renders of the ground truth beside each model's rollout (Figures 1, 7).
//!
//! - [`mse_curves`]: one PNG, one panel per scene, one line per model and baseline, MSE over
//!   scaled features against the step, log scale ([`crate::plot::panels`]).
//! - [`render_grid`]: one PNG per scene: rows = ground truth then each model, columns = steps
//!   0, H/4, H/2, 3H/4, H (0, 5, 10, 15, 20 for H = 20; step 0 is the last seed frame),
//!   [`CELL`] pixels per cell plus a [`LABEL_W`]-pixel label column and a [`HEADER`]-pixel
//!   header row ([`grid_size`]).
//! - [`render_gif`]: one animated GIF per scene: ground truth and each model side by side, one
//!   frame per step 0..=H ([`gif_size`]), 10 frames per second, looping.
//!
//! The domain is the unit square (y up); each particle is a 2 x 2 pixel square coloured by
//! material ([`crate::material`]'s palette, the Foxglove view's) on a dark background;
//! particles outside the box are not drawn. Used by `minflow eval` and `minflow report`.

use std::borrow::Cow;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use super::{EvalError, Evaluation, Snapshots};
use crate::material;
use crate::plot::{draw_text, panels, Series};

/// Side of one particle panel, pixels.
pub const CELL: u32 = 200;
/// Width of the row-label column of [`render_grid`], pixels.
pub const LABEL_W: u32 = 110;
/// Height of the header row (column labels), pixels.
pub const HEADER: u32 = 28;
const BACKGROUND: (u8, u8, u8) = (14, 14, 18);
const PANEL: (u8, u8, u8) = (30, 32, 40);
const BORDER: (u8, u8, u8) = (90, 92, 104);
const TEXT: (u8, u8, u8) = (235, 235, 235);

/// The steps shown in [`render_grid`] for horizon `h`: 0, h/4, h/2, 3h/4, h (duplicates
/// removed).
pub fn grid_steps(h: usize) -> Vec<usize> {
    let mut steps: Vec<usize> = (0..=4).map(|i| i * h / 4).collect();
    steps.dedup();
    steps
}

/// (width, height) of [`render_grid`]'s PNG for `models` models and horizon `h`.
pub fn grid_size(models: usize, h: usize) -> (u32, u32) {
    (
        LABEL_W + grid_steps(h).len() as u32 * CELL,
        HEADER + (1 + models) as u32 * CELL,
    )
}

/// (width, height) of [`render_gif`]'s frames for `models` models.
pub fn gif_size(models: usize) -> (u32, u32) {
    ((1 + models) as u32 * CELL, HEADER + CELL)
}

/// An RGB image being drawn.
struct Canvas {
    size: (u32, u32),
    pixels: Vec<u8>,
}

impl Canvas {
    fn new(size: (u32, u32)) -> Self {
        let mut pixels = Vec::with_capacity(size.0 as usize * size.1 as usize * 3);
        for _ in 0..size.0 as usize * size.1 as usize {
            pixels.extend_from_slice(&[BACKGROUND.0, BACKGROUND.1, BACKGROUND.2]);
        }
        Self { size, pixels }
    }

    fn put(&mut self, x: i64, y: i64, c: (u8, u8, u8)) {
        if x < 0 || y < 0 || x >= i64::from(self.size.0) || y >= i64::from(self.size.1) {
            return;
        }
        let i = (y as usize * self.size.0 as usize + x as usize) * 3;
        self.pixels[i..i + 3].copy_from_slice(&[c.0, c.1, c.2]);
    }

    fn text(&mut self, text: &str, pos: (u32, u32), px: f64) -> Result<(), String> {
        let pos = (pos.0 as i32, pos.1 as i32);
        draw_text(&mut self.pixels, self.size, text, pos, px, TEXT)
    }

    /// One panel at (x0, y0): the frame's particles (or "missing"), a border.
    fn panel(
        &mut self,
        x0: u32,
        y0: u32,
        frame: Option<&[f32]>,
        material: &[u8],
    ) -> Result<(), String> {
        let (x0, y0) = (i64::from(x0), i64::from(y0));
        let side = i64::from(CELL);
        for y in 0..side {
            for x in 0..side {
                let edge = x == 0 || y == 0 || x == side - 1 || y == side - 1;
                self.put(x0 + x, y0 + y, if edge { BORDER } else { PANEL });
            }
        }
        let Some(frame) = frame else {
            return self.text("missing", (x0 as u32 + 60, y0 as u32 + 90), 18.0);
        };
        let inner = (CELL - 2) as f32;
        for (r, &m) in frame.chunks_exact(4).zip(material) {
            let (x, y) = (r[0], r[1]);
            if !(0.0..=1.0).contains(&x) || !(0.0..=1.0).contains(&y) {
                continue;
            }
            let px = x0 + 1 + (x * inner) as i64;
            let py = y0 + 1 + ((1.0 - y) * inner) as i64;
            let c = material_colour(m);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (qx, qy) = (px + dx, py + dy);
                if qx > x0 && qy > y0 && qx < x0 + side - 1 && qy < y0 + side - 1 {
                    self.put(qx, qy, c);
                }
            }
        }
        Ok(())
    }
}

/// The model rows of a scene's snapshots: ground truth first, then the first `models`
/// predictors, each with its label.
fn rows<'a>(
    eval: &'a Evaluation,
    snap: &'a Snapshots,
    models: usize,
) -> Vec<(&'a str, &'a [Option<Vec<f32>>])> {
    let mut out = vec![("truth", snap.truth.as_slice())];
    for (name, frames) in eval.predictors.iter().zip(&snap.preds).take(models) {
        out.push((name.as_str(), frames.as_slice()));
    }
    out
}

fn out_err(path: &Path, what: impl ToString) -> EvalError {
    EvalError::Output {
        path: path.to_path_buf(),
        what: what.to_string(),
    }
}

/// The PNG grid of one scene (see the module doc) for the first `models` predictors of
/// `eval`; written to `path`.
pub fn render_grid(
    path: &Path,
    eval: &Evaluation,
    snap: &Snapshots,
    models: usize,
) -> Result<(), EvalError> {
    let h = scene_horizon(eval, snap);
    let rows = rows(eval, snap, models);
    let size = grid_size(rows.len() - 1, h);
    let mut c = Canvas::new(size);
    let e = |what: String| out_err(path, what);
    for (j, step) in grid_steps(h).into_iter().enumerate() {
        let x = LABEL_W + j as u32 * CELL;
        c.text(&format!("step {step}"), (x + 70, 6), 16.0)
            .map_err(e)?;
    }
    for (i, (label, frames)) in rows.iter().enumerate() {
        let y = HEADER + i as u32 * CELL;
        let lines = label_lines(label, LABEL_CHARS);
        let top = (y + CELL / 2).saturating_sub(LINE_PX * lines.len() as u32 / 2);
        for (k, line) in lines.iter().enumerate() {
            c.text(line, (8, top + LINE_PX * k as u32), 15.0)
                .map_err(e)?;
        }
        for (j, step) in grid_steps(h).into_iter().enumerate() {
            let frame = frames.get(step).and_then(|f| f.as_deref());
            c.panel(LABEL_W + j as u32 * CELL, y, frame, &snap.material)
                .map_err(e)?;
        }
    }
    write_png(path, size, &c.pixels)
}

/// The last step a scene's renders show: the horizon, or with whole-scene rollouts
/// (`--horizon full`) the scene's own last true frame, so a shorter scene is not drawn as
/// "missing" up to the longest one's end.
fn scene_horizon(eval: &Evaluation, snap: &Snapshots) -> usize {
    if !eval.full {
        return eval.horizon;
    }
    snap.truth
        .iter()
        .rposition(Option::is_some)
        .unwrap_or(0)
        .max(1)
}

fn write_png(path: &Path, size: (u32, u32), pixels: &[u8]) -> Result<(), EvalError> {
    let file = File::create(path).map_err(|e| out_err(path, e))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), size.0, size.1);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(|e| out_err(path, e))?;
    writer
        .write_image_data(pixels)
        .map_err(|e| out_err(path, e))?;
    writer.finish().map_err(|e| out_err(path, e))
}

/// The colour a particle of material id `m` is drawn in ([`material::colour_of`]).
fn material_colour(m: u8) -> (u8, u8, u8) {
    let [r, g, b] = material::colour_of(m);
    (r, g, b)
}

/// The GIF palette: background, panel, border, the materials, 16 greys for text, then the
/// colour of unknown material ids.
fn palette() -> Vec<(u8, u8, u8)> {
    let mut p = vec![BACKGROUND, PANEL, BORDER];
    p.extend(material::Material::ALL.map(|m| material_colour(m.id())));
    p.extend((0..16u8).map(|i| {
        let v = 14 + (i as u32 * (235 - 14) / 15) as u8;
        (v, v, v)
    }));
    p.push(material_colour(u8::MAX));
    p
}

/// Index of the palette colour nearest to `c`.
fn nearest(palette: &[(u8, u8, u8)], c: (u8, u8, u8)) -> u8 {
    let d = |p: &(u8, u8, u8)| {
        let sq = |a: u8, b: u8| (i32::from(a) - i32::from(b)).pow(2);
        sq(p.0, c.0) + sq(p.1, c.1) + sq(p.2, c.2)
    };
    (0..palette.len())
        .min_by_key(|&i| d(&palette[i]))
        .unwrap_or(0) as u8
}

/// The animated GIF of one scene (see the module doc) for the first `models` predictors of
/// `eval`; written to `path`.
pub fn render_gif(
    path: &Path,
    eval: &Evaluation,
    snap: &Snapshots,
    models: usize,
) -> Result<(), EvalError> {
    let rows = rows(eval, snap, models);
    let size = gif_size(rows.len() - 1);
    let palette = palette();
    let flat: Vec<u8> = palette.iter().flat_map(|&(r, g, b)| [r, g, b]).collect();
    let file = File::create(path).map_err(|e| out_err(path, e))?;
    let (w, h) = (size.0 as u16, size.1 as u16);
    let mut encoder =
        gif::Encoder::new(BufWriter::new(file), w, h, &flat).map_err(|e| out_err(path, e))?;
    encoder
        .set_repeat(gif::Repeat::Infinite)
        .map_err(|e| out_err(path, e))?;
    let mut cache = std::collections::HashMap::new();
    for step in 0..=scene_horizon(eval, snap) {
        let mut c = Canvas::new(size);
        for (i, (label, frames)) in rows.iter().enumerate() {
            let x = i as u32 * CELL;
            let text = format!("{label}  step {step}");
            c.text(&text, (x + 8, 6), 15.0)
                .map_err(|e| out_err(path, e))?;
            let frame = frames.get(step).and_then(|f| f.as_deref());
            c.panel(x, HEADER, frame, &snap.material)
                .map_err(|e| out_err(path, e))?;
        }
        let indices: Vec<u8> = c
            .pixels
            .chunks_exact(3)
            .map(|p| {
                let key = (p[0], p[1], p[2]);
                *cache.entry(key).or_insert_with(|| nearest(&palette, key))
            })
            .collect();
        let frame = gif::Frame {
            width: w,
            height: h,
            delay: 10,
            buffer: Cow::Owned(indices),
            ..gif::Frame::default()
        };
        encoder.write_frame(&frame).map_err(|e| out_err(path, e))?;
    }
    Ok(())
}

/// The per-scene MSE curves (one panel per scene, one line per predictor, log y) as a PNG at
/// `path`.
pub fn mse_curves(path: &Path, eval: &Evaluation) -> Result<(), EvalError> {
    let panel_list: Vec<(String, Vec<Series>)> = eval
        .scenes
        .iter()
        .map(|s| {
            let series = eval
                .predictors
                .iter()
                .zip(&s.curves)
                .map(|(name, curve)| Series {
                    name: name.clone(),
                    points: curve
                        .steps
                        .iter()
                        .enumerate()
                        .filter_map(|(k, m)| m.map(|m| ((k + 1) as f64, m.mse)))
                        .collect(),
                })
                .collect();
            (s.scene.clone(), series)
        })
        .collect();
    let cols = panel_list.len().clamp(1, 3);
    panels(
        path,
        &panel_list,
        "step",
        "MSE (scaled x, y, vx, vy)",
        true,
        cols,
        (520, 380),
    )
    .map_err(|e| out_err(path, e))
}

/// Characters of a row label a line holds in the [`LABEL_W`]-pixel column, and the lines' pitch.
const LABEL_CHARS: usize = 15;
const LINE_PX: u32 = 17;

/// `label` wrapped into lines of at most `width` characters, broken after a `-`, `,`, `[`, `/`
/// or `_` where it can be and cut where a run is longer: the rows of an ablation
/// (`NAME[rope,jelly,...]`) stay apart in the label column instead of all reading `NAME`.
pub fn label_lines(label: &str, width: usize) -> Vec<String> {
    let width = width.max(1);
    let mut tokens = vec![String::new()];
    for c in label.chars() {
        tokens.last_mut().expect("one token at least").push(c);
        if "-,[/_".contains(c) {
            tokens.push(String::new());
        }
    }
    let (mut lines, mut line) = (Vec::new(), String::new());
    for token in tokens.into_iter().filter(|t| !t.is_empty()) {
        if !line.is_empty() && line.chars().count() + token.chars().count() > width {
            lines.push(std::mem::take(&mut line));
        }
        for c in token.chars() {
            if line.chars().count() == width {
                lines.push(std::mem::take(&mut line));
            }
            line.push(c);
        }
    }
    if !line.is_empty() || lines.is_empty() {
        lines.push(line);
    }
    lines
}

/// A file name for a scene id: `multi/rope+snow/001` -> `multi_rope+snow_001`.
pub fn file_stem(scene: &str) -> String {
    scene
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "+-_.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::label_lines;

    #[test]
    fn labels_wrap_at_separators_and_keep_every_character() {
        let label = "all-grid-mingru-small-k4-mixed[rope,jelly,walls,pressure]";
        let lines = label_lines(label, 15);
        assert_eq!(lines.concat(), label);
        assert!(lines.iter().all(|l| l.chars().count() <= 15), "{lines:?}");
        assert_eq!(lines[0], "all-grid-");
        assert_eq!(lines.last().unwrap(), "pressure]");
        assert_eq!(label_lines("truth", 15), ["truth"]);
        assert_eq!(label_lines("abcdefgh", 3), ["abc", "def", "gh"]);
        assert_eq!(label_lines("", 15), [""]);
    }
}
