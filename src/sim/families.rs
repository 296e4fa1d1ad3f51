//! The generated scene families, as deterministic functions of (family, scene id, seed): the
//! paper's `multi` (60 ids, 64 x 64 grid, dt 8e-4 x 20 substeps, 625 frames) and `fluid`
//! (40 ids, 128 x 128 grid, dt 2e-4 x 80 substeps, 313-1563 frames), and minflow's `mixed`
//! (1-4 bodies of any material and shape, either grid; [`super::mixed`]).
//!
//! Body sizes and placements follow `docs/mpm.md` ("Scene families"): liquid block
//! 0.2 x 0.4, snow block ~0.25^2, jelly disk r 0.08-0.1, rope 0.4 long at y 0.6-0.9 with
//! 200 particles (spacing dx / 8), random placement, initial speed <= 2; fluid circle r 0.2
//! at (0.45, 0.46), rectangle [0.3, 0.7] x [0.25, 0.7], splash column with a random velocity
//! in [-4, 4]^2.

use super::material::{Elasticity, Material};
use super::scene::{Body, Scene, Shape};
use super::SimError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::fmt;
use std::str::FromStr;

/// A generated family of scenes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Family {
    /// Multi-material pairs and single materials on a 64 x 64 grid.
    Multi,
    /// Liquid-only scenes on a 128 x 128 grid.
    Fluid,
    /// 1-4 bodies of random materials, shapes and motions on either grid ([`super::mixed`]).
    Mixed,
}

impl Family {
    /// Number of scene ids `simulate` makes by default: the paper's 60 and 40, and 100
    /// `mixed` scenes.
    pub fn scene_count(self) -> u32 {
        match self {
            Family::Multi => 60,
            Family::Fluid => 40,
            Family::Mixed => 100,
        }
    }

    /// `multi`, `fluid` or `mixed`.
    pub fn name(self) -> &'static str {
        match self {
            Family::Multi => "multi",
            Family::Fluid => "fluid",
            Family::Mixed => "mixed",
        }
    }
}

impl fmt::Display for Family {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Family {
    type Err = SimError;
    fn from_str(s: &str) -> Result<Self, SimError> {
        match s {
            "multi" => Ok(Family::Multi),
            "fluid" => Ok(Family::Fluid),
            "mixed" => Ok(Family::Mixed),
            _ => Err(SimError::Invalid(format!(
                "unknown family {s:?} (multi | fluid | mixed)"
            ))),
        }
    }
}

/// The six material pairings of the `multi` family (paper, Fig. 1 and Table 3).
pub const PAIRINGS: [(Material, Material); 6] = [
    (Material::Liquid, Material::Snow),
    (Material::Rope, Material::Snow),
    (Material::Jelly, Material::Liquid),
    (Material::Snow, Material::Snow),
    (Material::Rope, Material::Jelly),
    (Material::Rope, Material::Liquid),
];
/// Single-material scenes of the `multi` family.
pub const SINGLES: [Material; 3] = [Material::Liquid, Material::Jelly, Material::Snow];

/// Particles per scene.
pub const PARTICLES: usize = 2500;
/// Particles in a rope (0.4 long: spacing 0.002 <= dx / 4 at dx = 1/64).
pub const ROPE_PARTICLES: usize = 200;

/// The materials of a `multi` scene id: of every 5 ids, 4 cycle through the pairings and
/// 1 through the single materials (8 scenes per pairing, 4 per single material).
pub fn multi_materials(id: u32) -> Vec<Material> {
    let k = id % 5;
    if k < 4 {
        let (a, b) = PAIRINGS[((id / 5 * 4 + k) % 6) as usize];
        vec![a, b]
    } else {
        vec![SINGLES[((id / 5) % 3) as usize]]
    }
}

/// Builds scene `id` of `family` (ids beyond the paper's 60 / 40 are allowed and keep
/// cycling). The same (family, id, seed) always gives the same scene.
pub fn scene(family: Family, id: u32, seed: u64) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(mix(family as u64, id as u64, seed));
    match family {
        Family::Multi => multi(id, &mut rng),
        Family::Fluid => fluid(id, &mut rng),
        Family::Mixed => super::mixed::scene(id, &mut rng),
    }
}

