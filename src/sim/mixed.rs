//! The `mixed` family: scenes beyond the paper's two families, for training surrogates that
//! hold on users' own scenes (docs/mpm.md, "Scene families"). A deterministic function of
//! (scene id, seed), as `multi` and `fluid` are.
//!
//! Each scene draws a grid (64 x 64 with dt 8e-4 x 20 substeps, or 128 x 128 with dt 2e-4 x
//! 80; both 0.016 time units a frame), a particle count from [`COUNTS`], and 1-4 bodies of
//! five kinds: disks and ellipses, rectangles, ropes (any tilt), liquid or snow columns
//! standing on the floor, and a liquid pool on the floor. Materials, sizes, positions,
//! velocities and spins are random; the bodies' areas are scaled together so that the solver
//! sees 3-6 particles per cell on the 64^2 grid or 0.9-2 on the 128^2 grid (the paper's
//! families have about 5.8 in `multi` and 0.9 in `fluid`).
//!
//! [`outside`] states the family's rules as checks (bodies apart and clear of the walls,
//! speeds, closing speeds between bodies, pool and column sizes). Every generated scene passes
//! them; the held-out scene kinds of `launch_configs/scenes/heldout/` each break one, so a
//! model trained on this family has never seen them.

use super::material::{Elasticity, Material};
use super::scene::{Body, Scene, Shape};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Total particle counts a scene draws from (a few values, so that training batches, which
/// group windows by particle count, stay full).
pub const COUNTS: [usize; 5] = [1000, 1500, 2500, 3500, 5000];
/// Frames per scene, frame 0 included (6.4 time units).
pub const FRAMES: u32 = 400;
/// Bodies keep at least this far from the walls (domain units).
pub const WALL_MARGIN: f32 = 0.06;
/// Bodies start at least this far apart, bounding box to bounding box (domain units).
pub const GAP: f32 = 0.03;
/// Initial speed at most (domain units per time unit), rope included.
pub const MAX_SPEED: f32 = 2.0;
/// Two bodies never start closing in on each other faster than this (domain units per time
/// unit, the relative velocity along the line between their centres).
pub const MAX_CLOSING: f32 = 1.0;
/// Spin at most (radians per time unit).
pub const MAX_SPIN: f32 = 4.0;
/// A pool is at most this deep and this wide (domain units).
pub const POOL_MAX: [f32; 2] = [0.8, 0.15];
/// Rope particles per grid cell along the rope (spacing dx / 6).
const ROPE_DENSITY: f32 = 6.0;

/// The body kinds of the family.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Disk,
    Rectangle,
    Rope,
    Column,
    Pool,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Disk => "disk",
            Kind::Rectangle => "rect",
            Kind::Rope => "rope",
            Kind::Column => "column",
            Kind::Pool => "pool",
        }
    }

    /// Kinds that stand on the floor at rest.
    fn on_floor(self) -> bool {
        matches!(self, Kind::Column | Kind::Pool)
    }
}

