//! The liquid's pressure projection on a grid, the way FLIP/APIC and MPM liquids are kept
//! incompressible (Bridson, "Fluid Simulation for Computer Graphics", 2nd ed., chapter 5: the
//! pressure solve on a MAC grid with empty cells at zero pressure and solid faces closed),
//! with the density error corrected in the same solve (Kugelstadt et al. 2019, "Implicit
//! Density Projection for Volume Conserving Liquids", section 4: a Poisson problem for the
//! displacement that undoes a cell's excess volume fraction) and unilateral, so liquid may
//! separate and splash but never compress (Gerszewski & Bargteil 2013, "Physics-Based
//! Animation of Large-Scale Splashing Liquids", section 4: pressure >= 0, solved by projected
//! Gauss-Seidel; Narain et al. 2010 for the complementarity form).
//!
//! Per predicted frame, on pressure nodes of spacing `h` (a node's control volume is the cell
//! around it; MAC faces half a cell between nodes):
//! 1. liquid particles past a wall are mirrored back inside (the walls part would
//!    stack them on one line);
//! 2. the liquid's volume fraction `phi_i = sum_p w_ip V_p` (MPM's quadratic B-spline,
//!    [`crate::bspline::weights`]), `V_p` the particle's rest volume in cells, fixed once
//!    from the scene's rest frame so that `phi = 1` there (see [`Pressure::new`]): the rest
//!    state is the one the solver starts the scene in (`J = 1`), whatever the sampling;
//! 3. the predicted velocities on the MAC faces (bilinear P2G, normalised) and their
//!    divergence at each node;
//! 4. on the full nodes (`phi >= full`) the unilateral constraint `div d >= r_i` on the
//!    displacement `d = -grad p`, `p >= 0`, with `r_i = stiffness max(phi_i - rest, 0) /
//!    phi_i - dt div v_i` (the excess compression removed, and no compressing velocity
//!    left; `rest` higher in a band along the walls, where the solver's own liquid
//!    packs); nodes that are not full are free surface (`p = 0`), nodes in the walls or in a
//!    solid body closed (no flow through their faces);
//! 5. red-black projected successive over-relaxation for `p` (deterministic, node order
//!    fixed), `d` on the faces, each liquid particle moved by `d` at its position (bilinear
//!    G2P of the change, FLIP-style: the particle's own motion is kept, only the correction
//!    is added). The projection then gives the velocity the move over `dt`
//!    ([`super::SceneShape::project`]), so a compressing velocity is removed with it.

use super::PressureParams;
use crate::material::Material;

/// The liquid of one scene for the pressure projection.
#[derive(Clone, Debug)]
pub(super) struct Pressure {
    /// Liquid particle indices.
    pub(super) ids: Vec<u32>,
    /// Per liquid particle, its rest volume in cells (`h^2` units).
    pub(super) volume: Vec<f32>,
    /// The liquid's median rest volume: what a particle of another material brings.
    solid: f32,
    /// Volume fraction above which a node is compressed (the scene's grid's threshold).
    pub(super) rest: f32,
    /// Width of the band along the walls (domain units) and the threshold there.
    pub(super) band: (f32, f32),
    /// Node spacing (domain units).
    pub(super) h: f32,
    /// Nodes per side (node `i` at `i h`).
    pub(super) side: usize,
    /// Buffers reused from frame to frame.
    scratch: Scratch,
}

/// Per-frame buffers (node arrays are `side * side`, row `i` along x).
#[derive(Clone, Debug, Default)]
struct Scratch {
    phi: Vec<f32>,
    solid: Vec<f32>,
    kind: Vec<u8>,
    rhs: Vec<f32>,
    p: Vec<f32>,
    /// Face values along x (face `(i, j)` between nodes `(i, j)` and `(i + 1, j)`) and their
    /// weights; the same along y.
    fx: Vec<f32>,
    wx: Vec<f32>,
    fy: Vec<f32>,
    wy: Vec<f32>,
    /// The solve's nodes, red then black: each full node with open neighbours, its open
    /// neighbours (the first `k`) and `k`; `red` of them red.
    stencils: Vec<([u32; 5], u32)>,
    red: usize,
}

