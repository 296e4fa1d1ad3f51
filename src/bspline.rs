//! MLS-MPM's quadratic B-spline (Hu et al. 2018, "A Moving Least Squares Material Point
//! Method with Displacement Discontinuity and Two-Way Rigid Body Coupling"; Taichi's mpm99):
//! the one definition of its per-axis weights that every CPU site reads: the solver's P2G and
//! G2P ([`crate::sim::mpm`]), the grid models' particle <-> grid transfers
//! ([`crate::ops::bspline_axis`]) and the liquid's density and pressure parts
//! (`model::constraints`, through [`stencil`]). Each site finds its own base node and
//! fractional offset (clamped or not, `x / dx` or `x * inv_dx`) and asks [`weights`] for the
//! three weights.
//!
//! The GPU transfer kernel (`ops::cuda::net::stencil`, cubecl) evaluates the same spline in its
//! own form, by distance `x` to each node (`0.75 - x^2` within 0.5, `0.5 (1.5 - |x|)^2`
//! within 1.5), since a `#[cube]` function cannot call this one.
//!
//! Uses nothing of the crate, so `sim`, `ops` and `model` depend on it instead of on each other.

/// Quadratic B-spline weights of the three nodes `base`, `base + 1`, `base + 2` of one axis
/// at the fractional offset `f = x / dx - base` (grid units, `f` in `[0.5, 1.5)`):
/// `[0.5 (1.5 - f)^2, 0.75 - (f - 1)^2, 0.5 (f - 0.5)^2]`, summing to 1 (up to rounding).
#[inline(always)]
pub fn weights(f: f32) -> [f32; 3] {
    let a = 1.5 - f;
    let b = f - 1.0;
    let c = f - 0.5;
    [0.5 * a * a, 0.75 - b * b, 0.5 * c * c]
}

/// The 3 x 3 nodes of a position `(x, y)` on nodes of spacing `h` (node `i` at `i h`): the
/// lower node, the fractional offsets `f` per axis and the [`weights`] per axis. Used by the
/// liquid's density and pressure parts (`model::constraints`).
#[inline]
pub fn stencil(x: f32, y: f32, h: f32) -> ([i32; 2], [f32; 2], [[f32; 3]; 2]) {
    let mut base = [0i32; 2];
    let mut frac = [0.0f32; 2];
    let mut w = [[0.0f32; 3]; 2];
    for (a, v) in [x, y].into_iter().enumerate() {
        let g = v / h;
        let b = (g - 0.5).floor();
        base[a] = b as i32;
        frac[a] = g - b;
        w[a] = weights(frac[a]);
    }
    (base, frac, w)
}

#[cfg(test)]
mod tests {
    use super::weights;

    /// Every f32 offset in `[0.25, 1.75]`: [`weights`] is bit for bit what each former copy
    /// wrote (`sim::mpm` and `model::constraints::density`: `(0.5 a) a`; `ops::cpu::transfer`:
    /// `0.5 a.powi(2)`), so moving them here changed no output.
    #[test]
    fn weights_match_every_former_copy_bit_for_bit() {
        let (lo, hi) = (0.25f32.to_bits(), 1.75f32.to_bits());
        for bits in lo..=hi {
            let f = f32::from_bits(bits);
            let got = weights(f).map(f32::to_bits);
            let density = [
                0.5 * (1.5 - f) * (1.5 - f),
                0.75 - (f - 1.0) * (f - 1.0),
                0.5 * (f - 0.5) * (f - 0.5),
            ];
            let transfer = [
                0.5 * (1.5 - f).powi(2),
                0.75 - (f - 1.0).powi(2),
                0.5 * (f - 0.5).powi(2),
            ];
            assert_eq!(got, density.map(f32::to_bits), "f = {f}");
            assert_eq!(got, transfer.map(f32::to_bits), "f = {f}");
        }
    }

    #[test]
    fn weights_sum_to_one() {
        for f in [0.5f32, 0.75, 1.0, 1.25, 1.49] {
            let s: f32 = weights(f).iter().sum();
            assert!((s - 1.0).abs() < 1e-6, "f = {f}: {s}");
        }
    }
}
