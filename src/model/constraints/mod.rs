//! `model::constraints`: structure by construction. After the network predicts a frame, its
//! positions are projected onto the material's constraints, as position-based dynamics does
//! after each step (Müller et al. 2007, "Position Based Dynamics"; the method behind NVIDIA
//! Flex), and the velocities take the correction: `v_c = v' + (x_c - x') / dt`.
//!
//! Per material, each part switchable ([`Parts`]) and with its parameters in `model.json`
//! ([`Constraints`], written by `minflow constraints fit`):
//! - rope ([`rope`]): distance constraints along the chain plus unilateral long-range pairs
//!   `i -> i + 2^m`, applied coarse to fine (Kim, Chentanez & Müller 2012, "Long Range
//!   Attachments"), so a rope stretches at most as far as the solver's does;
//! - jelly and snow ([`shape`]): shape matching of each body to its rest shape (Müller et
//!   al. 2005, "Meshless Deformations Based on Shape Matching"), with an optional linear
//!   part and, for snow, a rest shape that yields (plasticity);
//! - liquid ([`density`]): a unilateral density constraint, `rho_i <= rho_0` (Macklin &
//!   Müller 2013, "Position Based Fluids"), the density measured on a grid as MPM does
//!   (Kugelstadt et al. 2019), its rest density fitted so that it leaves the truth's frames
//!   in place;
//! - the box walls: positions clamped into the range the solver's particles stay in;
//! - contact ([`contact`]): shape-matched bodies pushed apart where they overlap, each as a
//!   rigid translation, before their shape matching;
//! - momentum ([`momentum`]): each cluster of particles clear of the walls and of the other
//!   clusters moved rigidly onto free flight (its momentum changed by gravity alone, as MPM
//!   keeps it), after the other parts and before the walls;
//! - rebound ([`rebound`]): a jelly body leaving a wall or another jelly body at between
//!   `restitution` and 1 times the speed it hit it with, each contact remembered from its
//!   first frame (before the momentum part).
//!
//! A scene's constraint data ([`SceneShape`]: rope chains, bodies and their rest shapes, the
//! liquid's grid cell and rest mass, the particle spacing of each material) is built once
//! from its rest frame (the first frame the model sees) and carried in the surrogate's
//! per-scene state. The projection is a host pass, one scene at a time and deterministic:
//! the node and offline `eval` project alike, batched and unbatched alike. [`mod@fit`] fits the
//! parameters on the truth; the cell list of [`crate::neighbours`] finds the bodies (fixed
//! radius), their particle spacing (k nearest) and their contacts (fixed radius).

mod contact;
mod density;
pub mod fit;
mod index;
mod momentum;
mod rebound;
mod rope;
mod shape;

pub use fit::{fit, FitReport};

use serde::{Deserialize, Serialize};

use crate::material::{Material, COUNT};

/// The bodies of a frame (`[N, stride]` rows, x and y first, domain units; material ids
/// `material`, `[N]`): for each material, its connected pieces, particles closer than 2.5
/// of that material's particle spacings joined (the pieces shape matching projects, found
/// the same way for every material). Each piece is `(material id, particle indices in
/// increasing order)`, of 3 particles or more; in material order, then by lowest index.
/// Used by `eval`'s conservation diagnostics ([`crate::eval::conservation`]).
pub fn pieces(frame: &[f32], stride: usize, material: &[u8]) -> Vec<(u8, Vec<u32>)> {
    let mut out = Vec::new();
    for m in 0..COUNT as u8 {
        let spacing = shape::spacing_of(frame, stride, material, m);
        out.extend(
            shape::pieces(frame, stride, material, m, spacing)
                .into_iter()
                .map(|p| (m, p)),
        );
    }
    out
}

