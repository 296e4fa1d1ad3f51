//! Rebound of elastic bodies: a jelly body that hits a wall or another jelly body leaves it at
//! between `restitution` and 1 times the speed it came in with, as the solver's jelly does
//! (0.61-0.87 of their closing speed for two disks, 0.83-0.95 off a floor). A network trained on
//! frames damps the rebound (the contact lasts a few frames, each of them predicted a little
//! slow); the projection keeps a memory of each contact instead, the one thing a frame alone
//! cannot say: the speed the contact began with.
//!
//! A contact is an event with a lifetime. It begins on the first frame a body comes within
//! [`ReboundParams::clearance`] of a wall (its extreme particle) or within
//! [`ReboundParams::reach`] of another body (its nearest particles): the zones where
//! [`super::momentum`] does not act. The approach speed is read from the frame before, the
//! last free one; below [`ReboundParams::resting`] the contact is resting and never bounces.
//! A contact already under way in the frame before (a rollout's first frame) has no known
//! approach speed and is left to the network.
//! While the contact lasts, once the body is [`ReboundParams::release`] from the wall or the
//! other body (the solver's contact forces act through grid nodes both touch, up to about
//! that far, so by then its rebound is done) and the network moves it away (positive
//! separating speed), it leaves no slower than `restitution` times the approach speed and no
//! faster than the approach speed itself (a passive body gains no energy in a bounce; both
//! less the gravity of the frames since it began to leave, for a wall across gravity): the
//! body is translated along the normal by the speed it lacks or has too much times `dt`, a
//! pair by equal and opposite impulses (momentum kept). The contact ends when the body
//! leaves the zone; a body separating in that frame gets its exit speed then too, since a
//! fast one can pass from under `release` to past the zone in one frame (two disks parting
//! at 2.5 move 0.04 a frame, twice the 0.02 between release and reach). Velocity-level
//! restitution with per-contact state is what rigid-body PBD solvers do (Müller et al. 2020,
//! "Detailed Rigid Body Simulation with Extended Position Based Dynamics", section 3.6:
//! the pre-contact normal velocity kept to set `v_n' = -e v_n`).

use std::collections::BTreeMap;

mod table;

use super::index::BodyIndex;
use super::ReboundParams;
use crate::geometry::centre_of_mass;
use crate::neighbours::Bins;

/// The key of a pair's contact is the other body's index; a wall's is `WALL + side` (side 0
/// and 1: the walls at x = 0 and 1; 2 and 3: y = 0 and 1).
const WALL: u32 = u32::MAX - 4;

/// A contact in progress.
#[derive(Clone, Copy, Debug)]
struct Event {
    /// Closing speed when it began (domain units per time unit; 0 for a resting contact);
    /// None where the body was already in contact in the frame before it began (the first
    /// frame a model predicts), so that no free frame gave it.
    speed_in: Option<f32>,
    /// Frames in which the body was leaving so far.
    leaving: u32,
}

impl Event {
    /// The speed to add along the normal to a body leaving this contact at separating speed
    /// `u` (module doc): 0 without a known approach speed or while not separating. `fall`:
    /// gravity's speed change per frame along the normal (a wall across gravity; 0 for a
    /// pair), counted over the frames the body has been leaving.
    fn exit(&mut self, p: &ReboundParams, u: f32, fall: f32) -> f32 {
        let Some(speed_in) = self.speed_in.filter(|&v| v > 0.0) else {
            return 0.0;
        };
        if u <= 0.0 {
            return 0.0;
        }
        let fall = fall * self.leaving as f32;
        self.leaving += 1;
        let (low, high) = (p.restitution * speed_in + fall, speed_in + fall);
        u.clamp(low, high.max(low)) - u
    }
}

/// One scene's elastic bodies and their contacts in progress.
#[derive(Clone, Debug)]
pub(super) struct Rebound {
    /// The jelly bodies' particles.
    bodies: BodyIndex,
    /// Contacts in progress, by `(body, other body or WALL + side)`.
    events: BTreeMap<(u32, u32), Event>,
    /// The contacts a device call left, read when next used (`table.rs`).
    pending: Option<table::Pending>,
}