/// A node the solve leaves at zero pressure (free surface).
const FREE: u8 = 0;
/// A node that may take pressure.
const FULL: u8 = 1;
/// A node no flow crosses (solid body).
const CLOSED: u8 = 2;
/// A node in the walls: closed, and its faces' velocity is the wall's, zero.
const WALL: u8 = 3;

/// Bilinear stencil on a lattice offset by `(ox, oy)` cells: the lower lattice point and the
/// fractions along each axis.
fn bilinear(x: f32, y: f32, h: f32, ox: f32, oy: f32) -> ([i32; 2], [f32; 2]) {
    let (gx, gy) = (x / h - ox, y / h - oy);
    let (bx, by) = (gx.floor(), gy.floor());
    ([bx as i32, by as i32], [gx - bx, gy - by])
}

impl Pressure {
    /// The liquid particles' indices (`[L]`).
    pub(super) fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// The liquid of the rest frame `rest` (`[N, stride]` rows), whose particle spacing is
    /// `spacing`, made on the solver grid `grid` (if known): nodes `p.radius` spacings apart,
    /// the compressed threshold [`PressureParams::rest_for`] the grid, and each particle's rest volume
    /// `V_p = 1 / rho_p`, `rho_p` the B-spline average of the rest frame's particles per cell
    /// around it over the occupied nodes, clamped to `[1, 2]` times the liquid's median: a
    /// cluster of the sampling is at rest (the solver's liquid starts there at `J = 1`), a
    /// sparse spot or the surface counts at the median (so it may fill in, and a surface
    /// particle is not given the volume of two). None without liquid.
    pub(super) fn new(
        rest: &[f32],
        stride: usize,
        material: &[u8],
        spacing: f32,
        (p, grid): (&PressureParams, Option<u32>),
    ) -> Option<Self> {
        let liquid = Material::Liquid.id();
        let ids: Vec<u32> = (0..material.len() as u32)
            .filter(|&i| material[i as usize] == liquid)
            .collect();
        if ids.is_empty() || spacing <= 0.0 || p.radius <= 0.0 {
            return None;
        }
        let h = p.radius * spacing;
        let side = (1.0 / h).ceil() as usize + 2;
        let mut out = Self {
            ids,
            rest: p.rest_for(grid),
            band: (
                p.band / grid.unwrap_or(64).max(1) as f32,
                p.band_rest * p.rest_for(grid),
            ),
            volume: Vec::new(),
            solid: 0.0,
            h,
            side,
            scratch: Scratch::default(),
        };
        let ones = vec![1.0f32; out.ids.len()];
        let mut count = vec![0.0f32; side * side];
        out.splat(rest, stride, &ones, &mut count);
        let mut rho: Vec<f32> = out
            .ids
            .iter()
            .map(|&i| {
                let (x, y) = (rest[stride * i as usize], rest[stride * i as usize + 1]);
                let (mut num, mut den) = (0.0f32, 0.0f32);
                out.each_quadratic(x, y, |n, w| {
                    if count[n] > 0.0 {
                        num += w * count[n];
                        den += w;
                    }
                });
                if den > 0.0 {
                    num / den
                } else {
                    0.0
                }
            })
            .collect();
        let mut sorted = rho.clone();
        let mid = sorted.len() / 2;
        sorted.select_nth_unstable_by(mid, f32::total_cmp);
        let median = sorted[mid].max(f32::MIN_POSITIVE);
        for r in &mut rho {
            *r = r.clamp(median, 2.0 * median);
        }
        out.volume = rho.iter().map(|r| 1.0 / r).collect();
        let mut sorted = out.volume.clone();
        let mid = sorted.len() / 2;
        out.solid = *sorted.select_nth_unstable_by(mid, f32::total_cmp).1;
        Some(out)
    }

    /// Visits the 9 nodes of the quadratic stencil at `(x, y)` (clamped into the grid): node
    /// index and weight.
    fn each_quadratic(&self, x: f32, y: f32, mut visit: impl FnMut(usize, f32)) {
        let (base, _, w) = crate::bspline::stencil(x, y, self.h);
        let c = |v: i32| v.clamp(0, self.side as i32 - 1) as usize;
        for (a, wa) in w[0].iter().enumerate() {
            for (b, wb) in w[1].iter().enumerate() {
                let (i, j) = (c(base[0] + a as i32), c(base[1] + b as i32));
                visit(i * self.side + j, wa * wb);
            }
        }
    }

