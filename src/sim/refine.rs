//! Scenes at scale: [`Scene::refined`] puts a scene on a finer grid with proportionally more
//! particles, the same bodies, materials and motions, so that the paper's families run at
//! 10,000 particles on 128 x 128 and 40,000 on 256 x 256 (the sizes where a surrogate pays:
//! the solver's cost grows with particles times substeps, a surrogate's with particles and
//! grid cells; `docs/scale.md`).

use super::scene::{Scene, Shape};
use super::SimError;

/// The substep length the solver takes on an `n x n` grid: the families' 8e-4 on 64^2 (the
/// paper's `multi`) and 2e-4 on 128^2 (`fluid`; 8e-4 is never stable there), then by the CFL
/// condition `dt ∝ dx`: 1e-4 on 256^2 (the substeps of the issue's JAX reference, 160 a frame),
/// 5e-5 on 512^2. The solver still splits a substep that breaks its own limits
/// (`Solver::substep`).
pub fn substep_for(n: usize) -> f32 {
    match n {
        0..=64 => 8e-4,
        _ => 2e-4 * 128.0 / n as f32,
    }
}

impl Scene {
    /// This scene on an `n x n` grid (`n` a multiple of its own grid): `(n / grid)^2` times
    /// its particles, each body's count scaled by that (a rope's by `n / grid`, so its spacing
    /// stays the same share of a cell, the rest going to the largest other body), `dt` from [`substep_for`] with as many substeps as keep the frame
    /// period (0.016 time units for the families), and the name's first part marked with the
    /// grid (`multi/liquid+snow/007` -> `multi@256/liquid+snow/007`). The same scene for
    /// `n` = its grid.
    ///
    /// # Errors
    /// `n` is not a multiple of the scene's grid, or the refined scene fails
    /// [`Scene::validate`] (over 1,000,000 particles, say).
    pub fn refined(&self, n: usize) -> Result<Scene, SimError> {
        if n == self.grid {
            return Ok(self.clone());
        }
        if n < self.grid || !n.is_multiple_of(self.grid) {
            return Err(SimError::Invalid(format!(
                "scene {}: grid {n} is not a multiple of its grid {}",
                self.name, self.grid
            )));
        }
        let r = n / self.grid;
        let mut out = self.clone();
        let mut short = 0;
        for b in &mut out.bodies {
            if b.shape == Shape::Line {
                short += b.count * (r * r - r);
                b.count *= r;
            } else {
                b.count *= r * r;
            }
        }
        // What the ropes did not take goes to the largest other body, so the scene keeps
        // `r^2` times its particles (scenes of one family keep one count: batches stack them).
        if let Some(b) = out
            .bodies
            .iter_mut()
            .filter(|b| b.shape != Shape::Line)
            .max_by_key(|b| b.count)
        {
            b.count += short;
        }
        let period = self.dt as f64 * self.substeps as f64;
        let dt = substep_for(n);
        out.substeps = (period / dt as f64).round().max(1.0) as u32;
        out.dt = (period / out.substeps as f64) as f32;
        out.grid = n;
        out.name = match self.name.split_once('/') {
            Some((family, rest)) => format!("{family}@{n}/{rest}"),
            None => format!("{}@{n}", self.name),
        };
        out.validate()?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use crate::sim::families::{self, Family};

    #[test]
    fn refined_multi_scene_has_the_issue_sizes() {
        let scene = families::scene(Family::Multi, 1, 0);
        let at128 = scene.refined(128).unwrap();
        let at256 = scene.refined(256).unwrap();
        assert_eq!(scene.particle_count(), 2_500);
        // Scene 1 has a rope: it grows by r, the scene by r^2.
        let rope = |s: &crate::sim::Scene| -> usize {
            s.bodies
                .iter()
                .filter(|b| b.shape == super::Shape::Line)
                .map(|b| b.count)
                .sum()
        };
        assert_eq!(rope(&at256), rope(&scene) * 4);
        assert_eq!(at128.particle_count(), 10_000);
        assert_eq!(at256.particle_count(), 40_000);
        assert_eq!((at128.grid, at128.substeps), (128, 80));
        assert_eq!((at256.grid, at256.substeps), (256, 160));
        assert!((at256.dt - 1e-4).abs() < 1e-9);
        assert!(at256.name.starts_with("multi@256/"));
        assert!(scene.refined(96).is_err());
        assert_eq!(scene.refined(64).unwrap(), scene);
    }
}
