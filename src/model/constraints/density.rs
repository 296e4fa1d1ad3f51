//! The liquid's unilateral density constraint, position-based (Macklin & Müller 2013,
//! "Position Based Fluids", section 3: per constraint `lambda = -C / sum |grad C|^2`, moves
//! `dx = sum lambda grad C`, Jacobi), with the density measured on a grid as MPM measures
//! it (Kugelstadt et al. 2019, "Implicit Density Projection for Volume Conserving Liquids",
//! which projects FLIP particles by their grid density): each node of a grid of cell `h`
//! carries the mass `m_i = sum_p w_ip` of the liquid particles around it with MPM's quadratic
//! B-spline weights (docs/mpm.md), and where a node holds more than the rest mass `m_0`,
//! `C_i = m_i / m_0 - 1 > 0` (compressed: a surrogate pressing the liquid into a layer), its
//! particles are pushed out of it. Unilateral: a node at or below `m_0` (a surface, a splash)
//! is left alone.
//!
//! Why the grid: MPM lets a liquid's particles cluster inside cells (its state lives on the
//! grid), so per-particle SPH densities of the solver's own frames swing by 2-3x and a
//! particle-based constraint would push the truth (measured: `minflow constraints fit`
//! found no SPH rest density under 3x the rest frame's that left the truth's liquid within
//! 0.1 spacings a frame). The B-spline node mass averages over ~9 cells, as MPM does.
//!
//! `h` is `radius` particle spacings of the rest frame (2 puts ~4 particles in a cell, as
//! the solver does), and `m_0` is `rest` times the rest frame's occupied nodes' 90th
//! percentile mass, `rest` fitted so that the truth's own frames are hardly moved.

use super::DensityParams;

/// The liquid of one scene: its particles, the cell of its density grid and the rest mass.
#[derive(Clone, Debug)]
pub(super) struct Liquid {
    ids: Vec<u32>,
    /// Cell of the density grid (domain units).
    h: f32,
    /// Rest mass of a node (particles).
    m0: f32,
    /// Scratch of [`Liquid::project`], reused from frame to frame.
    scratch: Scratch,
}

/// The grid and buffers one projection uses.
#[derive(Clone, Debug, Default)]
struct Scratch {
    mass: Vec<f32>,
    lambda: Vec<f32>,
    denom: Vec<f32>,
    stencils: Vec<Stencil>,
}

/// Quantile of the rest frame's occupied node masses that `rest` multiplies.
const REST_QUANTILE: f32 = 0.9;
/// A node counts as occupied in the rest frame above this mass (particles).
const OCCUPIED: f32 = 0.5;

/// A particle's 3 x 3 nodes: the lower-left node and the weights and their derivatives
/// along each axis (MPM's quadratic B-spline, `docs/mpm.md`: [`crate::bspline::weights`]).
#[derive(Clone, Debug)]
struct Stencil {
    base: [i32; 2],
    w: [[f32; 3]; 2],
    dw: [[f32; 3]; 2],
}

impl Stencil {
    fn at(x: f32, y: f32, h: f32) -> Self {
        let (base, frac, w) = crate::bspline::stencil(x, y, h);
        let dw = frac.map(|f| [-(1.5 - f) / h, -2.0 * (f - 1.0) / h, (f - 0.5) / h]);
        Self { base, w, dw }
    }
}

/// Node masses on a grid of `side` x `side` nodes of cell `h` (nodes past the box's edge
/// clamped onto it).
struct Grid {
    side: i32,
    mass: Vec<f32>,
}

impl Grid {
    fn new(h: f32) -> Self {
        Self::with_buffer(h, Vec::new())
    }

    /// The grid of cell `h`, its masses in `buffer` (resized and zeroed).
    fn with_buffer(h: f32, mut mass: Vec<f32>) -> Self {
        let side = (1.0 / h).ceil() as i32 + 3;
        mass.clear();
        mass.resize((side * side) as usize, 0.0);
        Self { side, mass }
    }

    /// Visits the 9 nodes of `s`: node index, weight and weight gradient.
    fn each(&self, s: &Stencil, visit: impl FnMut(usize, f32, [f32; 2])) {
        each_node(self.side, s, visit);
    }