    /// `out[n] = sum_p w_np values[p]` over the liquid particles of `frame` (zeroed first).
    fn splat(&self, frame: &[f32], stride: usize, values: &[f32], out: &mut [f32]) {
        out.iter_mut().for_each(|v| *v = 0.0);
        for (&i, &v) in self.ids.iter().zip(values) {
            let (x, y) = (frame[stride * i as usize], frame[stride * i as usize + 1]);
            self.each_quadratic(x, y, |n, w| out[n] += w * v);
        }
    }

    /// Visits the 4 faces of the bilinear stencil at `(x, y)` along `axis` (0: faces between
    /// nodes along x, at `((i + 1/2) h, j h)`; 1: along y): face index and weight; faces off
    /// the grid are skipped.
    fn each_face(&self, x: f32, y: f32, axis: usize, mut visit: impl FnMut(usize, f32)) {
        let (ox, oy) = if axis == 0 { (0.5, 0.0) } else { (0.0, 0.5) };
        let (base, t) = bilinear(x, y, self.h, ox, oy);
        let s = self.side as i32;
        for a in 0..2 {
            for b in 0..2 {
                let (i, j) = (base[0] + a, base[1] + b);
                if i < 0 || j < 0 || i >= s || j >= s {
                    continue;
                }
                let wa = if a == 0 { 1.0 - t[0] } else { t[0] };
                let wb = if b == 0 { 1.0 - t[1] } else { t[1] };
                visit(i as usize * self.side + j as usize, wa * wb);
            }
        }
    }
}

/// A frame's grid, solved.
impl Pressure {
    /// Projects the liquid of `frame` (`[N, 4]` physical x, y, vx, vy, predicted `dt` after the
    /// last frame) in place (module doc): positions moved, velocities left to the caller.
    /// `walls` (`lo`, `hi`, domain units) close the nodes outside them; the other materials'
    /// particles (ids `material`) close the nodes where they outweigh the liquid.
    pub(super) fn project(
        &mut self,
        p: &PressureParams,
        frame: &mut [f32],
        material: &[u8],
        dt: f32,
        walls: (f32, f32),
    ) {
        let mut s = std::mem::take(&mut self.scratch);
        let nodes = self.side * self.side;
        for v in [&mut s.phi, &mut s.solid, &mut s.rhs, &mut s.p] {
            v.clear();
            v.resize(nodes, 0.0);
        }
        self.reflect(frame, walls);
        self.splat(frame, 4, &self.volume, &mut s.phi);
        self.solids(frame, material, &mut s.solid);
        self.classify(p, walls, &mut s);
        let full: Vec<usize> = (0..nodes).filter(|&n| s.kind[n] == FULL).collect();
        if !full.is_empty() {
            if p.velocity {
                self.face_velocities(frame, &mut s);
            }
            let mut any = false;
            for &n in &full {
                let phi = s.phi[n];
                let rest = match self.off_the_walls(n, walls) {
                    true => self.rest,
                    false => self.band.1,
                };
                let mut r = p.stiffness * (phi - rest).max(0.0) / phi;
                if p.velocity {
                    r -= dt * self.divergence(n, &s);
                }
                s.rhs[n] = r;
                any |= r > 0.0;
            }
            if any {
                self.solve(p, &full, &mut s);
                self.displace(frame, &mut s);
            }
        }
        self.scratch = s;
    }

    /// Each liquid particle past a wall brought back inside by its depth (mirrored, within
    /// `[lo, hi]`): a surrogate that presses the liquid into the floor would otherwise have
    /// the walls stack it on one line, which no grid can pull apart again.
    fn reflect(&self, frame: &mut [f32], (lo, hi): (f32, f32)) {
        if lo >= hi {
            return;
        }
        for &i in &self.ids {
            for a in 0..2 {
                let v = &mut frame[4 * i as usize + a];
                if *v < lo {
                    *v = (2.0 * lo - *v).min(hi);
                } else if *v > hi {
                    *v = (2.0 * hi - *v).max(lo);
                }
            }
        }
    }

