//! Geometry of a set of particles that every layer reads: [`centre_of_mass`], the one
//! definition of a body's (or a frame's) centre of mass, and the sum it divides,
//! [`position_sum`]; for the constraint projection (`model::constraints`: contact normals,
//! shape matching, rebound, momentum), `eval` (the centre-of-mass errors of `metrics` and
//! `conservation`) and the solver's diagnostics (`sim::diagnostics`). It depends on nothing
//! else in the crate, so `sim` may read it without reaching up into `model` or `eval`.

use std::borrow::Borrow;

/// The centre of mass of the particles `ids` of `rows` (`[N, stride]` rows whose first two
/// values are x and y, domain units): the mean of their positions, every particle of equal
/// mass (as the surrogates' frames and the MLS-MPM solver have them: docs/mpm.md).
///
/// Summed in f64 in the order `ids` gives, then divided by the count, so the result does not
/// depend on how large the body is beside f32's 24 bits. `[0, 0]` for no particle.
///
/// # Panics
/// An index `i` with `stride * i + 1` outside `rows`.
pub fn centre_of_mass<I>(rows: &[f32], stride: usize, ids: I) -> [f64; 2]
where
    I: IntoIterator,
    I::Item: Borrow<u32>,
{
    let (sum, count) = position_sum(rows, stride, ids);
    let n = count.max(1) as f64;
    [sum[0] / n, sum[1] / n]
}

/// The sum of the positions (f64, in the order `ids` gives) of the particles `ids` of `rows`
/// (`[N, stride]` rows, x and y first) and their count: what [`centre_of_mass`] divides.
/// `eval::metrics` divides the difference of two frames' sums instead, once.
///
/// # Panics
/// As [`centre_of_mass`].
pub fn position_sum<I>(rows: &[f32], stride: usize, ids: I) -> ([f64; 2], usize)
where
    I: IntoIterator,
    I::Item: Borrow<u32>,
{
    let (mut sum, mut count) = ([0.0f64; 2], 0usize);
    for i in ids {
        let i = stride * *i.borrow() as usize;
        sum[0] += f64::from(rows[i]);
        sum[1] += f64::from(rows[i + 1]);
        count += 1;
    }
    (sum, count)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mean of the selected rows' first two values, whatever the stride; none is `[0, 0]`.
    #[test]
    fn centre_of_mass_is_the_mean_of_the_selected_positions() {
        let rows = [0.0f32, 1.0, 9.0, 2.0, 3.0, 9.0, 4.0, 5.0, 9.0];
        assert_eq!(centre_of_mass(&rows, 3, [0u32, 2]), [2.0, 3.0]);
        let ids: &[u32] = &[1];
        assert_eq!(centre_of_mass(&rows, 3, ids), [2.0, 3.0]);
        assert_eq!(
            centre_of_mass(&[0.0, 1.0, 4.0, 5.0], 2, 0..2u32),
            [2.0, 3.0]
        );
        assert_eq!(
            centre_of_mass(&rows, 3, std::iter::empty::<u32>()),
            [0.0; 2]
        );
    }
}