/// Builds scene `id` of the `mixed` family (any id; the same (id, seed) always gives the
/// same scene). Used by [`super::families::scene`].
pub fn scene(id: u32, rng: &mut ChaCha8Rng) -> Scene {
    let grid = if rng.random_bool(0.6) { 64 } else { 128 };
    let dx = 1.0 / grid as f32;
    let total = COUNTS[rng.random_range(0..COUNTS.len())];
    let kinds = draw_kinds(rng);
    let mut bodies: Vec<Body> = Vec::new();
    // Ropes first: their particle count follows their length, the rest share what is left.
    let mut left = total;
    for _ in kinds.iter().filter(|&&k| k == Kind::Rope) {
        let max_len = ((total / 3) as f32 / (grid as f32 * ROPE_DENSITY)).min(0.5);
        let len = rng.random_range(0.15f32.min(max_len)..=max_len);
        let tilt: f32 = rng.random_range(-0.6..0.6);
        let count = (len * grid as f32 * ROPE_DENSITY).ceil() as usize + 1;
        left -= count;
        bodies.push(body(
            Shape::Line,
            Material::Rope,
            [len * tilt.cos(), len * tilt.sin()],
        ));
        bodies.last_mut().unwrap().count = count;
    }
    let solids: Vec<Kind> = kinds.iter().copied().filter(|&k| k != Kind::Rope).collect();
    let ppc = match grid {
        64 => rng.random_range(3.0..6.0),
        _ => rng.random_range(0.9..2.0),
    };
    let area = (left as f32 * dx * dx / ppc).clamp(0.03, 0.32);
    let weights: Vec<f32> = solids.iter().map(|_| rng.random_range(0.5..1.5)).collect();
    let sum: f32 = weights.iter().sum();
    let mut solid_bodies: Vec<(Kind, Body)> = solids
        .iter()
        .zip(&weights)
        .map(|(&kind, w)| (kind, solid(kind, area * w / sum, rng)))
        .collect();
    // Floor bodies first (they are wide), then the largest first.
    solid_bodies.sort_by(|a, b| {
        (!a.0.on_floor())
            .cmp(&!b.0.on_floor())
            .then(extent(&b.1).total_cmp(&extent(&a.1)))
    });
    let ropes = std::mem::take(&mut bodies);
    let mut names: Vec<String> = Vec::new();
    for (kind, b) in solid_bodies
        .into_iter()
        .chain(ropes.into_iter().map(|r| (Kind::Rope, r)))
    {
        if let Some(b) = place(kind, b, &bodies, rng) {
            names.push(match kind {
                Kind::Rope => "rope".into(),
                _ => format!("{}-{}", b.material.name(), kind.name()),
            });
            bodies.push(b);
        }
    }
    set_motion(&mut bodies, rng);
    super::scene::assign_counts(&mut bodies, total);
    names.sort();
    Scene {
        name: format!("mixed/{}/{id:04}", names.join("+")),
        grid,
        dt: if grid == 64 { 8e-4 } else { 2e-4 },
        substeps: if grid == 64 { 20 } else { 80 },
        frames: FRAMES,
        gravity: [0.0, -9.8],
        elasticity: Elasticity::default(),
        seed: rng.random(),
        bodies,
    }
}

/// 1-4 body kinds: at most one pool and two ropes, at least one body that is not a rope.
fn draw_kinds(rng: &mut ChaCha8Rng) -> Vec<Kind> {
    let count = rng.random_range(1..=4);
    let mut kinds = Vec::with_capacity(count);
    while kinds.len() < count {
        let kind = match rng.random_range(0..20) {
            0..=5 => Kind::Disk,
            6..=10 => Kind::Rectangle,
            11..=13 => Kind::Rope,
            14..=16 => Kind::Column,
            _ => Kind::Pool,
        };
        let ropes = kinds.iter().filter(|&&k| k == Kind::Rope).count();
        if (kind == Kind::Pool && kinds.contains(&Kind::Pool)) || (kind == Kind::Rope && ropes == 2)
        {
            continue;
        }
        kinds.push(kind);
    }
    if kinds.iter().all(|&k| k == Kind::Rope) {
        kinds[0] = Kind::Disk;
    }
    kinds
}

fn body(shape: Shape, material: Material, size: [f32; 2]) -> Body {
    Body {
        shape,
        material,
        position: [0.5, 0.5],
        size,
        velocity: [0.0; 2],
        spin: 0.0,
        count: 0,
    }
}

/// A non-rope body of `kind` covering about `area` (domain units squared).
fn solid(kind: Kind, area: f32, rng: &mut ChaCha8Rng) -> Body {
    let material = |rng: &mut ChaCha8Rng| match rng.random_range(0..20) {
        0..=6 => Material::Jelly,
        7..=12 => Material::Snow,
        _ => Material::Liquid,
    };
    let (shape, m, size) = match kind {
        Kind::Disk => {
            let d = (4.0 * area / std::f32::consts::PI).sqrt();
            let a: f32 = match rng.random_bool(0.3) {
                true => rng.random_range(0.75..1.33),
                false => 1.0,
            };
            (Shape::Disk, material(rng), [d * a.sqrt(), d / a.sqrt()])
        }
        Kind::Rectangle => {
            let a: f32 = rng.random_range(0.5..2.0);
            (
                Shape::Rectangle,
                material(rng),
                [(area * a).sqrt(), (area / a).sqrt()],
            )
        }
        Kind::Column => {
            let a: f32 = rng.random_range(2.0..3.0);
            let m = match rng.random_bool(0.7) {
                true => Material::Liquid,
                false => Material::Snow,
            };
            let w = (area / a).sqrt().min(0.2);
            (Shape::Rectangle, m, [w, (a * w).min(0.55)])
        }
        Kind::Pool | Kind::Rope => {
            let w = rng.random_range(0.4..POOL_MAX[0]);
            let h = (area / w).clamp(0.04, POOL_MAX[1]);
            (Shape::Rectangle, Material::Liquid, [w, h])
        }
    };
    body(shape, m, [size[0].min(0.6), size[1].min(0.6)])
}