/// The constraint parameters of a model, per material (`"constraints"` in `model.json`). A
/// part that is `None` is never applied.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Constraints {
    /// Rope: chain and long-range distance limits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rope: Option<RopeParams>,
    /// Jelly: shape matching.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jelly: Option<ShapeParams>,
    /// Snow: shape matching with a yielding rest shape.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub snow: Option<ShapeParams>,
    /// Liquid: the unilateral density constraint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub liquid: Option<DensityParams>,
    /// The box walls.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub walls: Option<WallParams>,
    /// Contact between shape-matched bodies (none in models saved before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contact: Option<ContactParams>,
    /// Momentum of free clusters (none in models saved before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub momentum: Option<MomentumParams>,
    /// Rebound of jelly bodies (none in models saved before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rebound: Option<ReboundParams>,
}

/// Rebound parameters ([`rebound`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReboundParams {
    /// Least share of the approach speed a jelly body leaves a contact with (the most is 1).
    /// The solver's jelly leaves at 0.61 (two disks closing at 2 domain units per time
    /// unit) to 0.87 (closing at 6) of it, and a floor at 0.83-0.95.
    pub restitution: f32,
    /// Two bodies are in contact while particles of both are this close (domain units).
    pub reach: f32,
    /// A body is in contact with a wall while a particle of it is this close (domain units).
    pub clearance: f32,
    /// The gap (to the wall, or between the bodies' nearest particles) beyond which a
    /// contact's rebound is enforced (domain units, below `reach` and `clearance`).
    pub release: f32,
    /// Approach speeds below this are resting contact, never bounced (domain units per time
    /// unit).
    pub resting: f32,
    /// Gravity (domain units per time unit squared): a body leaving a wall across gravity
    /// slows by `g dt` a frame.
    pub gravity: [f32; 2],
}

impl ReboundParams {
    /// Restitution 0.5 (under the solver's least, 0.61), the momentum part's reach (0.07) and
    /// clearance (0.08), released at 0.05 (3 cells of the 64 x 64 grid), resting below 0.5
    /// (about three frames of gravity), gravity `(0, -9.8)`.
    pub const DEFAULT: ReboundParams = ReboundParams {
        restitution: 0.5,
        reach: 0.07,
        clearance: 0.08,
        release: 0.05,
        resting: 0.5,
        gravity: [0.0, -9.8],
    };
}

/// Momentum parameters ([`momentum`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MomentumParams {
    /// Particles this close in the frame before or the predicted one share a cluster (domain
    /// units): two particles share a grid node of the 64 x 64 grid up to `3 sqrt(2) dx`
    /// (0.066) apart.
    pub reach: f32,
    /// Distance from a wall a cluster's particles keep on a free axis (domain units): a wall
    /// zeroes the velocity of the nodes within 3 cells of it, which reach particles 1.5 cells
    /// farther (docs/mpm.md; [`crate::eval::conservation::WALL_CLEARANCE`]).
    pub clearance: f32,
    /// Substeps per frame of the solver (20 on the 64 x 64 grid, 80 on the 128 x 128 one):
    /// sets the gravity's share in the centre of mass's move, `(1 + 1/S) / 2` of `g dt^2`.
    pub substeps: u32,
    /// Gravity (domain units per time unit squared).
    pub gravity: [f32; 2],
}

impl MomentumParams {
    /// Reach 0.07, clearance 0.08, 20 substeps, gravity `(0, -9.8)`: the generated scenes'
    /// solver on the 64 x 64 grid. On the 128 x 128 grid (80 substeps) the centre of mass
    /// then lands `g dt^2 (1/20 - 1/80) / 2` (4.7e-5 domain units) low per frame of free
    /// flight.
    pub const DEFAULT: MomentumParams = MomentumParams {
        reach: 0.07,
        clearance: 0.08,
        substeps: 20,
        gravity: [0.0, -9.8],
    };
}