/// A body's means in the frame before and the predicted one.
#[derive(Clone, Copy, Debug, Default)]
struct Stats {
    /// Centre of mass before.
    c_prev: [f32; 2],
    /// Mean velocity before.
    v_prev: [f32; 2],
    /// Centre of mass now.
    c: [f32; 2],
    /// Mean velocity the frame ends with (its velocity plus the moves so far over dt).
    v: [f32; 2],
    /// Lowest and highest coordinate now, per axis.
    lo: [f32; 2],
    hi: [f32; 2],
    /// Lowest and highest coordinate before, per axis.
    lo_prev: [f32; 2],
    hi_prev: [f32; 2],
}

impl Rebound {
    /// The contact data of `bodies` (each a list of particle indices) in a scene of `n`
    /// particles; None without a body.
    pub(super) fn new(bodies: &[Vec<u32>], n: usize) -> Option<Self> {
        if bodies.is_empty() {
            return None;
        }
        Some(Self {
            bodies: BodyIndex::new(bodies.iter().map(Vec::as_slice), n),
            events: BTreeMap::new(),
            pending: None,
        })
    }

    /// Applies the rebound (module doc) to `frame` (`[N, 4]`), predicted from `prev`
    /// (`[N, 4]`, `dt` before); `before` (`[N, 4]`) is the network's frame before this
    /// projection. Moves positions only: the caller gives every move its velocity, `dx / dt`.
    pub(super) fn apply(
        &mut self,
        p: &ReboundParams,
        (prev, before, frame): (&[f32], &[f32], &mut [f32]),
        dt: f32,
    ) {
        self.settle();
        if dt <= 0.0 || prev.len() != frame.len() || before.len() != frame.len() {
            return;
        }
        let stats: Vec<Stats> = (0..self.bodies.len())
            .map(|b| stats(self.bodies.of(b), prev, before, frame, dt))
            .collect();
        let mut shift = vec![[0.0f32; 2]; self.bodies.len()];
        self.walls(p, &stats, dt, &mut shift);
        self.pairs(p, &stats, (prev, frame), &mut shift);
        let moves: Vec<[f32; 2]> = shift.iter().map(|s| [s[0] * dt, s[1] * dt]).collect();
        self.bodies.add(frame, &moves, 0);
    }

    /// The walls' contacts: per body and side, the speed to add along the wall's normal
    /// into `add` (domain units per time unit).
    fn walls(&mut self, p: &ReboundParams, stats: &[Stats], dt: f32, add: &mut [[f32; 2]]) {
        for (b, s) in stats.iter().enumerate() {
            for side in 0..4u32 {
                let axis = (side / 2) as usize;
                // The normal points away from the wall, into the box; the gap is the nearest
                // particle's distance from the wall.
                let (gap, gap_prev, normal) = match side % 2 {
                    0 => (s.lo[axis], s.lo_prev[axis], 1.0f32),
                    _ => (1.0 - s.hi[axis], 1.0 - s.hi_prev[axis], -1.0),
                };
                let key = (b as u32, WALL + side);
                let (u, fall) = (s.v[axis] * normal, p.gravity[axis] * normal * dt);
                if gap >= p.clearance {
                    // The contact ends in this frame.
                    if let Some(mut event) = self.events.remove(&key) {
                        add[b][axis] += event.exit(p, u, fall) * normal;
                    }
                    continue;
                }
                let event = self.events.entry(key).or_insert_with(|| Event {
                    speed_in: (gap_prev >= p.clearance)
                        .then(|| begin(-s.v_prev[axis] * normal, p.resting)),
                    leaving: 0,
                });
                if gap >= p.release {
                    add[b][axis] += event.exit(p, u, fall) * normal;
                }
            }
        }
    }

