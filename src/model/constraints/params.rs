//! The parameters of each constraint part, as `model.json`'s `"constraints"` holds them
//! ([`Constraints`]), and the defaults of a model none were fitted for. The parts themselves
//! live in the sibling modules; [`super::Parts`] selects which of them run.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::Parts;
use crate::material::Material;

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
    /// Liquid: the pressure projection on a grid (none in models saved before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pressure: Option<PressureParams>,
}

/// Rebound parameters ([`super::rebound`]).
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

/// Momentum parameters ([`super::momentum`]).
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

/// Contact parameters ([`super::contact`]).
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

/// Rope parameters ([`super::rope`]).
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

/// Shape-matching parameters ([`super::shape`]).
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

/// Liquid density parameters ([`super::density`]).
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

/// Liquid pressure-projection parameters ([`super::pressure`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PressureParams {
    /// Node spacing of the pressure grid in particle spacings of the rest frame (2 puts about
    /// 4 particles in a cell, as the solver's rest state does).
    pub radius: f32,
    /// Volume fraction above which a node counts as compressed, over the rest frame's 1,
    /// for a scene whose solver grid is unknown or not in `rest_by_grid` (fitted: `minflow
    /// constraints fit`, the least that leaves the truth in place).
    pub rest: f32,
    /// The same per solver grid (cells per side): the solver's liquid settles towards a
    /// density its grid sets (a 64 x 64 scene's expands from its sampling, a 128 x 128 one's
    /// packs to twice it), so each grid has its own threshold, fitted on its scenes.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub rest_by_grid: BTreeMap<u32, f32>,
    /// Share of the threshold from which a node is full: it takes pressure, and its
    /// compressing velocity is removed; nodes below are free surface.
    pub full: f32,
    /// Width of the band along each wall, in solver cells (of a 64 x 64 grid when the
    /// scene's is unknown), where the threshold is `band_rest` times higher: the solver's
    /// liquid packs against its walls, whose boundary nodes stop the flow, to well above its
    /// density elsewhere.
    #[serde(default = "PressureParams::default_band")]
    pub band: f32,
    /// The threshold's multiple in the band along the walls.
    #[serde(default = "PressureParams::default_band_rest")]
    pub band_rest: f32,
    /// Share of a node's excess compression removed per frame (0..=1).
    pub stiffness: f32,
    /// Whether the velocity's compressing divergence at full nodes is removed too (else the
    /// density error alone is corrected).
    pub velocity: bool,
    /// Projected SOR sweeps (red and black) per frame.
    pub iterations: usize,
    /// Over-relaxation of the sweeps (1 is Gauss-Seidel; below 2).
    pub omega: f32,
    /// Share (0..=1) of the kinetic energy that the projection took from the liquid given
    /// back to its motion relative to its mean velocity (`super::energy`): MPM's weakly
    /// compressible liquid stores a compression's energy and returns it as a splash, which a
    /// projection removes; 0 in models saved before it existed.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub restore: f32,
}

/// Whether `v` is 0 (a field left out of `model.json`).
fn is_zero(v: &f32) -> bool {
    *v == 0.0
}

impl PressureParams {
    /// Nodes 2 spacings apart, compressed above 2 (the loosest grid's, see `rest_by_grid`),
    /// full from 0.8 of it, half the excess removed a frame, the velocity part on, 40 sweeps
    /// at over-relaxation 1.6.
    pub const DEFAULT: PressureParams = PressureParams {
        radius: 2.0,
        rest: 2.0,
        rest_by_grid: BTreeMap::new(),
        full: 0.8,
        band: 4.0,
        band_rest: 1.4,
        stiffness: 0.5,
        velocity: true,
        iterations: 40,
        omega: 1.6,
        restore: 0.0,
    };
}

impl PressureParams {
    /// [`PressureParams::band`]'s value in models saved before it existed.
    fn default_band() -> f32 {
        4.0
    }

    /// [`PressureParams::band_rest`]'s value in models saved before it existed.
    fn default_band_rest() -> f32 {
        1.4
    }

    /// The compressed threshold of a scene made on the solver grid `grid` (`rest` when
    /// unknown or not fitted).
    pub fn rest_for(&self, grid: Option<u32>) -> f32 {
        grid.and_then(|g| self.rest_by_grid.get(&g).copied())
            .unwrap_or(self.rest)
    }
}

