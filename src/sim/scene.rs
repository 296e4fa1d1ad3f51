//! A scene: the bodies that make up the initial particle state plus the numerical settings
//! (grid, dt, substeps, frames, gravity). Scenes come from the generated families
//! ([`crate::sim::families`]) or from a TOML scene file (`minflow simulate --scene-file`).
//!
//! Every body is given by its centre `position` and its extent `size` (domain units):
//! a rectangle fills the box, a disk is the ellipse inscribed in it, a line runs along the
//! box's diagonal from `position - size / 2` to `position + size / 2` (so `size = [0.4, 0]`
//! is a horizontal rope 0.4 long). Rectangles and disks are sampled uniformly at random
//! from the scene's seed; lines are evenly spaced. Sampling is deterministic. The generated
//! families place their bodies apart with [`Body::apart`] and share a total particle count
//! among them with `assign_counts`.

use super::material::{Elasticity, Material};
use super::mpm::{Particles, Solver, SolverConfig};
use super::SimError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Shape of a body.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// Axis-aligned rectangle filling `size`.
    Rectangle,
    /// Ellipse inscribed in `size` (a disk when both sides are equal).
    Disk,
    /// Evenly spaced particles along the diagonal of `size` (rope).
    Line,
}

/// One body of a scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Body {
    /// Shape.
    pub shape: Shape,
    /// Material.
    pub material: Material,
    /// Centre, domain units.
    #[serde(deserialize_with = "pair")]
    pub position: [f32; 2],
    /// Extent `[width, height]`, domain units.
    #[serde(deserialize_with = "pair")]
    pub size: [f32; 2],
    /// Initial velocity, domain units per time unit.
    #[serde(default, deserialize_with = "pair")]
    pub velocity: [f32; 2],
    /// Initial angular velocity about the centre, radians per time unit.
    #[serde(default)]
    pub spin: f32,
    /// Number of particles.
    pub count: usize,
}

impl Body {
    /// Whether the boxes of `self` and `other` (centre `position`, extent `|size|`) are at
    /// least `gap` apart along some axis (domain units). Used to place bodies apart.
    pub fn apart(&self, other: &Body, gap: f32) -> bool {
        (0..2).any(|k| {
            (self.position[k] - other.position[k]).abs()
                >= (self.size[k].abs() + other.size[k].abs()) / 2.0 + gap
        })
    }
}

/// A complete scene description.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Scene id written into every frame, e.g. `multi/rope+snow/007`.
    pub name: String,
    /// Grid nodes per side (64 for `multi`, 128 for `fluid`).
    #[serde(default = "default_grid")]
    pub grid: usize,
    /// Substep length, time units.
    #[serde(default = "default_dt")]
    pub dt: f32,
    /// Substeps per saved frame.
    #[serde(default = "default_substeps")]
    pub substeps: u32,
    /// Saved frames, counting frame 0 (the initial state).
    pub frames: u32,
    /// Gravity, domain units per time unit squared.
    #[serde(default = "default_gravity", deserialize_with = "pair")]
    pub gravity: [f32; 2],
    /// E0 and nu.
    #[serde(default)]
    pub elasticity: Elasticity,
    /// Seed of the particle sampling.
    #[serde(default)]
    pub seed: u64,
    /// The bodies, in particle order.
    #[serde(rename = "body")]
    pub bodies: Vec<Body>,
}

/// A 2D vector of a scene file: exactly two numbers (TOML's arrays would otherwise give the
/// first two of `[0.5, 0.5, 0.5]` and silently drop the rest).
fn pair<'de, D: serde::Deserializer<'de>>(d: D) -> Result<[f32; 2], D::Error> {
    let values = Vec::<f32>::deserialize(d)?;
    <[f32; 2]>::try_from(values.as_slice()).map_err(|_| {
        serde::de::Error::custom(format!(
            "expected 2 values [x, y] (2D), found {}",
            values.len()
        ))
    })
}

