//! The constitutive update of each material of the ground truth ([`Material`], whose ids, names
//! and colours live in [`crate::material`]): given a particle's updated deformation gradient
//! `F` (and plastic volume ratio `Jp`), apply plasticity and return the Kirchhoff stress `tau`
//! (domain units: rho = 1, so stress is energy per area).
//!
//! Models follow Taichi's mpm99 example and `docs/mpm.md` ("Materials"): fixed-corotated
//! elasticity `tau = 2 mu (F - R) F^T + lambda J (J - 1) I` (R = U V^T, the polar rotation),
//! liquid with zero shear modulus and `F` reset to a matrix of determinant J, snow with
//! singular values clamped to `[1 - 2.5e-2, 1 + 4.5e-3]` and hardening `clamp(exp(10 (1 - Jp)),
//! 0.1, 5)`.

use super::linalg::{self, Mat2};
pub use crate::material::Material;
use serde::{Deserialize, Serialize};

// `project`, `hardening` and `kirchhoff_stress` below match on the four ids; a new material
// needs its arms there first (docs/mpm.md, "Adding a material").
const _: () = assert!(
    crate::material::COUNT == 4,
    "give the new material its constitutive update here"
);

/// Lamé parameters and snow plasticity limits, shared by every material of a scene.
///
/// Defaults: `E0 = 400`, `nu = 0.2` (mu0 = 166.7, lambda0 = 111.1), as in mpm99 and docs/mpm.md ("Global settings").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Elasticity {
    /// Young's modulus E0 before hardening.
    pub youngs_modulus: f32,
    /// Poisson's ratio.
    pub poisson_ratio: f32,
}

impl Default for Elasticity {
    fn default() -> Self {
        Self {
            youngs_modulus: 400.0,
            poisson_ratio: 0.2,
        }
    }
}

impl Elasticity {
    /// `(mu0, lambda0)` from E and nu.
    pub fn lame(&self) -> (f32, f32) {
        let e = self.youngs_modulus;
        let nu = self.poisson_ratio;
        (
            e / (2.0 * (1.0 + nu)),
            e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
        )
    }
}

/// The smallest volume ratio a liquid particle keeps. Explicit MPM can compress a liquid
/// particle through zero volume in one substep when a stiff body presses it against a wall
/// (`multi/liquid+snow/007` with `--seed 2` reached `J = 0` at frame 43-61), after which its
/// stress and volume are meaningless. The liquid's `J` is therefore floored after the
/// update, a volume floor in the plastic projection (the liquid already discards all of F
/// but its determinant). 0.1 is far below what a resolved scene reaches (the pressure
/// continues monotonically below 0.5, see [`liquid_pressure`]), so only the degenerate
/// substep is changed.
pub const LIQUID_J_MIN: f32 = 0.1;

/// Snow's singular-value clamp (docs/mpm.md, "Materials"): compression and stretch limits.
const SNOW_MIN: f32 = 1.0 - 2.5e-2;
const SNOW_MAX: f32 = 1.0 + 4.5e-3;
/// Snow's singular-value clamp `(SNOW_MIN, SNOW_MAX)`, for the GPU solver's kernels.
pub const SNOW_LIMITS: (f32, f32) = (SNOW_MIN, SNOW_MAX);

/// Plastic projection after `F <- (I + dt C) F` (done in G2P, as in Hu et al. 2018):
/// liquid resets `F` to `diag(J, 1)` (mpm99's `sqrt(J) I` has the same determinant, the only
/// part of F its stress uses); snow clamps its singular values to
/// `[1 - 2.5e-2, 1 + 4.5e-3]` and moves the clamped-off volume change into `jp`.
/// Jelly and rope are purely elastic and left unchanged.
#[inline(always)]
pub fn project(material: u8, f: &mut Mat2, jp: &mut f32) {
    match material {
        0 => {
            // mpm99 resets F to sqrt(J) I; only J = det F enters the liquid's stress, so
            // diag(J, 1) is equivalent and needs no square root.
            // J clamped away from 0 (see `LIQUID_J_MIN`).
            *f = [linalg::det(f).max(LIQUID_J_MIN), 0.0, 0.0, 1.0];
        }
        2 => {
            let (u, sig, v) = linalg::svd(f);
            let s0 = sig[0].clamp(SNOW_MIN, SNOW_MAX);
            let s1 = sig[1].clamp(SNOW_MIN, SNOW_MAX);
            *jp *= (sig[0] / s0) * (sig[1] / s1);
            let us = [u[0] * s0, u[1] * s1, u[2] * s0, u[3] * s1];
            *f = linalg::mul_bt(&us, &v);
        }
        _ => {}
    }
}