    /// Whether node `n` lies farther than the band from every wall (`walls`: `lo`, `hi`).
    fn off_the_walls(&self, n: usize, (lo, hi): (f32, f32)) -> bool {
        let (x, y) = (
            (n / self.side) as f32 * self.h,
            (n % self.side) as f32 * self.h,
        );
        let inside = |v: f32| v > lo + self.band.0 && v < hi - self.band.0;
        inside(x) && inside(y)
    }

    /// `out[n]`: the volume the other materials' particles bring to node `n`, in cells (each
    /// counted at the liquid's median rest volume).
    fn solids(&self, frame: &[f32], material: &[u8], out: &mut [f32]) {
        let liquid = Material::Liquid.id();
        let v = self.solid_volume();
        for (row, &m) in frame.chunks_exact(4).zip(material) {
            if m != liquid {
                self.each_quadratic(row[0], row[1], |n, w| out[n] += w * v);
            }
        }
    }

    /// The volume each particle of another material brings (cells): the liquid's median.
    pub(super) fn solid_volume(&self) -> f32 {
        self.solid
    }

    /// Each node's kind: closed in the walls (its cell wholly outside `walls` on either axis) or
    /// where the solids outweigh the liquid, full where the liquid's volume fraction reaches
    /// `p.full` of the compressed threshold, free otherwise.
    fn classify(&self, p: &PressureParams, (lo, hi): (f32, f32), s: &mut Scratch) {
        s.kind.clear();
        s.kind.resize(self.side * self.side, FREE);
        for i in 0..self.side {
            for j in 0..self.side {
                let n = i * self.side + j;
                let (x, y) = (i as f32 * self.h, j as f32 * self.h);
                let half = 0.5 * self.h;
                let beyond = |v: f32| v + half <= lo || v - half >= hi;
                let wall = beyond(x) || beyond(y);
                s.kind[n] = if wall {
                    WALL
                } else if s.solid[n] > s.phi[n] && s.solid[n] > 0.0 {
                    CLOSED
                } else if s.phi[n] >= p.full * self.rest {
                    FULL
                } else {
                    FREE
                };
            }
        }
    }

    /// The liquid's velocities on the MAC faces (bilinear P2G, normalised by the weights).
    fn face_velocities(&self, frame: &[f32], s: &mut Scratch) {
        let nodes = self.side * self.side;
        for v in [&mut s.fx, &mut s.wx, &mut s.fy, &mut s.wy] {
            v.clear();
            v.resize(nodes, 0.0);
        }
        for &i in &self.ids {
            let r = &frame[4 * i as usize..4 * i as usize + 4];
            let (fx, wx) = (&mut s.fx, &mut s.wx);
            self.each_face(r[0], r[1], 0, |f, w| {
                fx[f] += w * r[2];
                wx[f] += w;
            });
            let (fy, wy) = (&mut s.fy, &mut s.wy);
            self.each_face(r[0], r[1], 1, |f, w| {
                fy[f] += w * r[3];
                wy[f] += w;
            });
        }
        for (v, w) in s.fx.iter_mut().zip(&s.wx).chain(s.fy.iter_mut().zip(&s.wy)) {
            if *w > 0.0 {
                *v /= *w;
            }
        }
    }

    /// The divergence of the face velocities at node `n` (per time unit), a face against a
    /// wall at the wall's zero velocity; 0 where a face of the node holds no liquid.
    fn divergence(&self, n: usize, s: &Scratch) -> f32 {
        let (i, j) = (n / self.side, n % self.side);
        if i == 0 || j == 0 || i + 1 >= self.side || j + 1 >= self.side {
            return 0.0;
        }
        let (left, down) = (n - self.side, n - 1);
        // Each face's velocity: the wall's (zero) against a wall node, else the liquid's;
        // None where the face holds no liquid.
        let face = |v: &[f32], w: &[f32], f: usize, other: usize| match s.kind[other] {
            WALL => Some(0.0),
            _ => (w[f] > 0.0).then(|| v[f]),
        };
        let faces = [
            face(&s.fx, &s.wx, n, n + self.side),
            face(&s.fx, &s.wx, left, left),
            face(&s.fy, &s.wy, n, n + 1),
            face(&s.fy, &s.wy, down, down),
        ];
        match faces {
            [Some(r), Some(l), Some(u), Some(d)] => (r - l + u - d) / self.h,
            _ => 0.0,
        }
    }