/// Contact parameters ([`contact`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ContactParams {
    /// Closest two particles of different bodies may come, in particle spacings of the rest
    /// frame (the largest of the bodies' materials').
    pub distance: f32,
    /// Push-apart passes per frame.
    pub iterations: usize,
    /// Share of the closing speed two bodies leave a contact with (0 sticks, 1 is elastic;
    /// the solver's jelly disks rebound at 0.61-0.87 of their closing speed, docs/mpm.md
    /// check 4).
    #[serde(default)]
    pub restitution: f32,
}

/// Rope parameters ([`rope`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RopeParams {
    /// Largest distance between two rope particles as a multiple of their rest distance
    /// along the chain (dimensionless, >= 1): the solver's ropes stretch 10-23 %.
    pub stretch: f32,
    /// Coarse-to-fine sweeps per frame.
    pub iterations: usize,
    /// Long-range pairs `i -> i + 2^m` (m >= 1) beside the chain's own links.
    pub long_range: bool,
}

/// Shape-matching parameters ([`shape`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShapeParams {
    /// Share of the way to the goal positions a frame moves (0..=1; Müller 2005's alpha).
    pub stiffness: f32,
    /// Share of the linear fit in the goal, the rest a rotation (0..=1; Müller 2005's beta,
    /// section 4.2): 0 keeps the rest shape rigid, higher lets it shear and squash.
    pub linear: f32,
    /// Share of the remaining deformation the rest shape takes on per frame (0..=1):
    /// 0 elastic, above 0 plastic (snow).
    pub plastic: f32,
}

/// Liquid density parameters ([`density`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DensityParams {
    /// Cell of the density grid in particle spacings of the rest frame.
    pub radius: f32,
    /// Rest mass of a grid node over the rest frame's (90th percentile of its occupied
    /// nodes): above it a node counts as compressed and its particles are pushed out
    /// (fitted: `minflow constraints fit`).
    pub rest: f32,
    /// Jacobi iterations per frame.
    pub iterations: usize,
}

/// The box: positions are clamped into `[lo, hi]` on both axes (domain units).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WallParams {
    /// Lowest coordinate a particle may take.
    pub lo: f32,
    /// Highest coordinate a particle may take.
    pub hi: f32,
}

impl Constraints {
    /// Parameters for a model none were fitted for: rope stretch 1.25, rigid jelly, no snow
    /// part, liquid rest mass 3x the rest frame's (what the fit finds: the `fluid` family's
    /// liquid starts at a third of the solver's rest density), walls at the solver's
    /// `[0.5 dx, 1 - 0.5 dx]` of the 128 x 128 grid. `minflow constraints fit` replaces the
    /// fitted values from a model's training split.
    pub fn defaults() -> Self {
        Self {
            rope: Some(RopeParams {
                stretch: 1.25,
                iterations: 2,
                long_range: true,
            }),
            jelly: Some(ShapeParams {
                stiffness: 1.0,
                linear: 0.0,
                plastic: 0.0,
            }),
            snow: None,
            liquid: Some(DensityParams {
                radius: 3.0,
                rest: 3.0,
                iterations: 2,
            }),
            walls: Some(WallParams {
                lo: 0.5 / 128.0,
                hi: 1.0 - 0.5 / 128.0,
            }),
            contact: Some(ContactParams {
                distance: 1.0,
                iterations: 3,
                restitution: 0.8,
            }),
            momentum: Some(MomentumParams::DEFAULT),
            rebound: Some(ReboundParams::DEFAULT),
        }
    }

    /// These constraints with the parts `parts` leaves out removed.
    pub fn select(&self, parts: Parts) -> Self {
        Self {
            rope: self.rope.filter(|_| parts.rope),
            jelly: self.jelly.filter(|_| parts.jelly),
            snow: self.snow.filter(|_| parts.snow),
            liquid: self.liquid.filter(|_| parts.liquid),
            walls: self.walls.filter(|_| parts.walls),
            contact: self.contact.filter(|_| parts.contact),
            momentum: self.momentum.filter(|_| parts.momentum),
            rebound: self.rebound.filter(|_| parts.rebound),
        }
    }

