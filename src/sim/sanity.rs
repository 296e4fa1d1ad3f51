//! Per-frame sanity checks of a running scene (`docs/mpm.md`, "Validation checks", check 6): no
//! NaN, every particle inside `[0.5 dx, 1 - 1.5 dx)`, speed `<= 20` domain units per time unit,
//! liquid `J > 0`, and neighbouring rope particles no more than `dx` apart.
//!
//! Used by [`super::SceneRun`] on every frame it yields (so `minflow simulate` stops a scene
//! that breaks one, [`super::SimError::Unstable`]) and by the validation tests.

use super::linalg;
use super::mpm::{Particles, Solver};
use super::scene::{BodySpan, Shape};
use std::fmt;

/// Speed bound of check 6, domain units per time unit.
pub const MAX_SPEED: f32 = 20.0;

/// The first violation found in a frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Violation {
    /// Particle index.
    pub particle: usize,
    /// What is wrong, with the offending values.
    pub what: String,
}

impl fmt::Display for Violation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "particle {}: {}", self.particle, self.what)
    }
}

/// Checks the solver's current state; returns the first violation.
pub fn check(solver: &Solver, bodies: &[BodySpan]) -> Result<(), Violation> {
    check_particles(&solver.particles, solver.dx(), bodies)
}

/// [`check`] of particles `ps` on a grid of spacing `dx` (a GPU solver's state read back,
/// `sim::gpu`).
pub fn check_particles(ps: &Particles, dx: f32, bodies: &[BodySpan]) -> Result<(), Violation> {
    let (lo, hi) = (0.5 * dx, 1.0 - 1.5 * dx);
    let fail = |particle, what: String| Err(Violation { particle, what });
    for p in 0..ps.len() {
        let [x, y] = ps.x[p];
        let [vx, vy] = ps.v[p];
        if !(x.is_finite() && y.is_finite() && vx.is_finite() && vy.is_finite()) {
            return fail(p, format!("non-finite state x=({x}, {y}) v=({vx}, {vy})"));
        }
        if !(x >= lo && x < hi && y >= lo && y < hi) {
            return fail(p, format!("position ({x}, {y}) outside [{lo}, {hi})"));
        }
        let speed = vx.hypot(vy);
        if speed > MAX_SPEED {
            return fail(p, format!("speed {speed} > {MAX_SPEED}"));
        }
        if ps.material[p] == 0 {
            let j = linalg::det(&ps.f[p]);
            if j.is_nan() || j <= 0.0 {
                return fail(p, format!("liquid J = {j} <= 0"));
            }
        }
    }
    for b in bodies.iter().filter(|b| b.shape == Shape::Line) {
        for p in b.range.start + 1..b.range.end {
            let (a, c) = (ps.x[p - 1], ps.x[p]);
            let gap = (a[0] - c[0]).hypot(a[1] - c[1]);
            if gap > dx {
                return fail(
                    p,
                    format!("rope gap {gap} to particle {} > dx = {dx}", p - 1),
                );
            }
        }
    }
    Ok(())
}
