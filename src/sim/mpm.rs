//! The MLS-MPM solver: particle state, the background grid, and one substep
//! (P2G, grid update, G2P) with APIC transfers and quadratic B-spline weights.
//!
//! Units: the domain is the unit square, positions in domain units, velocities in domain
//! units per time unit, `dt` in time units, density 1 (so mass = area). State is `f32`;
//! the grid-mass diagnostic is accumulated in `f64`.
//!
//! Source: Hu et al., "A Moving Least Squares Material Point Method with Displacement
//! Discontinuity and Two-Way Rigid Body Coupling" (SIGGRAPH 2018), as laid out in Taichi's
//! public mpm99 example (taichi-dev/taichi, python/taichi/examples/simulation/mpm99.py):
//! P2G affine term `A = -dt p_vol 4 inv_dx^2 tau + p_mass C`, `F <- (I + dt C) F`, walls
//! that zero the outward velocity on grid nodes with index < 3 or > n - 3.

use super::linalg::{self, Mat2};
use super::material::{self, Elasticity};
use super::SimError;
use crate::bspline;

/// Numerical settings of one simulation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolverConfig {
    /// Grid nodes per side `n`; `dx = 1 / n`.
    pub grid: usize,
    /// Substep length in time units.
    pub dt: f32,
    /// Gravity in domain units per time unit squared, e.g. `[0, -9.8]`.
    pub gravity: [f32; 2],
    /// Material constants (E0, nu).
    pub elasticity: Elasticity,
    /// Largest allowed CFL number `max |v| dt / dx`; a substep that would exceed it is split
    /// into equal parts (see [`Solver::substep`]). `f32::INFINITY` disables splitting.
    pub max_cfl: f32,
}

/// Largest velocity-gradient increment `dt |C|_F` per substep. Beyond it the pressure of a
/// fast-compressed liquid lags its strain and overshoots (scenes blew up without it).
pub const MAX_STRAIN_STEP: f32 = 0.25;

/// Default [`SolverConfig::max_cfl`]: a particle moves at most a quarter cell per substep
/// (speeds up to 4.9 at dt = 8e-4 on the 64^2 grid). The appendix's eq. 3 allows 0.9, but at
/// 0.5 ropes tore (neighbour gaps > dx) and one rope+liquid scene ran away after frame 170.
pub const DEFAULT_MAX_CFL: f32 = 0.25;

/// Particle state, structure of arrays; all vectors have length N.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Particles {
    /// Positions `[x, y]`, domain units.
    pub x: Vec<[f32; 2]>,
    /// Velocities `[vx, vy]`, domain units per time unit.
    pub v: Vec<[f32; 2]>,
    /// APIC affine velocity matrix C (row-major), per time unit.
    pub c: Vec<Mat2>,
    /// Deformation gradient F (row-major), dimensionless.
    pub f: Vec<Mat2>,
    /// Plastic volume ratio Jp (snow), 1 for the other materials.
    pub jp: Vec<f32>,
    /// Material id (0 liquid, 1 jelly, 2 snow, 3 rope).
    pub material: Vec<u8>,
}

impl Particles {
    /// Number of particles N.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// True when there are no particles.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Appends an undeformed particle at rest state `F = I`, `C = 0`, `Jp = 1`.
    pub fn push(&mut self, x: [f32; 2], v: [f32; 2], material: u8) {
        self.x.push(x);
        self.v.push(v);
        self.c.push([0.0; 4]);
        self.f.push(linalg::IDENTITY);
        self.jp.push(1.0);
        self.material.push(material);
    }
}