    /// Whether no part is on.
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// The shape parameters of a shape-matched material (jelly, snow), if that part is on.
    fn shape_of(&self, m: u8) -> Option<&ShapeParams> {
        match Material::from_id(m) {
            Some(Material::Jelly) => self.jelly.as_ref(),
            Some(Material::Snow) => self.snow.as_ref(),
            _ => None,
        }
    }
}

/// Which parts of a model's [`Constraints`] to apply (`--constraints`): `on` (every part the
/// model has), `off`, or a comma-separated list of `rope`, `jelly`, `snow`, `liquid`,
/// `walls`, `contact`, `momentum`, `rebound`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Parts {
    /// Rope chain and long-range pairs.
    pub rope: bool,
    /// Jelly shape matching.
    pub jelly: bool,
    /// Snow shape matching.
    pub snow: bool,
    /// Liquid density.
    pub liquid: bool,
    /// Box walls.
    pub walls: bool,
    /// Contact between shape-matched bodies.
    pub contact: bool,
    /// Momentum of free clusters.
    pub momentum: bool,
    /// Rebound of jelly bodies.
    pub rebound: bool,
}

impl Parts {
    /// Every part.
    pub const ALL: Parts = Parts {
        rope: true,
        jelly: true,
        snow: true,
        liquid: true,
        walls: true,
        contact: true,
        momentum: true,
        rebound: true,
    };
    /// No part.
    pub const NONE: Parts = Parts {
        rope: false,
        jelly: false,
        snow: false,
        liquid: false,
        walls: false,
        contact: false,
        momentum: false,
        rebound: false,
    };
}

impl Default for Parts {
    fn default() -> Self {
        Parts::ALL
    }
}

impl std::str::FromStr for Parts {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            "on" | "all" => return Ok(Parts::ALL),
            "off" | "none" => return Ok(Parts::NONE),
            _ => {}
        }
        let mut parts = Parts::NONE;
        for name in s.split(',').map(str::trim) {
            let flag = match name {
                "rope" => &mut parts.rope,
                "jelly" => &mut parts.jelly,
                "snow" => &mut parts.snow,
                "liquid" => &mut parts.liquid,
                "walls" => &mut parts.walls,
                "contact" => &mut parts.contact,
                "momentum" => &mut parts.momentum,
                "rebound" => &mut parts.rebound,
                other => {
                    return Err(format!(
                        "unknown constraint part {other:?}: expected on, off or a list of \
                         rope, jelly, snow, liquid, walls, contact, momentum, rebound"
                    ))
                }
            };
            *flag = true;
        }
        Ok(parts)
    }
}

impl std::fmt::Display for Parts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if *self == Parts::ALL {
            return f.write_str("on");
        }
        if *self == Parts::NONE {
            return f.write_str("off");
        }
        let names = [
            (self.rope, "rope"),
            (self.jelly, "jelly"),
            (self.snow, "snow"),
            (self.liquid, "liquid"),
            (self.walls, "walls"),
            (self.contact, "contact"),
            (self.momentum, "momentum"),
            (self.rebound, "rebound"),
        ];
        let on: Vec<&str> = names.iter().filter(|(b, _)| *b).map(|(_, n)| *n).collect();
        f.write_str(&on.join(","))
    }
}

/// How far a projection moved each material: the sum over moved frames and particles of the
/// displacement in particle spacings of the rest frame, and the particle-frames counted.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Correction {
    /// Per material id: summed displacement, spacings.
    pub sum: [f64; COUNT],
    /// Per material id: particle-frames.
    pub count: [u64; COUNT],
}

impl Correction {
    /// Adds `other`'s sums and counts.
    pub fn add(&mut self, other: &Correction) {
        for m in 0..COUNT {
            self.sum[m] += other.sum[m];
            self.count[m] += other.count[m];
        }
    }