    /// The node masses of the particles `ids` of `frame` (`[N, stride]` rows).
    fn splat(&mut self, frame: &[f32], stride: usize, ids: &[u32], h: f32) -> Vec<Stencil> {
        let mut stencils = Vec::with_capacity(ids.len());
        self.splat_into(frame, stride, ids, h, &mut stencils);
        stencils
    }

    /// [`Grid::splat`] with the particles' stencils written into `stencils`.
    fn splat_into(
        &mut self,
        frame: &[f32],
        stride: usize,
        ids: &[u32],
        h: f32,
        stencils: &mut Vec<Stencil>,
    ) {
        self.mass.iter_mut().for_each(|m| *m = 0.0);
        stencils.clear();
        stencils.extend(ids.iter().map(|&i| {
            Stencil::at(
                frame[stride * i as usize],
                frame[stride * i as usize + 1],
                h,
            )
        }));
        let mass = &mut self.mass;
        for s in stencils.iter() {
            each_node(self.side, s, |n, w, _| mass[n] += w);
        }
    }
}

/// Visits the 9 nodes of `s` on a grid of `side` x `side` nodes (those past the box's edge
/// clamped onto it): node index, weight and weight gradient.
fn each_node(side: i32, s: &Stencil, mut visit: impl FnMut(usize, f32, [f32; 2])) {
    let c = |v: i32| v.clamp(0, side - 1);
    for a in 0..3 {
        for b in 0..3 {
            let w = s.w[0][a] * s.w[1][b];
            let g = [s.dw[0][a] * s.w[1][b], s.w[0][a] * s.dw[1][b]];
            let (i, j) = (c(s.base[0] + a as i32), c(s.base[1] + b as i32));
            visit((i * side + j) as usize, w, g);
        }
    }
}

impl Liquid {
    /// The liquid of the rest frame `rest` (`[N, stride]` rows) whose spacing is `spacing`;
    /// None without liquid particles or spacing.
    pub(super) fn new(
        rest: &[f32],
        stride: usize,
        material: &[u8],
        spacing: f32,
        p: &DensityParams,
    ) -> Option<Self> {
        let ids: Vec<u32> = (0..material.len() as u32)
            .filter(|&i| material[i as usize] == crate::material::Material::Liquid.id())
            .collect();
        if ids.is_empty() || spacing <= 0.0 {
            return None;
        }
        let h = p.radius * spacing;
        let mut grid = Grid::new(h);
        grid.splat(rest, stride, &ids, h);
        let mut occupied: Vec<f32> = grid
            .mass
            .iter()
            .copied()
            .filter(|&m| m > OCCUPIED)
            .collect();
        if occupied.is_empty() {
            return None;
        }
        let q = ((occupied.len() - 1) as f32 * REST_QUANTILE) as usize;
        occupied.select_nth_unstable_by(q, f32::total_cmp);
        let m0 = p.rest * occupied[q];
        Some(Self {
            ids,
            h,
            m0,
            scratch: Scratch::default(),
        })
    }

    /// Projects the liquid's particles in `frame` (`[N, 4]` rows): `p.iterations` Jacobi
    /// iterations over the compressed nodes (module doc).
    pub(super) fn project(&mut self, p: &DensityParams, frame: &mut [f32]) {
        let Scratch {
            mass,
            mut lambda,
            mut denom,
            mut stencils,
        } = std::mem::take(&mut self.scratch);
        let mut grid = Grid::with_buffer(self.h, mass);
        let inv_m0 = 1.0 / self.m0;
        lambda.resize(grid.mass.len(), 0.0);
        denom.resize(grid.mass.len(), 0.0);
        for _ in 0..p.iterations {
            grid.splat_into(frame, 4, &self.ids, self.h, &mut stencils);
            if grid.mass.iter().all(|&m| m <= self.m0) {
                break;
            }
            denom.iter_mut().for_each(|d| *d = 0.0);
            for s in &stencils {
                grid.each(s, |n, _, g| {
                    denom[n] += (g[0] * g[0] + g[1] * g[1]) * inv_m0 * inv_m0;
                });
            }
            for (n, l) in lambda.iter_mut().enumerate() {
                let c = grid.mass[n] * inv_m0 - 1.0;
                *l = if c > 0.0 && denom[n] > 0.0 {
                    -c / denom[n]
                } else {
                    0.0
                };
            }
            for (s, &i) in stencils.iter().zip(&self.ids) {
                let mut d = [0.0f32; 2];
                grid.each(s, |n, _, g| {
                    d[0] += lambda[n] * g[0] * inv_m0;
                    d[1] += lambda[n] * g[1] * inv_m0;
                });
                frame[4 * i as usize] += d[0];
                frame[4 * i as usize + 1] += d[1];
            }
        }
        self.scratch = Scratch {
            mass: grid.mass,
            lambda,
            denom,
            stencils,
        };
    }