fn default_grid() -> usize {
    64
}
fn default_dt() -> f32 {
    8e-4
}
fn default_substeps() -> u32 {
    20
}
fn default_gravity() -> [f32; 2] {
    [0.0, -9.8]
}

/// The particles of one body: its index range in [`Particles`] and its shape.
#[derive(Clone, Debug, PartialEq)]
pub struct BodySpan {
    /// Particle indices.
    pub range: Range<usize>,
    /// Shape (lines are checked for rope gaps).
    pub shape: Shape,
    /// Material.
    pub material: Material,
}

impl Scene {
    /// Parses a TOML scene file's text and validates it.
    pub fn from_toml(text: &str) -> Result<Self, SimError> {
        let scene: Scene = toml::from_str(text).map_err(|e| SimError::SceneFile(e.to_string()))?;
        scene.validate()?;
        Ok(scene)
    }

    /// Time between saved frames, `dt * substeps`, in time units.
    pub fn frame_dt(&self) -> f32 {
        self.dt * self.substeps as f32
    }

    /// Time between saved frames in integer nanoseconds, `round(dt * substeps * 1e9)`, the
    /// period of the frames' stamps (`sim::run`).
    pub fn period_ns(&self) -> u64 {
        (self.dt as f64 * self.substeps as f64 * 1e9).round() as u64
    }

    /// Total particle count N (saturating: counts that overflow `usize` when summed read as
    /// `usize::MAX`, which [`Scene::validate`] rejects).
    pub fn particle_count(&self) -> usize {
        self.bodies
            .iter()
            .fold(0usize, |n, b| n.saturating_add(b.count))
    }