impl DensityParams {
    /// Cell 3 spacings, rest mass 3x the rest frame's (what the fit finds: the `fluid`
    /// family's liquid starts at a third of the solver's rest density), 2 iterations.
    pub const LOOSE: DensityParams = DensityParams {
        radius: 3.0,
        rest: 3.0,
        iterations: 2,
    };
}

/// The box: positions are clamped into `[lo, hi]` on both axes (domain units), or, in a
/// scene whose solver grid `n` is known, into `[cells / n, 1 - cells / n]`: MLS-MPM's walls
/// are its boundary nodes (index < 3 or > n - 3, `MPM.md`), so its particles stop about 1.8
/// of the scene's own cells from the box's edge (a `multi` scene on 64^2 never goes below
/// 0.028, a `fluid` one on 128^2 reaches 0.014): one box for both let a surrogate's
/// `multi` liquid settle a cell below the truth's floor, a thinner sheet.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WallParams {
    /// Lowest coordinate a particle may take.
    pub lo: f32,
    /// Highest coordinate a particle may take.
    pub hi: f32,
    /// The walls' distance from the box's edge in the scene's solver cells, when fitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cells: Option<f32>,
}

impl WallParams {
    /// The walls `(lo, hi)` (domain units) of a scene on the solver grid `grid`: by
    /// [`WallParams::cells`] where both are known, else `lo` and `hi`.
    pub fn bounds(&self, grid: Option<u32>) -> (f32, f32) {
        match (self.cells, grid) {
            (Some(c), Some(n)) if n > 0 => (c / n as f32, 1.0 - c / n as f32),
            _ => (self.lo, self.hi),
        }
    }
}

impl Constraints {
    /// Parameters for a model none were fitted for: rope stretch 1.25, rigid jelly, no snow
    /// part, the liquid's pressure projection ([`PressureParams::DEFAULT`]; the older
    /// density part off: [`DensityParams::LOOSE`] on request), walls at the solver's
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
            liquid: None,
            walls: Some(WallParams {
                lo: 0.5 / 128.0,
                hi: 1.0 - 0.5 / 128.0,
                cells: None,
            }),
            contact: Some(ContactParams {
                distance: 1.0,
                iterations: 3,
                restitution: 0.8,
            }),
            momentum: Some(MomentumParams::DEFAULT),
            rebound: Some(ReboundParams::DEFAULT),
            pressure: Some(PressureParams::DEFAULT.clone()),
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
            pressure: self.pressure.clone().filter(|_| parts.pressure),
        }
    }

    /// These constraints with the parts `parts` names taken from `fitted`, present there or
    /// not, and the others kept (`constraints fit --parts` rewrites only what it fits).
    pub fn replaced(&self, fitted: &Constraints, parts: Parts) -> Self {
        fn pick<T: Clone>(on: bool, new: &Option<T>, old: &Option<T>) -> Option<T> {
            match on {
                true => new.clone(),
                false => old.clone(),
            }
        }
        Self {
            rope: pick(parts.rope, &fitted.rope, &self.rope),
            jelly: pick(parts.jelly, &fitted.jelly, &self.jelly),
            snow: pick(parts.snow, &fitted.snow, &self.snow),
            liquid: pick(parts.liquid, &fitted.liquid, &self.liquid),
            walls: pick(parts.walls, &fitted.walls, &self.walls),
            contact: pick(parts.contact, &fitted.contact, &self.contact),
            momentum: pick(parts.momentum, &fitted.momentum, &self.momentum),
            rebound: pick(parts.rebound, &fitted.rebound, &self.rebound),
            pressure: pick(parts.pressure, &fitted.pressure, &self.pressure),
        }
    }

    /// Whether no part is on.
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// The shape parameters of a shape-matched material (jelly, snow), if that part is on.
    pub(super) fn shape_of(&self, m: u8) -> Option<&ShapeParams> {
        match Material::from_id(m) {
            Some(Material::Jelly) => self.jelly.as_ref(),
            Some(Material::Snow) => self.snow.as_ref(),
            _ => None,
        }
    }
}