/// Hardening factor h scaling mu0 and lambda0 (docs/mpm.md, "Materials"): liquid 1, jelly 0.3,
/// snow `clamp(exp(10 (1 - Jp)), 0.1, 5)`, rope 0.5.
#[inline(always)]
pub fn hardening(material: u8, jp: f32) -> f32 {
    match material {
        0 => 1.0,
        1 => 0.3,
        2 => (10.0 * (1.0 - jp)).exp().clamp(0.1, 5.0),
        _ => 0.5,
    }
}

/// Kirchhoff stress of a projected state, and the stiffness `k` that bounds the stable
/// substep (see `Solver::substep`).
///
/// Liquid: `tau = p(J) I` with [`liquid_pressure`] (mu = 0), `k = dp/dJ`, at least lambda0.
/// Solids: fixed-corotated `2 mu (F - R) F^T + lambda J (J - 1) I` with `R = U V^T` the polar
/// rotation (after projection snow's singular values are positive, so the polar rotation
/// equals the signed-SVD `U V^T`), `(mu, lambda) = h (mu0, lambda0)`, `k = lambda + 2 mu`;
/// snow reports `k = 0`: its elastic strain is capped by the plastic clamp, so its stress
/// stays bounded and cannot run away (hardened snow would otherwise split most substeps).
#[inline(always)]
pub fn kirchhoff_stress(material: u8, f: &Mat2, jp: f32, mu0: f32, lambda0: f32) -> (Mat2, f32) {
    let j = linalg::det(f);
    if material == 0 {
        let p = liquid_pressure(j, lambda0);
        return ([p, 0.0, 0.0, p], lambda0 * (2.0 * j - 1.0).max(1.0));
    }
    let h = hardening(material, jp);
    let (mu, la) = (mu0 * h, lambda0 * h);
    let k = if material == 2 { 0.0 } else { la + 2.0 * mu };
    (corotated(f, &linalg::polar_rotation(f), j, mu, la), k)
}

/// Liquid Kirchhoff pressure term: `lambda J (J - 1)` (mpm99, docs/mpm.md "Materials") for `J >= 0.5`.
///
/// Below `J = 0.5` that expression loses stiffness (its magnitude falls back to 0 at
/// `J = 0`), so a particle squeezed past half its volume collapses to `J = 0`: seen in
/// `multi` scenes where snow (hardened up to 5x) presses liquid into the floor. There we
/// continue it monotonically and C1: `-lambda / 4 - lambda (0.5 - J)^2`. Only that
/// unphysical regime (over 50 % compression) differs from mpm99.
#[inline(always)]
pub fn liquid_pressure(j: f32, lambda0: f32) -> f32 {
    if j >= 0.5 {
        lambda0 * j * (j - 1.0)
    } else {
        let d = 0.5 - j;
        -lambda0 * (0.25 + d * d)
    }
}

/// `2 mu (F - R) F^T + lambda J (J - 1) I`.
#[inline(always)]
fn corotated(f: &Mat2, r: &Mat2, j: f32, mu: f32, la: f32) -> Mat2 {
    let d = [f[0] - r[0], f[1] - r[1], f[2] - r[2], f[3] - r[3]];
    let dft = linalg::mul_bt(&d, f);
    let p = la * j * (j - 1.0);
    [
        2.0 * mu * dft[0] + p,
        2.0 * mu * dft[1],
        2.0 * mu * dft[2],
        2.0 * mu * dft[3] + p,
    ]
}

/// Elastic energy density `psi(F)` per unit reference volume for energy diagnostics:
/// `mu ||F - R||^2 + lambda / 2 (J - 1)^2` (fixed-corotated; liquid has mu = 0).
pub fn energy_density(material: u8, f: &Mat2, jp: f32, mu0: f32, lambda0: f32) -> f64 {
    let h = hardening(material, jp);
    let mu = if material == 0 { 0.0 } else { mu0 * h };
    let la = lambda0 * h;
    let r = linalg::polar_rotation(f);
    let dev: f32 = f.iter().zip(&r).map(|(a, b)| (a - b) * (a - b)).sum();
    let j = linalg::det(f) - 1.0;
    (mu * dev) as f64 + 0.5 * (la as f64) * (j as f64) * (j as f64)
}