    /// The mean displacement per particle and frame of material `m`, in spacings; None where
    /// none was counted.
    pub fn mean(&self, m: usize) -> Option<f64> {
        (self.count[m] > 0).then(|| self.sum[m] / self.count[m] as f64)
    }
}

/// One scene's constraint data, built from its rest frame (see the module doc).
#[derive(Clone, Debug)]
pub struct SceneShape {
    n: usize,
    /// Per material id: the particle spacing of the rest frame (domain units).
    spacing: [f32; COUNT],
    chains: Vec<rope::Chain>,
    bodies: Vec<shape::Body>,
    /// Contact between the bodies (two or more of them, the part on).
    contact: Option<contact::Contact>,
    liquid: Option<density::Liquid>,
    /// The jelly bodies' contacts in progress (the rebound part on).
    rebound: Option<rebound::Rebound>,
    /// The frame before the projection (reused from frame to frame).
    before: Vec<f32>,
}

impl SceneShape {
    /// The constraint data of a scene whose rest frame is `rest` (`[N, stride]` rows, x and
    /// y first, domain units) with material ids `material` (`[N]`), for the parts of `c`
    /// that are on.
    pub fn new(rest: &[f32], stride: usize, material: &[u8], c: &Constraints) -> Self {
        let n = material.len();
        let mut spacing = [0.0f32; COUNT];
        for (m, s) in spacing.iter_mut().enumerate() {
            *s = shape::spacing_of(rest, stride, material, m as u8);
        }
        let chains = match c.rope {
            Some(_) => rope::chains(rest, stride, material, Material::Rope.id()),
            None => Vec::new(),
        };
        if let Some(link) = rope::median_link(&chains) {
            spacing[usize::from(Material::Rope.id())] = link;
        }
        let mut bodies = Vec::new();
        for m in [Material::Jelly.id(), Material::Snow.id()] {
            if c.shape_of(m).is_some() {
                let s = spacing[usize::from(m)];
                bodies.extend(shape::bodies(rest, stride, material, m, s));
            }
        }
        let contact = c
            .contact
            .and_then(|_| contact::Contact::new(&bodies, n, &spacing));
        let liquid = c.liquid.as_ref().and_then(|p| {
            let s = spacing[usize::from(Material::Liquid.id())];
            density::Liquid::new(rest, stride, material, s, p)
        });
        let rebound = c.rebound.and_then(|_| {
            let m = Material::Jelly.id();
            let s = spacing[usize::from(m)];
            rebound::Rebound::new(&shape::pieces(rest, stride, material, m, s), n)
        });
        Self {
            n,
            spacing,
            chains,
            bodies,
            contact,
            liquid,
            rebound,
            before: Vec::new(),
        }
    }

    /// The particle spacing of material `m` in the rest frame (domain units; 0 where the
    /// scene has none of it).
    pub fn spacing(&self, m: u8) -> f32 {
        self.spacing.get(usize::from(m)).copied().unwrap_or(0.0)
    }

