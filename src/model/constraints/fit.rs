//! Fitting a model's [`Constraints`] to the truth of its training split (`minflow constraints
//! fit`): the parameters the truth determines, never from test scenes.
//!
//! - rope `stretch`: the [`STRETCH_QUANTILE`] quantile of the solver's link stretch (a link's
//!   length over its rest length) over every frame of the training ropes;
//! - liquid `rest`: the smallest of [`REST_CANDIDATES`] at which projecting the truth's own
//!   frames moves the liquid less than [`TRUTH_MOVE`] spacings a frame on average, so the
//!   constraint acts on a surrogate's compression and not on the solver's (the largest when
//!   none does: [`FitReport::liquid_met`] says which);
//! - liquid pressure `rest`: likewise, the least of [`PRESSURE_CANDIDATES`] (volume
//!   fractions) that leaves the truth in place;
//! - walls: the smallest and largest coordinate any training particle takes, and the least
//!   distance from the box's edge, in its scene's solver cells, of any particle of a scene
//!   whose grid is known ([`super::WallParams::cells`]).
//!
//! Shape matching's stiffness, linear share and plasticity, the kernel radius and the
//! iteration counts are kept from the base parameters.

use rayon::prelude::*;

use super::{rope, Constraints, SceneShape};
use crate::data::Trajectory;
use crate::material::Material;

/// The quantile of the truth's link stretch taken as the rope's limit.
pub const STRETCH_QUANTILE: f64 = 0.999;
/// [`STRETCH_QUANTILE`] in percent, for reports.
pub const STRETCH_QUANTILE_PERCENT: f64 = STRETCH_QUANTILE * 100.0;
/// The liquid's mean move on the truth's frames, in spacings per frame, the fitted rest
/// density stays under.
pub const TRUTH_MOVE: f64 = 0.02;
/// Rest densities tried, over the rest frame's median, in order.
pub const REST_CANDIDATES: [f32; 16] = [
    1.0, 1.05, 1.1, 1.15, 1.2, 1.25, 1.3, 1.4, 1.5, 1.6, 1.8, 2.0, 2.5, 3.0, 3.5, 4.0,
];
/// Volume fractions tried as the pressure projection's compressed threshold, in order.
pub const PRESSURE_CANDIDATES: [f32; 16] = [
    0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6, 1.8, 2.0, 2.25, 2.5, 3.0, 3.5, 4.0,
];
/// Truth frames per scene the liquid's rest density is tried on (evenly spaced).
const LIQUID_FRAMES: usize = 24;

/// What [`fit`] measured.
#[derive(Clone, Debug, Default)]
pub struct FitReport {
    /// Rope links measured (link-frames).
    pub rope_links: usize,
    /// The largest link stretch of the truth.
    pub rope_max_stretch: f32,
    /// Per liquid rest density tried: the truth's mean move, spacings per frame.
    pub liquid_moves: Vec<(f32, f64)>,
    /// Liquid frames each candidate was tried on.
    pub liquid_frames: usize,
    /// Whether a candidate met [`TRUTH_MOVE`] (else the last, the loosest, was kept).
    pub liquid_met: bool,
    /// Per pressure threshold tried: the truth's mean move, spacings per frame.
    pub pressure_moves: Vec<(f32, f64)>,
    /// Whether a pressure threshold met [`TRUTH_MOVE`].
    pub pressure_met: bool,
    /// Per solver grid: each threshold's truth move, and whether one met [`TRUTH_MOVE`].
    pub pressure_by_grid: Vec<(u32, Vec<(f32, f64)>, bool)>,
}