/// splitmix64 of the three inputs, so nearby ids get unrelated streams.
fn mix(a: u64, b: u64, c: u64) -> u64 {
    let mut z = a
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(b.wrapping_mul(0xBF58_476D_1CE4_E5B9))
        .wrapping_add(c.wrapping_mul(0x94D0_49BB_1331_11EB))
        .wrapping_add(0x2545_F491_4F6C_DD1D);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn random_velocity(rng: &mut ChaCha8Rng, max_speed: f32) -> [f32; 2] {
    let angle: f32 = rng.random_range(0.0..std::f32::consts::TAU);
    let speed: f32 = max_speed * rng.random::<f32>();
    [speed * angle.cos(), speed * angle.sin()]
}

/// Shape and size of a non-rope body of a material, before placement.
fn template(material: Material, rng: &mut ChaCha8Rng) -> (Shape, [f32; 2]) {
    match material {
        Material::Liquid => (Shape::Rectangle, [0.2, 0.4]),
        Material::Snow => {
            let s = rng.random_range(0.22..0.28);
            (Shape::Rectangle, [s, s])
        }
        // Rope is a line (see `multi`) and never asks; a new material needs its own arm.
        Material::Jelly | Material::Rope => {
            let d = 2.0 * rng.random_range(0.08..0.10);
            (Shape::Disk, [d, d])
        }
    }
}

fn multi(id: u32, rng: &mut ChaCha8Rng) -> Scene {
    let materials = multi_materials(id);
    let rope = materials.contains(&Material::Rope);
    let mut bodies: Vec<Body> = Vec::new();
    if rope {
        let y = rng.random_range(0.6..0.9);
        let x = rng.random_range(0.3..0.7);
        let tilt = rng.random_range(-0.05..0.05);
        bodies.push(Body {
            shape: Shape::Line,
            material: Material::Rope,
            position: [x, y],
            size: [0.4, tilt],
            velocity: random_velocity(rng, 0.5),
            spin: 0.0,
            count: ROPE_PARTICLES,
        });
    }
    let (lo, hi) = (0.06f32, 0.94f32);
    for &m in materials.iter().filter(|&&m| m != Material::Rope) {
        let (shape, size) = template(m, rng);
        // Below the rope when there is one, anywhere otherwise; retry until apart.
        let top = if rope {
            bodies[0].position[1] - 0.08
        } else {
            hi
        };
        let mut body = Body {
            shape,
            material: m,
            position: [0.5, 0.5],
            size,
            velocity: [0.0; 2],
            spin: 0.0,
            count: 0,
        };
        for _ in 0..1000 {
            let x = rng.random_range(lo + size[0] / 2.0..hi - size[0] / 2.0);
            let ymax = (top - size[1] / 2.0).max(lo + size[1] / 2.0 + 1e-3);
            let y = rng.random_range(lo + size[1] / 2.0..ymax);
            body.position = [x, y];
            if !bodies
                .iter()
                .any(|b| b.shape != Shape::Line && !b.apart(&body, 0.02))
            {
                break;
            }
        }
        body.velocity = random_velocity(rng, 2.0);
        bodies.push(body);
    }
    super::scene::assign_counts(&mut bodies, PARTICLES);
    let names: Vec<&str> = materials.iter().map(|m| m.name()).collect();
    Scene {
        name: format!("multi/{}/{id:03}", names.join("+")),
        grid: 64,
        dt: 8e-4,
        substeps: 20,
        frames: 625,
        gravity: [0.0, -9.8],
        elasticity: Elasticity::default(),
        seed: rng.random(),
        bodies,
    }
}

/// The three fluid layouts, by `id % 3`.
pub const FLUID_KINDS: [&str; 3] = ["circle", "rectangle", "splash"];

fn fluid(id: u32, rng: &mut ChaCha8Rng) -> Scene {
    let kind = FLUID_KINDS[(id % 3) as usize];
    let jitter = |rng: &mut ChaCha8Rng| rng.random_range(-0.03..0.03);
    let body = match kind {
        "circle" => Body {
            shape: Shape::Disk,
            material: Material::Liquid,
            position: [0.45 + jitter(rng), 0.46 + jitter(rng)],
            size: [0.4, 0.4],
            velocity: random_velocity(rng, 1.0),
            spin: 0.0,
            count: PARTICLES,
        },
        "rectangle" => Body {
            shape: Shape::Rectangle,
            material: Material::Liquid,
            position: [0.5 + jitter(rng), 0.475 + jitter(rng)],
            size: [0.4, 0.45],
            velocity: random_velocity(rng, 1.0),
            spin: 0.0,
            count: PARTICLES,
        },
        _ => Body {
            shape: Shape::Rectangle,
            material: Material::Liquid,
            position: [rng.random_range(0.25..0.75), 0.35],
            size: [0.2, 0.5],
            velocity: [rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0)],
            spin: 0.0,
            count: PARTICLES,
        },
    };
    // 5, 10, 15, 20 or 25 time units at 62.5 frames per unit: 313 ... 1563 frames.
    let units = 5 * (1 + (id / 3) % 5);
    Scene {
        name: format!("fluid/{kind}/{id:03}"),
        grid: 128,
        dt: 2e-4,
        substeps: 80,
        frames: (units as f32 * 62.5).ceil() as u32,
        gravity: [0.0, -9.8],
        elasticity: Elasticity::default(),
        seed: rng.random(),
        bodies: vec![body],
    }
}