    /// The pairs' contacts: per pair within `reach`, equal and opposite speeds along the
    /// line between their centres into `add`.
    fn pairs(
        &mut self,
        p: &ReboundParams,
        stats: &[Stats],
        (prev, frame): (&[f32], &[f32]),
        add: &mut [[f32; 2]],
    ) {
        let near = self.near_pairs(frame, p.reach);
        let near_prev = self.near_pairs(prev, p.reach);
        // Contacts of pairs past `reach` end in this frame, with their exit speed.
        let ended: Vec<(u32, u32)> = self
            .events
            .keys()
            .filter(|key| key.1 < WALL && near.binary_search_by_key(*key, |&(k, _)| k).is_err())
            .copied()
            .collect();
        for (a, b) in ended {
            let mut event = self.events.remove(&(a, b)).expect("listed above");
            self.part(p, stats, (a, b), &mut event, add);
        }
        for &((a, b), gap) in &near {
            let (sa, sb) = (&stats[a as usize], &stats[b as usize]);
            let mut event = *self.events.entry((a, b)).or_insert_with(|| {
                let n = unit([sa.c_prev[0] - sb.c_prev[0], sa.c_prev[1] - sb.c_prev[1]]);
                let closing =
                    -((sa.v_prev[0] - sb.v_prev[0]) * n[0] + (sa.v_prev[1] - sb.v_prev[1]) * n[1]);
                let known = near_prev
                    .binary_search_by_key(&(a, b), |&(k, _)| k)
                    .is_err();
                Event {
                    speed_in: known.then(|| begin(closing, p.resting)),
                    leaving: 0,
                }
            });
            if gap >= p.release {
                self.part(p, stats, (a, b), &mut event, add);
                self.events.insert((a, b), event);
            }
        }
    }

    /// Pair `(a, b)` leaving `event`: equal and opposite speeds along the line between their
    /// centres into `add`, weighed by their particle counts (momentum kept).
    fn part(
        &self,
        p: &ReboundParams,
        stats: &[Stats],
        (a, b): (u32, u32),
        event: &mut Event,
        add: &mut [[f32; 2]],
    ) {
        let (sa, sb) = (&stats[a as usize], &stats[b as usize]);
        let n = unit([sa.c[0] - sb.c[0], sa.c[1] - sb.c[1]]);
        let u = (sa.v[0] - sb.v[0]) * n[0] + (sa.v[1] - sb.v[1]) * n[1];
        let d = event.exit(p, u, 0.0);
        if d != 0.0 {
            let ma = self.bodies.of(a as usize).len() as f32;
            let mb = self.bodies.of(b as usize).len() as f32;
            for k in 0..2 {
                add[a as usize][k] += d * mb / (ma + mb) * n[k];
                add[b as usize][k] -= d * ma / (ma + mb) * n[k];
            }
        }
    }

    /// The pairs of bodies `(a, b)`, `a < b`, with particles within `reach` in `frame`, in
    /// increasing order, each with the distance of its nearest two particles.
    fn near_pairs(&self, frame: &[f32], reach: f32) -> Vec<((u32, u32), f32)> {
        if self.bodies.len() < 2 {
            return Vec::new();
        }
        let bins = Bins::for_radius(frame, 4, &self.bodies.ids, reach);
        let mut near = BTreeMap::new();
        for &i in &self.bodies.ids {
            let bi = self.bodies.body_of[i as usize];
            let (x, y) = (frame[4 * i as usize], frame[4 * i as usize + 1]);
            bins.around(x, y, |j| {
                let bj = self.bodies.body_of[j];
                if bj > bi {
                    let r = (frame[4 * j] - x).hypot(frame[4 * j + 1] - y);
                    if r <= reach {
                        let gap = near.entry((bi, bj)).or_insert(r);
                        *gap = gap.min(r);
                    }
                }
            });
        }
        near.into_iter().collect()
    }
}

/// The approach speed a contact keeps: `speed` where it is above `resting`, else 0.
fn begin(speed: f32, resting: f32) -> f32 {
    if speed > resting {
        speed
    } else {
        0.0
    }
}

/// `v` over its length (`[0, 0]` for a zero vector).
fn unit(v: [f32; 2]) -> [f32; 2] {
    let len = v[0].hypot(v[1]);
    if len > 0.0 {
        [v[0] / len, v[1] / len]
    } else {
        [0.0, 0.0]
    }
}

