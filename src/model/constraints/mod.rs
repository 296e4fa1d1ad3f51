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
//! - liquid pressure ([`pressure`]): the liquid's velocities and volume fraction on a grid,
//!   and a unilateral pressure solve that removes its compression and its compressing
//!   velocity, as FLIP and MPM liquids stay incompressible (after the density part), then
//!   optionally a share of the kinetic energy the projection took given back ([`energy`]);
//! - the box walls: positions clamped into the range the solver's particles stay in, in
//!   the scene's own solver cells where its grid is known ([`WallParams::bounds`]);
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
//! the node and offline `eval` project alike, batched and unbatched alike. On a GPU the parts
//! but momentum and rebound also have a device form, laid out by [`projection_plan`] (the
//! same steps in the same order; `crate::ops`' CUDA kernels). [`mod@fit`] fits the
//! parameters on the truth; the cell list of [`crate::neighbours`] finds the bodies (fixed
//! radius), their particle spacing (k nearest) and their contacts (fixed radius).

mod contact;
mod density;
mod device;
mod energy;
pub mod fit;
mod index;
mod momentum;
mod params;
mod parts;
mod pressure;
mod rebound;
mod rope;
mod shape;
mod spacing;

pub use device::projection_plan;
pub use fit::{fit, FitReport};
pub use params::{
    Constraints, ContactParams, DensityParams, MomentumParams, PressureParams, ReboundParams,
    RopeParams, ShapeParams, WallParams,
};
pub use parts::Parts;

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
        let spacing = spacing::spacing_of(frame, stride, material, m);
        out.extend(
            shape::pieces(frame, stride, material, m, spacing)
                .into_iter()
                .map(|p| (m, p)),
        );
    }
    out
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
    /// The liquid of the pressure projection (the part on).
    pressure: Option<pressure::Pressure>,
    /// The jelly bodies' contacts in progress (the rebound part on).
    rebound: Option<rebound::Rebound>,
    /// The frame before the projection (reused from frame to frame).
    before: Vec<f32>,
    /// The solver grid the scene was made on, if known (the walls and the pressure part's
    /// threshold depend on it).
    grid: Option<u32>,
}

impl SceneShape {
    /// The constraint data of a scene whose rest frame is `rest` (`[N, stride]` rows, x and
    /// y first, domain units) with material ids `material` (`[N]`), for the parts of `c`
    /// that are on.
    pub fn new(rest: &[f32], stride: usize, material: &[u8], c: &Constraints) -> Self {
        Self::on_grid(rest, stride, material, c, None)
    }