    /// Red-black projected SOR for `q = p / h^2` on the full nodes: at each,
    /// `sum_n (q_i - q_n) = r_i` over its open neighbours (free ones at 0), `q >= 0`.
    fn solve(&self, p: &PressureParams, full: &[usize], s: &mut Scratch) {
        self.stencils(full, s);
        let Scratch {
            stencils,
            red,
            rhs,
            p: q,
            ..
        } = s;
        let omega = p.omega;
        let (reds, blacks) = stencils.split_at(*red);
        for _ in 0..p.iterations {
            for colour in [reds, blacks] {
                for &([n, m @ ..], k) in colour {
                    let mut sum = 0.0f32;
                    for &m in &m[..k as usize] {
                        sum += q[m as usize];
                    }
                    let n = n as usize;
                    let target = (rhs[n] + sum) / k as f32;
                    q[n] = (q[n] + omega * (target - q[n])).max(0.0);
                }
            }
        }
    }

    /// The solve's stencils into `s` (red-black by `(i + j) % 2`, each colour in node
    /// order): every full node with an open neighbour and those neighbours, in the order
    /// `i - 1, i + 1, j - 1, j + 1` (so the sums, and the results, are those of a sweep that
    /// looks them up). The node kinds do not change during a solve.
    fn stencils(&self, full: &[usize], s: &mut Scratch) {
        let side = self.side;
        s.stencils.clear();
        for c in 0..2 {
            for &n in full.iter().filter(|&&n| (n / side + n % side) % 2 == c) {
                let (i, j) = (n / side, n % side);
                let neighbours = [
                    (i > 0).then(|| n - side),
                    (i + 1 < side).then(|| n + side),
                    (j > 0).then(|| n - 1),
                    (j + 1 < side).then(|| n + 1),
                ];
                let mut st = [n as u32, 0, 0, 0, 0];
                let mut k = 0;
                for m in neighbours.into_iter().flatten() {
                    if s.kind[m] < CLOSED {
                        k += 1;
                        st[k] = m as u32;
                    }
                }
                if k > 0 {
                    s.stencils.push((st, k as u32));
                }
            }
            if c == 0 {
                s.red = s.stencils.len();
            }
        }
    }

    /// The displacement `d = (q_i - q_n) h` on every face between two open nodes (0 at a
    /// closed one), and each liquid particle moved by its bilinear average.
    fn displace(&self, frame: &mut [f32], s: &mut Scratch) {
        let side = self.side;
        let nodes = side * side;
        for v in [&mut s.fx, &mut s.fy] {
            v.clear();
            v.resize(nodes, 0.0);
        }
        for n in 0..nodes {
            let (i, j) = (n / side, n % side);
            let open = |m: usize| s.kind[m] < CLOSED;
            if i + 1 < side && open(n) && open(n + side) {
                s.fx[n] = (s.p[n] - s.p[n + side]) * self.h;
            }
            if j + 1 < side && open(n) && open(n + 1) {
                s.fy[n] = (s.p[n] - s.p[n + 1]) * self.h;
            }
        }
        for &i in &self.ids {
            let at = 4 * i as usize;
            let (x, y) = (frame[at], frame[at + 1]);
            let (mut dx, mut dy) = (0.0f32, 0.0f32);
            self.each_face(x, y, 0, |f, w| dx += w * s.fx[f]);
            self.each_face(x, y, 1, |f, w| dy += w * s.fy[f]);
            frame[at] += dx;
            frame[at + 1] += dy;
        }
    }

    /// The liquid's volume fraction at every node of `frame` (`[N, 4]`; for tests and the
    /// fit).
    #[cfg(test)]
    pub(super) fn fractions(&self, frame: &[f32]) -> Vec<f32> {
        let mut phi = vec![0.0; self.side * self.side];
        self.splat(frame, 4, &self.volume, &mut phi);
        phi
    }
}

#[cfg(test)]
mod tests;
