//! Conservation diagnostics of a [`Solver`] state, summed in `f64`: mass, linear and angular
//! momentum (with the APIC term), kinetic, elastic and gravitational energy, and the centre of
//! mass. Used by the validation tests of `docs/mpm.md` ("Validation checks",
//! `tests/it/sim_validation.rs`).
//!
//! Units follow the solver: rho = 1, so mass is area; momentum is mass x domain units per time
//! unit; energies are mass x (domain units / time unit)^2.

use super::material;
use super::mpm::{Particles, Solver, SolverConfig};
use crate::geometry::centre_of_mass;

/// Sums over all particles, in `f64`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Diagnostics {
    /// Total particle mass.
    pub mass: f64,
    /// Linear momentum `sum m v`.
    pub momentum: [f64; 2],
    /// Angular momentum about the origin, `sum m (x cross v) + m dx^2 / 4 (C10 - C01)`
    /// (the APIC affine term for quadratic B-splines, `D = dx^2 / 4 I`).
    pub angular_momentum: f64,
    /// Kinetic energy `sum m / 2 (|v|^2 + dx^2 / 4 |C|_F^2)` (APIC kinetic energy).
    pub kinetic: f64,
    /// Elastic energy `sum p_vol psi(F)`.
    pub elastic: f64,
    /// Gravitational potential energy `-sum m g . x`.
    pub potential: f64,
    /// Centre of mass ([`centre_of_mass`]: every particle has the same mass, the particle
    /// volume at rho = 1).
    pub center_of_mass: [f64; 2],
}

impl Diagnostics {
    /// Computes the sums for the solver's current particle state.
    pub fn of(solver: &Solver) -> Self {
        Self::of_particles(&solver.config, &solver.particles)
    }

    /// Computes the sums for particles `ps` of a solver with settings `config` (a GPU
    /// solver's state read back, `sim::gpu`).
    pub fn of_particles(config: &SolverConfig, ps: &Particles) -> Self {
        // As `Solver::dx` and `Solver::particle_volume`, in f32.
        let dx32 = 1.0 / config.grid as f32;
        let (dx, h) = (dx32 as f64, 0.5 * dx32);
        let m = (h * h) as f64;
        let d = dx * dx / 4.0;
        let (mu0, lambda0) = config.elasticity.lame();
        let g = config.gravity;
        let mut out = Diagnostics::default();
        for p in 0..ps.len() {
            let x = [ps.x[p][0] as f64, ps.x[p][1] as f64];
            let v = [ps.v[p][0] as f64, ps.v[p][1] as f64];
            let c = ps.c[p].map(|e| e as f64);
            out.mass += m;
            out.momentum[0] += m * v[0];
            out.momentum[1] += m * v[1];
            out.angular_momentum += m * (x[0] * v[1] - x[1] * v[0]) + m * d * (c[2] - c[1]);
            let c2: f64 = c.iter().map(|e| e * e).sum();
            out.kinetic += 0.5 * m * (v[0] * v[0] + v[1] * v[1] + d * c2);
            out.elastic +=
                m * material::energy_density(ps.material[p], &ps.f[p], ps.jp[p], mu0, lambda0);
            out.potential -= m * (g[0] as f64 * x[0] + g[1] as f64 * x[1]);
        }
        out.center_of_mass = centre_of_mass(ps.x.as_flattened(), 2, 0..ps.len() as u32);
        out
    }

    /// Kinetic + elastic + gravitational energy.
    pub fn total_energy(&self) -> f64 {
        self.kinetic + self.elastic + self.potential
    }

    /// Centre-of-mass velocity `momentum / mass`.
    pub fn velocity(&self) -> [f64; 2] {
        [self.momentum[0] / self.mass, self.momentum[1] / self.mass]
    }
}