/// The larger side of a body's box.
fn extent(b: &Body) -> f32 {
    b.size[0].abs().max(b.size[1].abs())
}

/// Places `b` apart from `placed` ([`GAP`]) and clear of the walls ([`WALL_MARGIN`]); floor
/// kinds stand on the floor margin. A body that does not fit in 200 tries is shrunk by 15 %
/// and tried again, up to 5 times, then left out (None).
fn place(kind: Kind, mut b: Body, placed: &[Body], rng: &mut ChaCha8Rng) -> Option<Body> {
    let (lo, hi) = (WALL_MARGIN, 1.0 - WALL_MARGIN);
    for _ in 0..6 {
        let half = [b.size[0].abs() / 2.0, b.size[1].abs() / 2.0];
        if lo + half[0] < hi - half[0] && lo + half[1] < hi - half[1] {
            for _ in 0..200 {
                let x = rng.random_range(lo + half[0]..hi - half[0]);
                let y = match kind.on_floor() {
                    true => lo + half[1],
                    false => rng.random_range(lo + half[1]..hi - half[1]),
                };
                b.position = [x, y];
                if placed.iter().all(|p| p.apart(&b, GAP)) {
                    return Some(b);
                }
            }
        }
        b.size = [b.size[0] * 0.85, b.size[1] * 0.85];
    }
    None
}

/// Velocities (speed at most [`MAX_SPEED`], redrawn until no pair closes faster than
/// [`MAX_CLOSING`], else at rest) and spins (jelly and snow, at most [`MAX_SPIN`]); floor
/// bodies start at rest.
fn set_motion(bodies: &mut [Body], rng: &mut ChaCha8Rng) {
    for k in 0..bodies.len() {
        let floor = bodies[k].shape == Shape::Rectangle
            && (bodies[k].position[1] - bodies[k].size[1] / 2.0 - WALL_MARGIN).abs() < 1e-6;
        if floor {
            continue;
        }
        for _ in 0..20 {
            let angle: f32 = rng.random_range(0.0..std::f32::consts::TAU);
            let speed = MAX_SPEED * rng.random::<f32>();
            bodies[k].velocity = [speed * angle.cos(), speed * angle.sin()];
            if (0..k).all(|j| closing(&bodies[j], &bodies[k]) <= MAX_CLOSING) {
                break;
            }
            bodies[k].velocity = [0.0; 2];
        }
        if matches!(bodies[k].material, Material::Jelly | Material::Snow) {
            bodies[k].spin = rng.random_range(-MAX_SPIN..MAX_SPIN);
        }
    }
}

/// The speed at which `a` and `b` close in on each other along the line between their
/// centres (negative when they move apart).
fn closing(a: &Body, b: &Body) -> f32 {
    let d = [b.position[0] - a.position[0], b.position[1] - a.position[1]];
    let len = d[0].hypot(d[1]).max(1e-6);
    let dv = [b.velocity[0] - a.velocity[0], b.velocity[1] - a.velocity[1]];
    -(dv[0] * d[0] + dv[1] * d[1]) / len
}