/// The [`Stats`] of body `ids`.
fn stats(ids: &[u32], prev: &[f32], before: &[f32], frame: &[f32], dt: f32) -> Stats {
    let mut s = Stats {
        lo: [f32::INFINITY; 2],
        hi: [f32::NEG_INFINITY; 2],
        lo_prev: [f32::INFINITY; 2],
        hi_prev: [f32::NEG_INFINITY; 2],
        ..Default::default()
    };
    let (cp, c) = (centre_of_mass(prev, 4, ids), centre_of_mass(frame, 4, ids));
    let (mut vp, mut v) = ([0.0f64; 2], [0.0f64; 2]);
    for &i in ids {
        let i = 4 * i as usize;
        for a in 0..2 {
            vp[a] += f64::from(prev[i + 2 + a]);
            v[a] += f64::from(frame[i + 2 + a] + (frame[i + a] - before[i + a]) / dt);
            s.lo[a] = s.lo[a].min(frame[i + a]);
            s.hi[a] = s.hi[a].max(frame[i + a]);
            s.lo_prev[a] = s.lo_prev[a].min(prev[i + a]);
            s.hi_prev[a] = s.hi_prev[a].max(prev[i + a]);
        }
    }
    let m = ids.len().max(1) as f64;
    for a in 0..2 {
        s.c_prev[a] = cp[a] as f32;
        s.v_prev[a] = (vp[a] / m) as f32;
        s.c[a] = c[a] as f32;
        s.v[a] = (v[a] / m) as f32;
    }
    s
}

#[cfg(test)]
mod tests {
    use super::super::block;
    use super::*;

    const P: ReboundParams = ReboundParams {
        gravity: [0.0, 0.0],
        ..ReboundParams::DEFAULT
    };
    const DT: f32 = 0.016;

    /// The mean velocity of particles `range` of `frame`.
    fn velocity(frame: &[f32], range: std::ops::Range<usize>) -> [f32; 2] {
        let mut v = [0.0f32; 2];
        for i in range.clone() {
            for a in 0..2 {
                v[a] += frame[4 * i + 2 + a];
            }
        }
        let n = range.len() as f32;
        [v[0] / n, v[1] / n]
    }

    /// `frames[1..]`, each predicted from the one before as the projection left it, through
    /// the rebound and the caller's `v += dx / dt`; returns the last as projected and as
    /// predicted.
    fn run(rebound: &mut Rebound, frames: &[Vec<f32>]) -> (Vec<f32>, Vec<f32>) {
        let mut prev = frames[0].clone();
        let mut last = (Vec::new(), Vec::new());
        for f in &frames[1..] {
            let before = f.clone();
            let mut frame = f.clone();
            rebound.apply(&P, (&prev, &before, &mut frame), DT);
            for (r, b) in frame.chunks_exact_mut(4).zip(before.chunks_exact(4)) {
                r[2] += (r[0] - b[0]) / DT;
                r[3] += (r[1] - b[1]) / DT;
            }
            prev = frame.clone();
            last = (frame, before);
        }
        last
    }

    #[test]
    fn a_body_leaves_a_wall_at_the_restitution_of_its_approach() {
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        // Free at x = 0.2 moving left at 2; at the wall (0.05); leaving slowly at 0.5.
        let frames = [
            block(0.2, 0.5, [-2.0, 0.0]),
            block(0.05, 0.5, [0.0, 0.0]),
            block(0.06, 0.5, [0.5, 0.0]),
        ];
        let (frame, _) = run(&mut rebound, &frames);
        let v = velocity(&frame, 0..25);
        assert!((v[0] - 1.0).abs() < 1e-4, "{v:?}");
        // Still touching (0.03 from the wall, under the release gap): not yet.
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        let touching = [
            frames[0].clone(),
            frames[1].clone(),
            block(0.03, 0.5, [0.5, 0.0]),
        ];
        let (frame, before) = run(&mut rebound, &touching);
        assert_eq!(frame, before);
        // A body that leaves between 0.5 and 1 times its approach speed is left alone.
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        let within = [
            frames[0].clone(),
            frames[1].clone(),
            block(0.06, 0.5, [1.8, 0.0]),
        ];
        let (frame, before) = run(&mut rebound, &within);
        assert_eq!(frame, before);
        // One that leaves faster than it came is slowed to its approach speed.
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        let faster = [
            frames[0].clone(),
            frames[1].clone(),
            block(0.06, 0.5, [3.0, 0.0]),
        ];
        let (frame, _) = run(&mut rebound, &faster);
        assert!((velocity(&frame, 0..25)[0] - 2.0).abs() < 1e-4);
        // A contact under way in the first frame seen has no approach speed: left alone.
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        let (frame, before) = run(&mut rebound, &frames[1..]);
        assert_eq!(frame, before);
    }