/// A 2D MLS-MPM simulation: particles plus the grid they exchange momentum through.
#[derive(Clone, Debug)]
pub struct Solver {
    /// Numerical settings.
    pub config: SolverConfig,
    /// Particle state.
    pub particles: Particles,
    /// Grid nodes `[momentum x | velocity x, momentum y | velocity y, mass, 0]`, index
    /// `i * n + j` (16 bytes, so a node is one SIMD lane group).
    grid: Vec<[f32; 4]>,
    /// Each particle's stencil, computed in P2G and reused by G2P (same positions).
    stencils: Vec<Stencil>,
    /// Inclusive node box `[i0, i1, j0, j1]` touched by the last P2G (cleared before the next).
    active: [usize; 4],
    /// Total grid mass after the last P2G, in f64 (validation check 1).
    pub grid_mass: f64,
    /// Substeps taken since the start (each of length `config.dt`).
    pub substeps_done: u64,
    /// Extra partial substeps taken because the CFL limit split a substep.
    pub splits: u64,
    /// `max |v|`, `max |C|_F` and `max k phi` (stiffness times own-mass share) over
    /// particles after the last G2P.
    last_max: [f32; 3],
    /// Particle-substeps that ended outside the interpolation band `[0.5 dx, 1 - 1.5 dx)`
    /// (there the stencil's base node is clamped and the weights are wrong; the sanity
    /// checks report it). Zero in a healthy run.
    pub escaped: u64,
}

impl Solver {
    /// Creates a solver. Errors as [`Solver::check`].
    pub fn new(config: SolverConfig, particles: Particles) -> Result<Self, SimError> {
        Self::check(&config, &particles)?;
        let n = config.grid;
        Ok(Self {
            config,
            particles,
            grid: vec![[0.0; 4]; n * n],
            stencils: Vec::new(),
            active: [0, n - 1, 0, n - 1],
            grid_mass: 0.0,
            substeps_done: 0,
            splits: 0,
            last_max: [0.0; 3],
            escaped: 0,
        })
    }

    /// Checks that `particles` can start a solver with `config`: a grid of 8 to 4,096
    /// nodes, a positive finite `dt`, every particle inside `[dx, 1 - 2 dx]` and of a known
    /// material (also the GPU solver's check, `sim::gpu`).
    pub fn check(config: &SolverConfig, particles: &Particles) -> Result<(), SimError> {
        let n = config.grid;
        if !(8..=4096).contains(&n) {
            return Err(SimError::Invalid(format!("grid {n} outside 8..=4096")));
        }
        if !(config.dt.is_finite() && config.dt > 0.0) {
            return Err(SimError::Invalid(format!("dt {} must be > 0", config.dt)));
        }
        let dx = 1.0 / n as f32;
        for (p, (x, &m)) in particles.x.iter().zip(&particles.material).enumerate() {
            let inside = |c: f32| c >= dx && c <= 1.0 - 2.0 * dx;
            if !(inside(x[0]) && inside(x[1])) {
                return Err(SimError::Invalid(format!(
                    "particle {p} at ({}, {}) outside [dx, 1 - 2 dx]",
                    x[0], x[1]
                )));
            }
            if super::Material::from_id(m).is_none() {
                return Err(SimError::Invalid(format!("particle {p}: material {m}")));
            }
        }
        Ok(())
    }

    /// Grid spacing `dx = 1 / n` in domain units.
    pub fn dx(&self) -> f32 {
        1.0 / self.config.grid as f32
    }

    /// Particle reference volume `(dx / 2)^2`, equal to its mass (rho = 1).
    pub fn particle_volume(&self) -> f32 {
        let h = 0.5 * self.dx();
        h * h
    }

    /// Simulated time in time units.
    pub fn time(&self) -> f64 {
        self.substeps_done as f64 * self.config.dt as f64
    }

    /// Advances `count` substeps.
    pub fn advance(&mut self, count: u32) {
        for _ in 0..count {
            self.substep();
        }
    }