    /// [`SceneShape::new`] for a scene the solver made on a `grid` x `grid` grid (when
    /// known: the walls stand in its cells, [`WallParams::bounds`], and the liquid's pressure
    /// part picks its threshold by it, [`PressureParams::rest_for`]).
    pub fn on_grid(
        rest: &[f32],
        stride: usize,
        material: &[u8],
        c: &Constraints,
        grid: Option<u32>,
    ) -> Self {
        let n = material.len();
        let mut spacing = [0.0f32; COUNT];
        for (m, s) in spacing.iter_mut().enumerate() {
            *s = spacing::spacing_of(rest, stride, material, m as u8);
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
        let pressure = c.pressure.as_ref().and_then(|p| {
            let s = spacing[usize::from(Material::Liquid.id())];
            pressure::Pressure::new(rest, stride, material, s, (p, grid))
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
            pressure,
            rebound,
            before: Vec::new(),
            grid,
        }
    }

    /// The particle spacing of material `m` in the rest frame (domain units; 0 where the
    /// scene has none of it).
    pub fn spacing(&self, m: u8) -> f32 {
        self.spacing.get(usize::from(m)).copied().unwrap_or(0.0)
    }

    /// The rebound part's bodies (0 without the part or a jelly body).
    pub fn rebound_bodies(&self) -> usize {
        self.rebound.as_ref().map_or(0, |r| r.body_count())
    }

    /// Writes the rebound part's contacts in progress into `out` (`[r (r + 4) 3]`, zeroed:
    /// `crate::ops::ProjectionPlan::events`' layout), for a call of at most `r` bodies a scene.
    pub fn write_events(&mut self, r: usize, out: &mut [f32]) {
        if let Some(rebound) = &mut self.rebound {
            rebound.write_table(r, out);
        }
    }

    /// Hands the rebound part the contacts a device call left (scene `at` of the call's
    /// `tables`, `r` bodies a row), read when next used.
    pub fn defer_events(&mut self, tables: crate::ops::TablesLater, r: usize, at: usize) {
        if let Some(rebound) = &mut self.rebound {
            rebound.defer(tables, r, at);
        }
    }

    /// Projects `frame` (`[N, 4]` physical x, y, vx, vy), predicted from `prev` (`[N, 4]`,
    /// the frame `dt` before), onto the constraints of `c` in place: positions moved,
    /// velocities given the move over `dt`, then the liquid's share of the kinetic energy the
    /// projection took given back where the pressure part's `restore` asks ([`energy`]).
    /// Without `prev` the momentum and rebound parts are left out.
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
        if let (Some(p), Some(pressure)) = (&c.pressure, &mut self.pressure) {
            let walls = c.walls.map_or((0.0, 1.0), |w| w.bounds(self.grid));
            pressure.project(p, frame, material, dt, walls);
        }
        if let (Some(p), Some(prev), Some(rebound)) = (&c.rebound, prev, &mut self.rebound) {
            rebound.apply(p, (prev, &before, frame), dt);
        }
        if let (Some(p), Some(prev)) = (&c.momentum, prev) {
            momentum::conserve(p, prev, &before, frame, dt);
        }
        if let Some(w) = &c.walls {
            let (lo, hi) = w.bounds(self.grid);
            for row in frame.chunks_exact_mut(4) {
                row[0] = row[0].clamp(lo, hi);
                row[1] = row[1].clamp(lo, hi);
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
        if let (Some(p), Some(pressure)) = (&c.pressure, &self.pressure) {
            energy::restore(p.restore, &before, frame, pressure.ids());
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
    fn walls_clamp_and_the_velocity_takes_the_move() {
        let c = Constraints {
            walls: Some(WallParams {
                lo: 0.1,
                hi: 0.9,
                cells: None,
            }),
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

    #[test]
    fn the_energy_restore_gives_the_liquid_back_speed_not_places() {
        // A 30 x 30 liquid pool at rest, then falling and closing in on its middle: the
        // pressure part removes the compressing velocity of its full region, and its energy.
        let mut rest = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                rest.extend([0.3 + 0.01 * i as f32, 0.1 + 0.01 * j as f32, 0.0, 0.0]);
            }
        }
        let closing: Vec<f32> = rest
            .chunks(4)
            .flat_map(|r| [r[0], r[1], -4.0 * (r[0] - 0.445), -1.0])
            .collect();
        let project = |restore| {
            let c = Constraints {
                pressure: Some(PressureParams {
                    rest: 1.1,
                    full: 0.9 / 1.1,
                    band: 0.0,
                    band_rest: 1.0,
                    restore,
                    ..PressureParams::DEFAULT
                }),
                ..Default::default()
            };
            let mut shape = SceneShape::new(&rest, 4, &[0; 900], &c);
            let mut frame = closing.clone();
            shape.project(&c, (None, &mut frame), &[0; 900], 0.016);
            frame
        };
        let sums = |f: &[f32]| {
            f.chunks(4).fold([0.0f64; 3], |[e, u, v], r| {
                let (a, b) = (f64::from(r[2]), f64::from(r[3]));
                [e + a * a + b * b, u + a, v + b]
            })
        };
        let (off, on) = (project(0.0), project(1.0));
        let (e_off, e_on, e_net) = (sums(&off), sums(&on), sums(&closing));
        assert!(e_off[0] < e_net[0], "the projection took energy: {e_off:?}");
        assert!(
            e_on[0] > e_off[0] && e_on[0] <= e_net[0] + 1e-3,
            "{e_on:?} {e_off:?}"
        );
        assert!((e_on[1] - e_off[1]).abs() < 1e-3 && (e_on[2] - e_off[2]).abs() < 1e-3);
        let places = |f: &[f32]| f.chunks(4).flat_map(|r| [r[0], r[1]]).collect::<Vec<_>>();
        assert_eq!(places(&on), places(&off));
    }

    #[test]
    fn walls_stand_in_the_scenes_own_solver_cells() {
        let c = Constraints {
            walls: Some(WallParams {
                lo: 0.03,
                hi: 0.97,
                cells: Some(1.8),
            }),
            ..Default::default()
        };
        let rest = [0.5, 0.5, 0.0, 0.0];
        let below = |grid| {
            let mut shape = SceneShape::on_grid(&rest, 4, &[0], &c, grid);
            let mut frame = [0.985, 0.02, 0.0, 0.0];
            shape.project(&c, (None, &mut frame), &[0], 0.01);
            [frame[0], frame[1]]
        };
        // 64^2: 1.8 / 64 = 0.028125 from each edge; 128^2: 0.0140625, inside which the
        // frame already is; an unknown grid: lo and hi.
        assert_eq!(below(Some(64)), [1.0 - 1.8 / 64.0, 1.8 / 64.0]);
        assert_eq!(below(Some(128)), [0.985, 0.02]);
        assert_eq!(below(None), [0.97, 0.03]);
    }
}