/// `base` with its rope stretch, liquid rest density and walls fitted to `trajs` (the
/// training split's truth; see the module doc). Parts `base` lacks stay off.
pub fn fit(trajs: &[Trajectory], base: &Constraints) -> (Constraints, FitReport) {
    let mut out = base.clone();
    let mut report = FitReport::default();
    if let Some(p) = out.rope.as_mut() {
        let mut ratios = rope_stretches(trajs);
        report.rope_links = ratios.len();
        if !ratios.is_empty() {
            ratios.sort_by(f32::total_cmp);
            report.rope_max_stretch = ratios[ratios.len() - 1];
            let q = ((ratios.len() - 1) as f64 * STRETCH_QUANTILE).round() as usize;
            p.stretch = ratios[q].max(1.0);
        }
    }
    if let Some(w) = out.walls.as_mut() {
        let coords = trajs
            .iter()
            .flat_map(|t| t.states.chunks_exact(4).flat_map(|r| [r[0], r[1]]));
        let (lo, hi) = coords.fold((f32::MAX, f32::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
        if lo <= hi {
            (w.lo, w.hi) = (lo, hi);
        }
        w.cells = wall_cells(trajs);
    }
    if let Some(p) = out.liquid {
        let only = Constraints {
            liquid: Some(p),
            ..Default::default()
        };
        let set = |c: &mut Constraints, rest| c.liquid.as_mut().unwrap().rest = rest;
        let all: Vec<&Trajectory> = trajs.iter().collect();
        let (rest, moves, frames, met) = fit_rest(&all, only, set, &REST_CANDIDATES);
        out.liquid.as_mut().unwrap().rest = rest;
        (report.liquid_moves, report.liquid_frames, report.liquid_met) = (moves, frames, met);
    }
    if let Some(p) = out.pressure.clone() {
        let only = Constraints {
            pressure: Some(p),
            walls: out.walls,
            ..Default::default()
        };
        let set = |c: &mut Constraints, rest| c.pressure.as_mut().unwrap().rest = rest;
        let all: Vec<&Trajectory> = trajs.iter().collect();
        let (rest, moves, _, met) = fit_rest(&all, only.clone(), set, &PRESSURE_CANDIDATES);
        out.pressure.as_mut().unwrap().rest = rest;
        (report.pressure_moves, report.pressure_met) = (moves, met);
        // Then each solver grid's own threshold, on its scenes.
        let mut grids: Vec<u32> = trajs.iter().filter_map(|t| t.solver_grid).collect();
        grids.sort_unstable();
        grids.dedup();
        for g in grids {
            let on: Vec<&Trajectory> = trajs.iter().filter(|t| t.solver_grid == Some(g)).collect();
            let (rest, moves, _, met) = fit_rest(&on, only.clone(), set, &PRESSURE_CANDIDATES);
            out.pressure.as_mut().unwrap().rest_by_grid.insert(g, rest);
            report.pressure_by_grid.push((g, moves, met));
        }
    }
    (out, report)
}

/// The first of `candidates` (set into `only` by `set`) at which projecting the truth moves
/// its liquid less than [`TRUTH_MOVE`] spacings a frame (else the last): the rest value,
/// each candidate's move, the frames measured and whether one met it.
fn fit_rest(
    trajs: &[&Trajectory],
    mut only: Constraints,
    set: impl Fn(&mut Constraints, f32),
    candidates: &[f32],
) -> (f32, Vec<(f32, f64)>, usize, bool) {
    let (mut moves, mut frames) = (Vec::new(), 0);
    let mut rest = candidates[0];
    for &r in candidates {
        set(&mut only, r);
        let (moved, n) = truth_moves(trajs, &only);
        frames = n;
        moves.push((r, moved));
        rest = r;
        if moved < TRUTH_MOVE {
            return (rest, moves, frames, true);
        }
    }
    (rest, moves, frames, false)
}

/// The least distance of any particle from the box's edge in its scene's solver cells, over
/// the scenes whose solver grid is known (None without one).
fn wall_cells(trajs: &[Trajectory]) -> Option<f32> {
    trajs
        .iter()
        .filter_map(|t| {
            let n = t.solver_grid? as f32;
            let s = &t.states;
            let edge = s
                .chunks_exact(4)
                .flat_map(|r| [r[0], r[1], 1.0 - r[0], 1.0 - r[1]]);
            Some(edge.fold(f32::MAX, f32::min) * n)
        })
        .reduce(f32::min)
}

/// Every link stretch of the truth's ropes, every frame (chains of each scene's frame 0).
fn rope_stretches(trajs: &[Trajectory]) -> Vec<f32> {
    let rope_id = Material::Rope.id();
    trajs
        .par_iter()
        .flat_map_iter(|t| {
            let chains = rope::chains(t.state(0), 4, &t.material, rope_id);
            let links: Vec<(usize, usize, f32)> = chains.iter().flat_map(|c| c.links()).collect();
            (0..t.frames).flat_map(move |k| {
                let s = t.state(k);
                links.clone().into_iter().map(move |(i, j, rest)| {
                    (s[4 * j] - s[4 * i]).hypot(s[4 * j + 1] - s[4 * i + 1]) / rest
                })
            })
        })
        .collect()
}

/// The liquid's mean move (spacings per particle and frame) when `c` projects the truth's
/// own frames, and the frames it was measured on.
fn truth_moves(trajs: &[&Trajectory], c: &Constraints) -> (f64, usize) {
    let liquid = usize::from(Material::Liquid.id());
    let per_scene: Vec<(f64, u64, usize)> = trajs
        .par_iter()
        .filter(|t| t.material.contains(&Material::Liquid.id()))
        .map(|t| {
            let mut shape = SceneShape::on_grid(t.state(0), 4, &t.material, c, t.solver_grid);
            let every = (t.frames / LIQUID_FRAMES).max(1);
            let (mut sum, mut count, mut frames) = (0.0, 0u64, 0);
            for k in (every..t.frames).step_by(every) {
                let mut frame = t.state(k).to_vec();
                let corr = shape.project(c, (None, &mut frame), &t.material, t.dt);
                sum += corr.sum[liquid];
                count += corr.count[liquid];
                frames += 1;
            }
            (sum, count, frames)
        })
        .collect();
    let (sum, count, frames) = per_scene
        .iter()
        .fold((0.0, 0, 0), |a, s| (a.0 + s.0, a.1 + s.1, a.2 + s.2));
    (
        (count > 0).then(|| sum / count as f64).unwrap_or(0.0),
        frames,
    )
}