    /// The node masses of the liquid in `frame` over the rest mass (for tests).
    #[cfg(test)]
    pub(super) fn compression(&self, frame: &[f32]) -> Vec<f32> {
        let mut grid = Grid::new(self.h);
        grid.splat(frame, 4, &self.ids, self.h);
        grid.mass.iter().map(|m| m / self.m0).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 30 x 30 lattice of liquid of spacing `s` from (0.3, 0.1), as `[N, 4]` rows.
    fn pool(s: f32) -> Vec<f32> {
        (0..900)
            .flat_map(|i| {
                [
                    0.3 + s * (i / 30) as f32,
                    0.1 + s * (i % 30) as f32,
                    0.0,
                    0.0,
                ]
            })
            .collect()
    }

    #[test]
    fn the_node_mass_of_a_lattice_is_its_particles_per_cell() {
        let p = DensityParams {
            radius: 2.0,
            rest: 1.0,
            iterations: 2,
        };
        let liquid = Liquid::new(&pool(0.01), 4, &[0; 900], 0.01, &p).unwrap();
        // Cell 0.02: 4 particles a cell inside, the B-spline weights summing to 1 a particle.
        assert!((liquid.m0 - 4.0).abs() < 0.2, "{}", liquid.m0);
    }

    #[test]
    fn a_compressed_pool_is_pushed_apart_and_a_resting_one_left_alone() {
        let p = DensityParams {
            radius: 2.0,
            rest: 1.05,
            iterations: 2,
        };
        let material = vec![0u8; 900];
        let rest = pool(0.01);
        let mut liquid = Liquid::new(&rest, 4, &material, 0.01, &p).unwrap();
        let mut same = rest.clone();
        liquid.project(&p, &mut same);
        assert_eq!(same, rest, "the rest frame is below the rest mass");
        // Pressed to 70 % of its height: 1.4x the rest mass inside.
        let mut pressed: Vec<f32> = rest
            .chunks(4)
            .flat_map(|r| [r[0], 0.1 + 0.7 * (r[1] - 0.1), 0.0, 0.0])
            .collect();
        let before = liquid.compression(&pressed);
        let height = |f: &[f32]| f.chunks(4).map(|r| r[1]).fold(0.0, f32::max);
        let h0 = height(&pressed);
        liquid.project(&p, &mut pressed);
        let after = liquid.compression(&pressed);
        let max = |v: &[f32]| v.iter().copied().fold(0.0, f32::max);
        let over = |v: &[f32]| v.iter().map(|&c| (c - 1.0).max(0.0)).sum::<f32>();
        assert!(max(&before) > 1.25, "{}", max(&before));
        // A uniformly pressed block can only expand from its surface: the outer nodes are
        // relieved in a frame, the inner ones on later frames (the moves carry on as
        // velocities); none is pressed much harder.
        let (m0, m1) = (max(&before), max(&after));
        assert!(m1 <= 1.01 * m0, "{m0} -> {m1}");
        // The compression summed over the nodes goes down.
        assert!(
            over(&after) < over(&before),
            "{} -> {}",
            over(&before),
            over(&after)
        );
        let h1 = height(&pressed);
        assert!(h1 > h0 + 0.003, "{h0} -> {h1}");
    }
}