    /// Advances one substep of `config.dt`: clear the grid, P2G, grid update, G2P (which
    /// also updates and projects F, as in Hu et al. 2018, section 5).
    ///
    /// The substep is taken as `k` equal parts of `dt / k` when the last G2P left
    /// - the CFL number `max |v| dt / dx` above `config.max_cfl` (the paper's appendix A,
    ///   eq. 3), or the strain increment `dt max |C|_F` above [`MAX_STRAIN_STEP`], or
    /// - the elastic stability bound violated: a particle of stiffness `k` (see
    ///   [`material::kirchhoff_stress`]) holding a share `phi` of its nodes' mass feeds its
    ///   stress back through P2G/G2P like an oscillator of `(omega dt)^2 = 8 k phi dt^2 / dx^2`,
    ///   stable below 4. A liquid droplet alone on its nodes (phi = 1) with `J > 1.4` breaks
    ///   it at the paper's dt = 8e-4 on the 64^2 grid and blows up; bulk material never does.
    ///
    /// Frames stay exactly `substeps * dt` apart and the run stays deterministic.
    pub fn substep(&mut self) {
        let dt = self.config.dt;
        let dx = self.dx();
        let [vmax, cmax, kphi] = self.last_max;
        let cfl = (vmax * dt / dx / self.config.max_cfl).max(cmax * dt / MAX_STRAIN_STEP);
        // Elastic stability: an oscillator of gain 8 k phi dt^2 / dx^2 (a particle alone on
        // its nodes has phi = 1) is stable below 4; keep it under 4 * 0.7.
        let stiff = (2.0 * kphi * dt * dt / (dx * dx) / 0.7).sqrt();
        let need = cfl.max(stiff);
        let parts = if need > 1.0 {
            (need.ceil() as u32).min(64)
        } else {
            1
        };
        let h = dt / parts as f32;
        for _ in 0..parts {
            self.clear_grid();
            self.p2g(h);
            self.update_grid(h);
            self.g2p(h);
        }
        self.splits += u64::from(parts - 1);
        self.substeps_done += 1;
    }

    #[inline(never)]
    fn clear_grid(&mut self) {
        let n = self.config.grid;
        let [i0, i1, j0, j1] = self.active;
        for i in i0..=i1 {
            self.grid[i * n + j0..=i * n + j1].fill([0.0; 4]);
        }
    }

    /// P2G: scatter mass and APIC momentum `m v + A (x_i - x_p)` with
    /// `A = -dt p_vol 4 inv_dx^2 tau + m C`, and cache each particle's stencil for G2P.
    #[inline(never)]
    fn p2g(&mut self, dt: f32) {
        let n = self.config.grid;
        let inv_dx = n as f32;
        let dx = 1.0 / inv_dx;
        let p_mass = self.particle_volume();
        let (mu0, lambda0) = self.config.elasticity.lame();
        let stress_scale = -dt * p_mass * 4.0 * inv_dx * inv_dx;
        let mut bbox = [usize::MAX, 0, usize::MAX, 0];
        let ps = &self.particles;
        self.stencils.clear();
        for p in 0..ps.x.len() {
            let mut st = Stencil::new(ps.x[p], inv_dx, n);
            let c = ps.c[p];
            let (tau, k) =
                material::kirchhoff_stress(ps.material[p], &ps.f[p], ps.jp[p], mu0, lambda0);
            st.stiffness = k;
            // A dx, since x_i - x_p = ((i, j) - fx) dx.
            let a = [
                (stress_scale * tau[0] + p_mass * c[0]) * dx,
                (stress_scale * tau[1] + p_mass * c[1]) * dx,
                (stress_scale * tau[2] + p_mass * c[2]) * dx,
                (stress_scale * tau[3] + p_mass * c[3]) * dx,
            ];
            let v = ps.v[p];
            // Momentum at node offset (i, j) is q + i a_col0 + j a_col1.
            let q = [
                p_mass * v[0] - a[0] * st.fx[0] - a[1] * st.fx[1],
                p_mass * v[1] - a[2] * st.fx[0] - a[3] * st.fx[1],
            ];
            for i in 0..3 {
                let row = st.row(i, n);
                let cells: &mut [[f32; 4]; 3] = (&mut self.grid[row..row + 3])
                    .try_into()
                    .expect("stencil rows lie inside the grid");
                let fi = i as f32;
                let r = [q[0] + a[0] * fi, q[1] + a[2] * fi, p_mass, 0.0];
                let s = [a[1], a[3], 0.0, 0.0];
                for (j, node) in cells.iter_mut().enumerate() {
                    let w = st.wx[i] * st.wy[j];
                    let fj = j as f32;
                    for k in 0..4 {
                        node[k] += w * (r[k] + s[k] * fj);
                    }
                }
            }
            bbox = [
                bbox[0].min(st.bi),
                bbox[1].max(st.bi + 2),
                bbox[2].min(st.bj),
                bbox[3].max(st.bj + 2),
            ];
            self.stencils.push(st);
        }
        if bbox[0] == usize::MAX {
            bbox = [0, 0, 0, 0];
        }
        self.active = bbox;
    }