    /// Checks ranges: a name that can be a bag's file name, grid, dt, counts, bodies inside
    /// `[dx, 1 - 2 dx]`, rope spacing `<= dx / 4` (docs/mpm.md, "Materials"), at most 1,000,000 particles.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |what: String| Err(SimError::Invalid(format!("scene {}: {what}", self.name)));
        // The name becomes the bag's file name (`/` -> `_`, see `cli::bag_name`): an empty
        // one wrote a hidden `.mcap` that `bag info DIR` does not list.
        if self.name.is_empty()
            || self.name.starts_with('.')
            || self.name.chars().any(|c| c.is_control() || c == '\\')
        {
            return Err(SimError::Invalid(format!(
                "name {:?}: must be non-empty, must not start with '.' and must hold no \
                 control characters or backslashes (it names the bag file)",
                self.name
            )));
        }
        if !(8..=4096).contains(&self.grid) {
            return bad(format!("grid {} outside 8..=4096", self.grid));
        }
        if !(self.dt.is_finite() && self.dt > 0.0) || self.substeps == 0 || self.frames == 0 {
            return bad("dt, substeps and frames must be positive".into());
        }
        if self.bodies.is_empty() || self.particle_count() > 1_000_000 {
            return bad(format!(
                "{} particles (1..=1000000 allowed)",
                self.particle_count()
            ));
        }
        let dx = 1.0 / self.grid as f32;
        for (k, b) in self.bodies.iter().enumerate() {
            let half = [b.size[0].abs() / 2.0, b.size[1].abs() / 2.0];
            let lo = [b.position[0] - half[0], b.position[1] - half[1]];
            let hi = [b.position[0] + half[0], b.position[1] + half[1]];
            let finite = b
                .position
                .iter()
                .chain(&b.size)
                .chain(&b.velocity)
                .all(|v| v.is_finite());
            if !finite || !b.spin.is_finite() || b.count == 0 {
                return bad(format!("body {k}: needs finite values and count >= 1"));
            }
            if lo.iter().chain(&hi).any(|&c| c < dx || c > 1.0 - 2.0 * dx) {
                return bad(format!(
                    "body {k}: extends outside [dx, 1 - 2 dx] = [{dx}, {}]",
                    1.0 - 2.0 * dx
                ));
            }
            if b.shape == Shape::Line && b.count > 1 {
                let gap = b.size[0].hypot(b.size[1]) / (b.count - 1) as f32;
                if gap > dx / 4.0 * 1.0001 {
                    return bad(format!(
                        "body {k}: line spacing {gap} > dx / 4; use more particles"
                    ));
                }
            } else if b.shape != Shape::Line && (b.size[0] <= 0.0 || b.size[1] <= 0.0) {
                return bad(format!("body {k}: rectangle and disk need a positive size"));
            }
        }
        Ok(())
    }

    /// Samples the initial particles (deterministic in `seed`), body by body.
    pub fn particles(&self) -> (Particles, Vec<BodySpan>) {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let mut ps = Particles::default();
        let mut spans = Vec::with_capacity(self.bodies.len());
        for b in &self.bodies {
            let start = ps.len();
            let half = [b.size[0] / 2.0, b.size[1] / 2.0];
            let mut pushed = 0;
            while pushed < b.count {
                let (ox, oy) = match b.shape {
                    Shape::Line => {
                        let t = if b.count == 1 {
                            0.5
                        } else {
                            pushed as f32 / (b.count - 1) as f32
                        };
                        ((t - 0.5) * b.size[0], (t - 0.5) * b.size[1])
                    }
                    Shape::Rectangle | Shape::Disk => {
                        let u: f32 = rng.random_range(-1.0..1.0);
                        let w: f32 = rng.random_range(-1.0..1.0);
                        if b.shape == Shape::Disk && u * u + w * w > 1.0 {
                            continue;
                        }
                        (u * half[0], w * half[1])
                    }
                };
                let v = [b.velocity[0] - b.spin * oy, b.velocity[1] + b.spin * ox];
                ps.push([b.position[0] + ox, b.position[1] + oy], v, b.material.id());
                pushed += 1;
            }
            spans.push(BodySpan {
                range: start..ps.len(),
                shape: b.shape,
                material: b.material,
            });
        }
        (ps, spans)
    }

    /// Builds the solver at frame 0 (validates first).
    pub fn solver(&self) -> Result<(Solver, Vec<BodySpan>), SimError> {
        self.validate()?;
        let (ps, spans) = self.particles();
        Ok((Solver::new(self.solver_config(), ps)?, spans))
    }

    /// The solver's settings for this scene (its grid, `dt`, gravity and elasticity; the
    /// default CFL limit).
    pub fn solver_config(&self) -> SolverConfig {
        SolverConfig {
            grid: self.grid,
            dt: self.dt,
            gravity: self.gravity,
            elasticity: self.elasticity,
            max_cfl: super::mpm::DEFAULT_MAX_CFL,
        }
    }
}

/// Gives the non-rope bodies the particles the ropes leave of `total` (each rope's count is
/// its own), in proportion to their area, the last taking the remainder; each other body
/// gets at least one. Used by the `multi` and `mixed` families.
pub(super) fn assign_counts(bodies: &mut [Body], total: usize) {
    let ropes: usize = bodies
        .iter()
        .filter(|b| b.shape == Shape::Line)
        .map(|b| b.count)
        .sum();
    let left = total - ropes;
    let area = |b: &Body| {
        b.size[0]
            * b.size[1]
            * if b.shape == Shape::Disk {
                std::f32::consts::FRAC_PI_4
            } else {
                1.0
            }
    };
    let solid: Vec<usize> = (0..bodies.len())
        .filter(|&k| bodies[k].shape != Shape::Line)
        .collect();
    let sum: f32 = solid.iter().map(|&k| area(&bodies[k])).sum();
    let mut given = 0;
    for (n, &k) in solid.iter().enumerate() {
        let count = match n + 1 == solid.len() {
            true => left - given,
            false => ((left as f32 * area(&bodies[k]) / sum).round() as usize).max(1),
        };
        bodies[k].count = count;
        given += count;
    }
}