    #[test]
    fn a_resting_contact_does_not_bounce() {
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        let frames = [
            block(0.4, 0.06, [0.0, -0.2]),
            block(0.4, 0.05, [0.0, 0.0]),
            block(0.4, 0.052, [0.0, 0.1]),
        ];
        let (frame, before) = run(&mut rebound, &frames);
        assert_eq!(frame, before);
    }

    #[test]
    fn a_pair_leaves_at_the_restitution_of_its_closing_speed_and_keeps_its_momentum() {
        let ids = |r: std::ops::Range<u32>| r.collect::<Vec<u32>>();
        let mut rebound = Rebound::new(&[ids(0..25), ids(25..50)], 50).unwrap();
        // Closing at 4 (2 each), far apart; touching; parting at 1.
        let frames = [
            [block(0.2, 0.5, [2.0, 0.0]), block(0.6, 0.5, [-2.0, 0.0])].concat(),
            [block(0.4, 0.5, [0.0, 0.0]), block(0.46, 0.5, [0.0, 0.0])].concat(),
            [block(0.38, 0.5, [-0.5, 0.0]), block(0.48, 0.5, [0.5, 0.0])].concat(),
        ];
        let (frame, _) = run(&mut rebound, &frames);
        let (a, b) = (velocity(&frame, 0..25), velocity(&frame, 25..50));
        assert!((b[0] - a[0] - 2.0).abs() < 1e-3, "{a:?} {b:?}");
        assert!((a[0] + b[0]).abs() < 1e-4, "momentum: {a:?} {b:?}");
    }

    #[test]
    fn a_pair_that_parts_past_reach_in_one_frame_still_gets_its_exit_speed() {
        let ids = |r: std::ops::Range<u32>| r.collect::<Vec<u32>>();
        let mut rebound = Rebound::new(&[ids(0..25), ids(25..50)], 50).unwrap();
        // Closing at 6, far apart; 0.04 apart (under release); then 0.08 apart (past reach,
        // 0.07) at once, parting at 2.5: below 0.5 times 6.
        let frames = [
            [block(0.2, 0.5, [3.0, 0.0]), block(0.6, 0.5, [-3.0, 0.0])].concat(),
            [block(0.4, 0.5, [0.0, 0.0]), block(0.48, 0.5, [0.0, 0.0])].concat(),
            [block(0.38, 0.5, [-1.25, 0.0]), block(0.5, 0.5, [1.25, 0.0])].concat(),
        ];
        let (frame, _) = run(&mut rebound, &frames);
        let (a, b) = (velocity(&frame, 0..25), velocity(&frame, 25..50));
        assert!((b[0] - a[0] - 3.0).abs() < 1e-3, "{a:?} {b:?}");
        assert!((a[0] + b[0]).abs() < 1e-4, "momentum: {a:?} {b:?}");
        // The contact has ended: the next frame is left alone.
        let next = [frame.clone(), frame.clone()];
        let (again, before) = run(&mut rebound, &next);
        assert_eq!(again, before);
    }

    #[test]
    fn a_body_that_leaves_a_wall_past_the_zone_in_one_frame_still_gets_its_exit_speed() {
        let mut rebound = Rebound::new(&[(0..25).collect()], 25).unwrap();
        // Free at x = 0.2 moving left at 2; at the wall (0.05); at 0.09, past the zone (0.08),
        // leaving at 0.5.
        let frames = [
            block(0.2, 0.5, [-2.0, 0.0]),
            block(0.05, 0.5, [0.0, 0.0]),
            block(0.09, 0.5, [0.5, 0.0]),
        ];
        let (frame, _) = run(&mut rebound, &frames);
        let v = velocity(&frame, 0..25);
        assert!((v[0] - 1.0).abs() < 1e-4, "{v:?}");
    }
}