    /// Grid update: momentum to velocity, gravity, and the walls (outward component zeroed
    /// on nodes with index < 3 or > n - 3).
    #[inline(never)]
    fn update_grid(&mut self, dt: f32) {
        let n = self.config.grid;
        let [gx, gy] = self.config.gravity;
        let [i0, i1, j0, j1] = self.active;
        let mut mass = 0.0f64;
        for i in i0..=i1 {
            let row = &mut self.grid[i * n + j0..=i * n + j1];
            for (jj, node) in row.iter_mut().enumerate() {
                let m = node[2];
                if m <= 0.0 {
                    continue;
                }
                mass += m as f64;
                let j = j0 + jj;
                let inv = 1.0 / m;
                node[3] = inv;
                let mut vx = node[0] * inv + dt * gx;
                let mut vy = node[1] * inv + dt * gy;
                if (i < 3 && vx < 0.0) || (i > n - 3 && vx > 0.0) {
                    vx = 0.0;
                }
                if (j < 3 && vy < 0.0) || (j > n - 3 && vy > 0.0) {
                    vy = 0.0;
                }
                node[0] = vx;
                node[1] = vy;
            }
        }
        self.grid_mass = mass;
    }

    /// G2P: gather `v = sum w v_i` and `C = 4 inv_dx^2 sum w v_i (x_i - x_p)^T`, advect,
    /// then `F <- (I + dt C) F` and the plastic projection.
    #[inline(never)]
    fn g2p(&mut self, dt: f32) {
        let p_mass = self.particle_volume();
        let n = self.config.grid;
        let inv_dx = n as f32;
        let lo = 0.5 / inv_dx;
        let hi = 1.0 - 1.5 / inv_dx;
        let grid = &self.grid;
        let ps = &mut self.particles;
        let mut escaped = 0u64;
        let (mut vmax2, mut cmax2, mut kphi) = (0.0f32, 0.0f32, 0.0f32);
        for (p, st) in self.stencils.iter().enumerate() {
            // Per row i: s = sum_j w_j v_ij, t = sum_j j w_j v_ij.
            let mut v = [0.0f32; 2];
            let mut bi = [0.0f32; 2];
            let mut bj = [0.0f32; 2];
            // phi = sum_i w_i (w_i m / m_i): the particle's own share of its nodes' mass.
            let mut phi = 0.0f32;
            for i in 0..3 {
                let row = st.row(i, n);
                let cells: &[[f32; 4]; 3] = (&grid[row..row + 3])
                    .try_into()
                    .expect("stencil rows lie inside the grid");
                let mut s = [0.0f32; 2];
                let mut t = [0.0f32; 2];
                let w2 = st.wy[0] * st.wy[0] * cells[0][3]
                    + st.wy[1] * st.wy[1] * cells[1][3]
                    + st.wy[2] * st.wy[2] * cells[2][3];
                phi += st.wx[i] * st.wx[i] * w2;
                for k in 0..2 {
                    s[k] = st.wy[0] * cells[0][k] + st.wy[1] * cells[1][k] + st.wy[2] * cells[2][k];
                    t[k] = st.wy[1] * cells[1][k] + 2.0 * st.wy[2] * cells[2][k];
                    v[k] += st.wx[i] * s[k];
                    bi[k] += st.wx[i] * i as f32 * s[k];
                    bj[k] += st.wx[i] * t[k];
                }
            }
            let k4 = 4.0 * inv_dx;
            let c = [
                k4 * (bi[0] - v[0] * st.fx[0]),
                k4 * (bj[0] - v[0] * st.fx[1]),
                k4 * (bi[1] - v[1] * st.fx[0]),
                k4 * (bj[1] - v[1] * st.fx[1]),
            ];
            vmax2 = vmax2.max(v[0] * v[0] + v[1] * v[1]);
            cmax2 = cmax2.max(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + c[3] * c[3]);
            kphi = kphi.max(st.stiffness * phi * p_mass);
            ps.c[p] = c;
            ps.v[p] = v;
            let x = ps.x[p];
            let nx = [x[0] + dt * v[0], x[1] + dt * v[1]];
            escaped += u64::from(!(nx[0] >= lo && nx[0] < hi && nx[1] >= lo && nx[1] < hi));
            ps.x[p] = nx;
            let mut f = update_deformation(&ps.f[p], &c, dt);
            material::project(ps.material[p], &mut f, &mut ps.jp[p]);
            ps.f[p] = f;
        }
        self.escaped += escaped;
        self.last_max = [vmax2.sqrt(), cmax2.sqrt(), kphi];
    }
}