    /// Projects `frame` (`[N, 4]` physical x, y, vx, vy), predicted from `prev` (`[N, 4]`,
    /// the frame `dt` before), onto the constraints of `c` in place: positions moved,
    /// velocities given the move over `dt`. Without `prev` the momentum and rebound parts are
    /// left out.
    /// Snow's rest shapes yield (the scene's data changes). Returns how far each material
    /// moved.
    ///
    /// # Panics
    /// When `frame` is not `N` rows of 4.
    pub fn project(
        &mut self,
        c: &Constraints,
        (prev, frame): (Option<&[f32]>, &mut [f32]),
        material: &[u8],
        dt: f32,
    ) -> Correction {
        assert_eq!(
            frame.len(),
            self.n * 4,
            "projection of a frame of another scene"
        );
        let mut before = std::mem::take(&mut self.before);
        before.clear();
        before.extend_from_slice(frame);
        if let Some(p) = &c.rope {
            for chain in &self.chains {
                chain.project(p, frame);
            }
        }
        if let (Some(p), Some(contact)) = (&c.contact, &self.contact) {
            contact.separate(p, frame, dt);
        }
        for body in &mut self.bodies {
            if let Some(p) = c.shape_of(body.material) {
                body.project(p, frame);
            }
        }
        if let (Some(p), Some(liquid)) = (&c.liquid, &mut self.liquid) {
            liquid.project(p, frame);
        }
        if let (Some(p), Some(prev), Some(rebound)) = (&c.rebound, prev, &mut self.rebound) {
            rebound.apply(p, (prev, &before, frame), dt);
        }
        if let (Some(p), Some(prev)) = (&c.momentum, prev) {
            momentum::conserve(p, prev, &before, frame, dt);
        }
        if let Some(w) = &c.walls {
            for row in frame.chunks_exact_mut(4) {
                row[0] = row[0].clamp(w.lo, w.hi);
                row[1] = row[1].clamp(w.lo, w.hi);
            }
        }
        let mut out = Correction::default();
        let inv_dt = if dt > 0.0 { 1.0 / dt } else { 0.0 };
        for (i, (row, old)) in frame
            .chunks_exact_mut(4)
            .zip(before.chunks_exact(4))
            .enumerate()
        {
            let (dx, dy) = (row[0] - old[0], row[1] - old[1]);
            row[2] += dx * inv_dt;
            row[3] += dy * inv_dt;
            let m = usize::from(material[i]).min(COUNT - 1);
            let s = self.spacing[m];
            if s > 0.0 {
                out.sum[m] += f64::from(dx.hypot(dy) / s);
            }
            out.count[m] += 1;
        }
        self.before = before;
        out
    }
}

/// A 5 x 5 block of particles (spacing 0.01, `[25, 4]` rows) with its lower left corner at
/// `(x0, y0)`, all moving at `v`: the momentum and rebound tests' body.
#[cfg(test)]
fn block(x0: f32, y0: f32, v: [f32; 2]) -> Vec<f32> {
    let mut f = Vec::new();
    for i in 0..5 {
        for j in 0..5 {
            f.extend([x0 + 0.01 * i as f32, y0 + 0.01 * j as f32, v[0], v[1]]);
        }
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_parse_and_print() {
        assert_eq!("on".parse::<Parts>().unwrap(), Parts::ALL);
        assert_eq!("off".parse::<Parts>().unwrap(), Parts::NONE);
        let p: Parts = "rope,liquid".parse().unwrap();
        assert!(p.rope && p.liquid && !p.jelly && !p.snow && !p.walls);
        assert_eq!(p.to_string(), "rope,liquid");
        assert!("ropes".parse::<Parts>().is_err());
    }

    #[test]
    fn selecting_no_part_leaves_nothing() {
        let c = Constraints::defaults();
        assert!(c.select(Parts::NONE).is_empty());
        assert!(!c.select("jelly".parse().unwrap()).is_empty());
        assert!(c.select("snow".parse().unwrap()).is_empty()); // the defaults have no snow
    }

    #[test]
    fn walls_clamp_and_the_velocity_takes_the_move() {
        let c = Constraints {
            walls: Some(WallParams { lo: 0.1, hi: 0.9 }),
            ..Default::default()
        };
        let rest = [0.5, 0.5, 0.0, 0.0];
        let mut shape = SceneShape::new(&rest, 4, &[0], &c);
        let mut frame = [0.95, 0.5, 1.0, 0.0];
        let corr = shape.project(&c, (None, &mut frame), &[0], 0.01);
        assert!((frame[0] - 0.9).abs() < 1e-6);
        // v = 1 + (0.9 - 0.95) / 0.01 = -4.
        assert!((frame[2] + 4.0).abs() < 1e-3, "{}", frame[2]);
        assert_eq!(corr.count[0], 1);
    }
}
