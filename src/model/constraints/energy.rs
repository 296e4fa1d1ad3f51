//! The liquid's kinetic energy given back after the projection (`PressureParams::restore`).
//!
//! MPM's liquid is weakly compressible (`MPM.md`: an equation of state on `J`): a falling
//! column that hits the floor compresses, stores the impact's energy and returns it as a
//! sideways surge and a splash. A position projection instead removes the compressing motion
//! and with it the energy (on the 16 unseen scenes of the README, `-small-k4`'s liquid keeps
//! 0.88 / 1.20 of the truth's kinetic energy without the pressure part and 0.80 / 0.86 with
//! it, `multi` / `fluid`). This step gives a share of that energy back to the liquid's motion
//! relative to its mean velocity, the way energy-preserving fluid integrators rescale a
//! velocity field that a projection has damped (Mullen et al. 2009, "Energy-preserving
//! integrators for fluid animation", section 4): the mean velocity, and so the momentum, is
//! kept; the velocities' pattern after the projection is kept; only their spread grows.

/// The largest factor by which one frame scales the liquid's velocities about their mean
/// (a frame whose projection stopped nearly all relative motion is not blown up).
pub const MAX_SCALE: f32 = 2.0;

/// Gives `restore` (0..=1) of the kinetic energy that the projection took from the liquid
/// back to it: `net` (`[N, 4]`, the network's frame before the projection) and `frame`
/// (`[N, 4]`, after it, velocities final) in physical units; `liquid` (`[L]`) the liquid
/// particles' indices. The energy lost is `sum |v'|^2 - sum |v|^2` over the liquid (none:
/// nothing changes); the liquid's velocities about their mean `u` are scaled by `s`
/// (at most [`MAX_SCALE`]) so that `sum |v - u|^2` grows by `restore` times it. Returns `s`.
pub fn restore(restore: f32, net: &[f32], frame: &mut [f32], liquid: &[u32]) -> f32 {
    if restore <= 0.0 || liquid.len() < 2 {
        return 1.0;
    }
    let vel = |f: &[f32], i: u32| {
        let r = 4 * i as usize;
        [f64::from(f[r + 2]), f64::from(f[r + 3])]
    };
    let n = liquid.len() as f64;
    let (mut mean, mut e_net, mut e_now) = ([0.0f64; 2], 0.0f64, 0.0f64);
    for &i in liquid {
        let (a, b) = (vel(net, i), vel(frame, i));
        e_net += a[0] * a[0] + a[1] * a[1];
        e_now += b[0] * b[0] + b[1] * b[1];
        mean = [mean[0] + b[0] / n, mean[1] + b[1] / n];
    }
    let spread = e_now - n * (mean[0] * mean[0] + mean[1] * mean[1]);
    let lost = e_net - e_now;
    if lost <= 0.0 || spread <= f64::EPSILON * e_now.max(1.0) {
        return 1.0;
    }
    let s = ((spread + f64::from(restore.min(1.0)) * lost) / spread).sqrt();
    let s = (s as f32).min(MAX_SCALE);
    let u = [mean[0] as f32, mean[1] as f32];
    for &i in liquid {
        let r = 4 * i as usize;
        frame[r + 2] = u[0] + s * (frame[r + 2] - u[0]);
        frame[r + 3] = u[1] + s * (frame[r + 3] - u[1]);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn energy(f: &[f32]) -> f64 {
        f.chunks(4)
            .map(|r| f64::from(r[2] * r[2] + r[3] * r[3]))
            .sum()
    }

    #[test]
    fn gives_back_the_share_asked_for_and_keeps_the_momentum() {
        // The network's liquid: four particles, two moving apart fast; the projection's
        // result: the same pattern at half the speed, all drifting right at 1.
        let net = [
            0.0, 0.0, -3.0, 0.0, 0.1, 0.0, 5.0, 0.0, 0.2, 0.0, 1.0, 2.0, 0.3, 0.0, 1.0, -2.0,
        ];
        let mut frame = [
            0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 2.0, 0.0, 0.2, 0.0, 1.0, 1.0, 0.3, 0.0, 1.0, -1.0,
        ];
        let all = [0, 1, 2, 3];
        let lost = energy(&net) - energy(&frame);
        let before = energy(&frame);
        let s = restore(0.1, &net, &mut frame, &all);
        assert!(s > 1.0 && s < MAX_SCALE, "{s}");
        assert!(
            (energy(&frame) - (before + 0.1 * lost)).abs() < 1e-4,
            "{}",
            energy(&frame)
        );
        let momentum: f32 = frame.chunks(4).map(|r| r[2]).sum();
        assert!((momentum - 4.0).abs() < 1e-5, "{momentum}");
        assert!(frame.chunks(4).map(|r| r[3]).sum::<f32>().abs() < 1e-5);
        // The positions are the projection's.
        assert_eq!(frame[4], 0.1);
    }

    #[test]
    fn leaves_a_liquid_that_lost_nothing_or_moves_as_one() {
        let net = [0.0, 0.0, 1.0, 0.0, 0.1, 0.0, 1.0, 0.0];
        let mut same = net;
        assert_eq!(restore(1.0, &net, &mut same, &[0, 1]), 1.0);
        assert_eq!(same, net);
        // Slowed down as a whole: no relative motion to give the energy to.
        let mut slowed = [0.0, 0.0, 0.5, 0.0, 0.1, 0.0, 0.5, 0.0];
        assert_eq!(restore(1.0, &net, &mut slowed, &[0, 1]), 1.0);
        assert_eq!(slowed[2], 0.5);
        // Off: nothing.
        let mut frame = [0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.2, 0.0];
        assert_eq!(
            restore(
                0.0,
                &[0.0, 0.0, -3.0, 0.0, 0.1, 0.0, 3.0, 0.0],
                &mut frame,
                &[0, 1]
            ),
            1.0
        );
    }

    #[test]
    fn a_stopped_spread_is_scaled_at_most_max_scale() {
        let net = [0.0, 0.0, -10.0, 0.0, 0.1, 0.0, 10.0, 0.0];
        let mut frame = [0.0, 0.0, -0.1, 0.0, 0.1, 0.0, 0.1, 0.0];
        assert_eq!(restore(1.0, &net, &mut frame, &[0, 1]), MAX_SCALE);
        assert!((frame[6] - 0.2).abs() < 1e-6);
    }
}