/// `F <- (I + dt C) F` (docs/mpm.md, "Materials"). When `dt |C|_F > 0.25` a single factor can invert F
/// (`det(I + dt C) <= 0`, seen when a fast particle meets a wall), so `F' = C F` is then
/// integrated in `m` equal steps, `F <- (I + dt/m C)^m F`, which tends to the exact
/// `exp(dt C) F` and keeps `det F > 0`. Rare in the generated scenes.
#[inline(always)]
fn update_deformation(f: &Mat2, c: &Mat2, dt: f32) -> Mat2 {
    let norm2 = dt * dt * (c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + c[3] * c[3]);
    let steps = if norm2 > 0.0625 {
        ((norm2.sqrt() / 0.25).ceil() as u32).min(1024)
    } else {
        1
    };
    let h = dt / steps as f32;
    let step = [1.0 + h * c[0], h * c[1], h * c[2], 1.0 + h * c[3]];
    let mut out = *f;
    for _ in 0..steps {
        out = linalg::mul(&step, &out);
    }
    out
}

/// A particle's 3 x 3 interpolation stencil: base node `(bi, bj)`, fractional offset
/// `fx = x / dx - base` in `[0.5, 1.5)`, and the quadratic B-spline weights per axis
/// ([`crate::bspline::weights`]).
#[derive(Clone, Copy, Debug, Default)]
struct Stencil {
    bi: usize,
    bj: usize,
    fx: [f32; 2],
    wx: [f32; 3],
    wy: [f32; 3],
    /// Stiffness k of the particle's stress at P2G (for the substep stability bound).
    stiffness: f32,
}

impl Stencil {
    #[inline(always)]
    fn new(x: [f32; 2], inv_dx: f32, n: usize) -> Self {
        let hi = (n - 3) as i32;
        let bi = ((x[0] * inv_dx - 0.5) as i32).clamp(0, hi) as usize;
        let bj = ((x[1] * inv_dx - 0.5) as i32).clamp(0, hi) as usize;
        let fx = [x[0] * inv_dx - bi as f32, x[1] * inv_dx - bj as f32];
        Self {
            bi,
            bj,
            fx,
            wx: bspline::weights(fx[0]),
            wy: bspline::weights(fx[1]),
            stiffness: 0.0,
        }
    }

    /// Grid index of node `(bi + i, bj)`.
    #[inline(always)]
    fn row(&self, i: usize, n: usize) -> usize {
        (self.bi + i) * n + self.bj
    }
}
