//! Tests of the liquid's pressure projection (`pressure.rs`): the rest frame left in place, a
//! pressed pool relieved, compressing and expanding velocities, the walls' and solids' nodes.

use super::*;

/// A 30 x 30 lattice of liquid of spacing `s` from (0.3, 0.1) moving at `v(x, y)`, as
/// `[N, 4]` rows.
fn pool(s: f32, v: impl Fn(f32, f32) -> [f32; 2]) -> Vec<f32> {
    (0..900)
        .flat_map(|i| {
            let (x, y) = (0.3 + s * (i / 30) as f32, 0.1 + s * (i % 30) as f32);
            let [vx, vy] = v(x, y);
            [x, y, vx, vy]
        })
        .collect()
}

/// Compressed above 1.1, full from 0.9, no band along the walls.
fn params() -> PressureParams {
    PressureParams {
        rest: 1.1,
        full: 0.9 / 1.1,
        band: 0.0,
        band_rest: 1.0,
        ..PressureParams::DEFAULT
    }
}

fn liquid(rest: &[f32]) -> Pressure {
    Pressure::new(rest, 4, &[0; 900], 0.01, (&params(), None)).unwrap()
}

fn max(v: &[f32]) -> f32 {
    v.iter().copied().fold(0.0, f32::max)
}

#[test]
fn the_rest_frame_has_a_volume_fraction_of_one_and_is_left_in_place() {
    let rest = pool(0.01, |_, _| [0.0, -1.0]);
    let mut pressure = liquid(&rest);
    let phi = pressure.fractions(&rest);
    // Inside the lattice every node holds one cell of liquid (the B-spline sums to 1).
    assert!((max(&phi) - 1.0).abs() < 0.02, "{}", max(&phi));
    let mut same = rest.clone();
    pressure.project(&params(), &mut same, &[0; 900], 0.016, (0.0, 1.0));
    assert_eq!(same, rest, "uncompressed, falling as one: no move");
}

#[test]
fn a_pressed_pool_is_relieved_and_grows() {
    let rest = pool(0.01, |_, _| [0.0; 2]);
    let mut pressure = liquid(&rest);
    let mut pressed: Vec<f32> = rest
        .chunks(4)
        .flat_map(|r| [r[0], 0.1 + 0.7 * (r[1] - 0.1), 0.0, 0.0])
        .collect();
    let before = max(&pressure.fractions(&pressed));
    let height = |f: &[f32]| f.chunks(4).map(|r| r[1]).fold(0.0, f32::max);
    let h0 = height(&pressed);
    let p = PressureParams {
        velocity: false,
        ..params()
    };
    // The floor closes the nodes below y = 0.095: the pool can only rise and widen.
    for _ in 0..10 {
        pressure.project(&p, &mut pressed, &[0; 900], 0.016, (0.095, 1.0));
    }
    let after = max(&pressure.fractions(&pressed));
    assert!(before > 1.35, "{before}");
    assert!(after < 1.25, "{before} -> {after}");
    assert!(
        height(&pressed) > h0 + 0.015,
        "{h0} -> {}",
        height(&pressed)
    );
    let low = pressed.chunks(4).map(|r| r[1]).fold(1.0, f32::min);
    assert!(low > 0.095, "nothing is pushed through the floor: {low}");
}

#[test]
fn a_compressing_velocity_is_removed_and_an_expanding_one_kept() {
    let rest = pool(0.01, |_, _| [0.0; 2]);
    let mut pressure = liquid(&rest);
    let dt = 0.016;
    // Converging on the pool's centre line x = 0.445 at 2 per time unit per unit.
    let mut squeezed = pool(0.01, |x, _| [-2.0 * (x - 0.445), 0.0]);
    let before = squeezed.clone();
    pressure.project(&params(), &mut squeezed, &[0; 900], dt, (0.0, 1.0));
    // The move over dt, as velocity, cancels most of the inward velocity inside.
    let centre = 15 * 30 + 15;
    let left = 5 * 30 + 15;
    let v_left = before[4 * left + 2] + (squeezed[4 * left] - before[4 * left]) / dt;
    assert!(before[4 * left + 2] > 0.1, "{}", before[4 * left + 2]);
    assert!(v_left.abs() < 0.5 * before[4 * left + 2], "{v_left}");
    let moved = |k: usize| (squeezed[4 * k] - before[4 * k]).abs();
    assert!(
        moved(centre) < 0.2 * moved(left),
        "{} {}",
        moved(centre),
        moved(left)
    );
    let mut spread = pool(0.01, |x, _| [x - 0.445, 0.0]);
    let kept = spread.clone();
    pressure.project(&params(), &mut spread, &[0; 900], dt, (0.0, 1.0));
    assert_eq!(spread, kept, "an expanding liquid is free");
}

#[test]
fn the_walls_and_solid_bodies_close_their_nodes() {
    let rest = pool(0.01, |_, _| [0.0; 2]);
    let mut pressure = liquid(&rest);
    let mut s = Scratch::default();
    s.phi = pressure.fractions(&rest);
    s.solid = vec![0.0; s.phi.len()];
    s.solid[pressure.side * 40 + 20] = 5.0;
    pressure.classify(&params(), (0.05, 0.95), &mut s);
    assert_eq!(s.kind[0], WALL, "node (0, 0) is in the wall");
    assert_eq!(s.kind[pressure.side * 40 + 20], CLOSED, "a solid node");
    assert_eq!(s.kind[pressure.side * 22 + 12], FULL, "inside the pool");
    assert_eq!(s.kind[pressure.side * 10 + 30], FREE, "outside it");
    pressure.scratch = s;
}