/// The family's rules that `scene` breaks (empty when it could have been generated):
/// bodies at least [`WALL_MARGIN`] from the walls and [`GAP`] apart, speeds at most
/// [`MAX_SPEED`], no pair closing faster than [`MAX_CLOSING`], spins at most [`MAX_SPIN`],
/// liquid on the floor no wider or deeper than [`POOL_MAX`], the grid 64 or 128 with the
/// family's dt and substeps, the particle count one of [`COUNTS`].
pub fn outside(scene: &Scene) -> Vec<String> {
    let mut why = Vec::new();
    let eps = 1e-4;
    if !COUNTS.contains(&scene.particle_count()) {
        why.push(format!("{} particles", scene.particle_count()));
    }
    let settings = match scene.grid {
        64 => (8e-4, 20),
        128 => (2e-4, 80),
        _ => (0.0, 0),
    };
    if (scene.dt, scene.substeps) != settings {
        why.push(format!(
            "grid {} with dt {} x {}",
            scene.grid, scene.dt, scene.substeps
        ));
    }
    for (k, b) in scene.bodies.iter().enumerate() {
        let half = [b.size[0].abs() / 2.0, b.size[1].abs() / 2.0];
        let near_wall = (0..2).any(|a| {
            b.position[a] - half[a] < WALL_MARGIN - eps
                || b.position[a] + half[a] > 1.0 - WALL_MARGIN + eps
        });
        if near_wall {
            why.push(format!("body {k} within {WALL_MARGIN} of a wall"));
        }
        if b.velocity[0].hypot(b.velocity[1]) > MAX_SPEED + eps {
            why.push(format!("body {k} faster than {MAX_SPEED}"));
        }
        if b.spin.abs() > MAX_SPIN + eps {
            why.push(format!("body {k} spins faster than {MAX_SPIN}"));
        }
        let on_floor = b.position[1] - half[1] < WALL_MARGIN + eps;
        let wide = b.size[0] > POOL_MAX[0] + eps || b.size[1] > POOL_MAX[1] + eps;
        if b.material == Material::Liquid
            && b.shape == Shape::Rectangle
            && on_floor
            && wide
            && b.size[1] < b.size[0]
        {
            why.push(format!("body {k}: a pool larger than {POOL_MAX:?}"));
        }
        for (j, a) in scene.bodies[..k].iter().enumerate() {
            if !a.apart(b, GAP - eps) {
                why.push(format!("bodies {j} and {k} closer than {GAP}"));
            }
            if closing(a, b) > MAX_CLOSING + eps {
                why.push(format!(
                    "bodies {j} and {k} close in faster than {MAX_CLOSING}"
                ));
            }
        }
    }
    why
}

#[cfg(test)]
mod tests {
    use super::*;

    fn generated(id: u32) -> Scene {
        super::super::families::scene(super::super::Family::Mixed, id, 0)
    }

    #[test]
    fn generated_scenes_are_valid_and_inside_the_family() {
        for id in 0..400 {
            let s = generated(id);
            s.validate().unwrap_or_else(|e| panic!("{}: {e}", s.name));
            assert_eq!(outside(&s), Vec::<String>::new(), "{}", s.name);
            assert!((1..=4).contains(&s.bodies.len()), "{}", s.name);
        }
    }

    #[test]
    fn the_family_spans_both_grids_every_count_and_every_kind() {
        let scenes: Vec<Scene> = (0..200).map(generated).collect();
        for grid in [64, 128] {
            assert!(scenes.iter().any(|s| s.grid == grid));
        }
        for n in COUNTS {
            assert!(scenes.iter().any(|s| s.particle_count() == n), "{n}");
        }
        for kind in ["disk", "rect", "rope", "column", "pool"] {
            assert!(scenes.iter().any(|s| s.name.contains(kind)), "{kind}");
        }
        for m in [
            Material::Liquid,
            Material::Jelly,
            Material::Snow,
            Material::Rope,
        ] {
            assert!(scenes
                .iter()
                .any(|s| s.bodies.iter().any(|b| b.material == m)));
        }
    }

    #[test]
    fn a_scene_is_a_function_of_id_and_seed() {
        let a = super::super::families::scene(super::super::Family::Mixed, 7, 3);
        let b = super::super::families::scene(super::super::Family::Mixed, 7, 3);
        let c = super::super::families::scene(super::super::Family::Mixed, 7, 4);
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn head_on_bodies_and_touching_bodies_are_outside() {
        let mut s = generated(1);
        let mut a = body(Shape::Disk, Material::Jelly, [0.15, 0.15]);
        a.position = [0.3, 0.5];
        a.velocity = [2.0, 0.0];
        let mut b = a.clone();
        b.position = [0.7, 0.5];
        b.velocity = [-2.0, 0.0];
        s.bodies = vec![a.clone(), b];
        assert!(outside(&s).iter().any(|w| w.contains("close in")));
        let mut c = a.clone();
        c.position = [0.3, 0.66];
        c.velocity = [2.0, 0.0];
        s.bodies = vec![a, c];
        assert!(outside(&s).iter().any(|w| w.contains("closer than")));
    }
}
