//! The MLS-MPM solver batched over scenes on a CUDA GPU (feature `cuda`): [`GpuSolver`] holds
//! the particles of many scenes of one [`SolverConfig`] on the device and advances them all
//! together, substep by substep, with the kernels of `kernels.rs`: per substep one kernel
//! decides each scene's equal parts (the CPU solver's CFL, strain and stability limits), then
//! per part P2G, the grid update and G2P, each one launch over every scene.
//!
//! It is the GPU form of [`crate::sim::mpm::Solver`] (Hu et al. 2018 as laid out in Taichi's
//! mpm99, `docs/mpm.md`): the same materials, walls, substep split and `F` update, in `f32`
//! with the same order of operations, but with P2G summed in 64-bit fixed point, so that a
//! run is the same to the bit on every run and independent of the order the GPU's atomics
//! land in (the CPU solver sums in particle order in `f32`: the two agree to f32 rounding per
//! substep and drift apart as any two f32 orders of a chaotic system do). The GPU solvers of
//! MPM codes scatter P2G with atomic adds the same way (Hu et al. 2019, "Taichi"; Wang et al.
//! 2020, "A massively parallel and scalable multi-GPU material point method"). Used by
//! `minflow bench sim --device cuda`, `bench rollout --device cuda` and `simulate --device
//! cuda`.

mod constitutive;
mod kernels;
mod support;

use burn::cubecl::cuda::CudaRuntime;
use burn_cubecl::cubecl;
use cubecl::prelude::*;
use cubecl::server::Handle;
use cubecl::{calculate_cube_count_elemwise, CubeElement};

use super::material::LIQUID_J_MIN;
use super::mpm::{Particles, Solver, SolverConfig, MAX_STRAIN_STEP};
use super::SimError;
use kernels::{g2p_kernel, grid_kernel, p2g_kernel, parts_kernel, TALLY};
use support::{copy_f32_kernel, copy_u32_kernel, maxima_kernel, zero_kernel, REDUCE_THREADS};

/// A GPU.
pub type CudaDevice = burn::backend::cuda::CudaDevice;

/// The fixed-point units of P2G per unit of `value / p_mass` (`2^40`): a node's mass of up to
/// `2^20` particles and momenta of up to `2^20` particle-masses times unit speed stay below
/// `i64`'s `2^63`, each contribution truncated to `2^-40` of a particle's mass.
const FIXED_UNITS: f32 = 1_099_511_627_776.0;

/// The device arrays of a batch (layout: `kernels.rs`); `saved` holds the particle state and
/// tallies at the start of a speculative frame.
struct Buffers {
    /// `x`, `v`, `c`, `f`, `jp`.
    state: [Handle; 5],
    saved: [Handle; 5],
    tally: Handle,
    saved_tally: Handle,
    material: Handle,
    scene: Handle,
    /// Each scene's first particle, and the total: `[B + 1]`.
    offsets: Handle,
    /// Each particle's three words of its scene's maxima: `[P 3]`.
    pmax: Handle,
    stiffness: Handle,
    acc: Handle,
    grid: Handle,
    parts: Handle,
    most: Handle,
}

/// Floats per particle of each state array (`x`, `v`, `c`, `f`, `jp`).
const WIDTHS: [usize; 5] = [2, 2, 4, 4, 1];

/// How many recent frames' most-split substep sets the parts a speculative frame runs, by
/// default ([`GpuSolver::with_window`]).
pub const RECENT: usize = 8;

/// Many scenes of one solver setting advanced together on the GPU.
pub struct GpuSolver {
    client: ComputeClient<CudaRuntime>,
    config: SolverConfig,
    /// Particles per scene, in order.
    counts: Vec<usize>,
    /// Every particle's material (they never change).
    material: Vec<u8>,
    buffers: Buffers,
    /// The most parts a substep took in each of the last `window` calls of
    /// [`GpuSolver::advance`].
    recent: Vec<u32>,
    window: usize,
    /// Substeps taken since the start (each of length `config.dt`).
    pub substeps_done: u64,
    /// Frames whose speculation fell short and were taken again substep by substep.
    pub redone: u64,
    /// Parts launched (each a P2G, a grid update and a G2P over the batch).
    pub passes: u64,
}

impl GpuSolver {
    /// Uploads `scenes` (each checked as [`Solver::check`] checks it) to `device`.
    ///
    /// # Errors
    /// A scene the CPU solver would refuse, no scenes, or more particles or nodes than
    /// 32-bit indices reach.
    pub fn new(
        device: &CudaDevice,
        config: SolverConfig,
        scenes: Vec<Particles>,
    ) -> Result<Self, SimError> {
        if scenes.is_empty() {
            return Err(SimError::Invalid("a GPU batch needs a scene".into()));
        }
        let n = config.grid;
        let mut flat = Particles::default();
        let mut counts = Vec::with_capacity(scenes.len());
        let mut scene_of = Vec::new();
        for (s, checked) in scenes.into_iter().enumerate() {
            Solver::check(&config, &checked)?;
            counts.push(checked.len());
            scene_of.extend(std::iter::repeat_n(s as u32, checked.len()));
            flat.x.extend(checked.x);
            flat.v.extend(checked.v);
            flat.c.extend(checked.c);
            flat.f.extend(checked.f);
            flat.jp.extend(checked.jp);
            flat.material.extend(checked.material);
        }
        let (total, b) = (flat.len(), counts.len());
        if total >= u32::MAX as usize / 4 || b * n * n * 3 >= u32::MAX as usize {
            return Err(SimError::Invalid(format!(
                "{b} scenes of {total} particles on {n}^2 grids exceed the GPU solver's 32-bit indices"
            )));
        }
        let client = CudaRuntime::client(device);
        let floats = |v: &[f32]| client.create_from_slice(f32::as_bytes(v));
        let words = |v: &[u32]| client.create_from_slice(u32::as_bytes(v));
        let material: Vec<u32> = flat.material.iter().map(|&m| m as u32).collect();
        let offsets: Vec<u32> = std::iter::once(0)
            .chain(counts.iter().scan(0u32, |at, &c| {
                *at += c as u32;
                Some(*at)
            }))
            .collect();
        let state = [
            floats(flat.x.as_flattened()),
            floats(flat.v.as_flattened()),
            floats(flat.c.as_flattened()),
            floats(flat.f.as_flattened()),
            floats(&flat.jp),
        ];
        let saved = WIDTHS.map(|w| client.empty(total * w * 4));
        let buffers = Buffers {
            state,
            saved,
            tally: words(&vec![0; b * TALLY]),
            saved_tally: words(&vec![0; b * TALLY]),
            material: words(&material),
            scene: words(&scene_of),
            offsets: words(&offsets),
            pmax: words(&vec![0; total * 3]),
            stiffness: floats(&vec![0.0; total]),
            acc: client.create_from_slice(i64::as_bytes(&vec![0i64; b * n * n * 3])),
            grid: floats(&vec![0.0; b * n * n * 3]),
            parts: words(&vec![1; b]),
            most: words(&[0]),
        };
        Ok(Self {
            client,
            config,
            counts,
            material: flat.material,
            buffers,
            recent: Vec::new(),
            window: RECENT,
            substeps_done: 0,
            redone: 0,
            passes: 0,
        })
    }

    /// Speculates each frame's parts from the last `frames` frames (default [`RECENT`]): a
    /// longer window redoes fewer frames and idles more parts; 0 never speculates (each
    /// substep's parts are read back before they run).
    pub fn with_window(mut self, frames: usize) -> Self {
        self.window = frames;
        self
    }

    /// Number of scenes.
    pub fn scenes(&self) -> usize {
        self.counts.len()
    }

    /// Particles of all scenes.
    pub fn particles(&self) -> usize {
        self.material.len()
    }

    /// Advances every scene `count` substeps (a frame), each substep in each scene's own
    /// number of equal parts (`Solver::substep`), with one read-back.
    ///
    /// The parts are decided on the device. The batch runs, in every substep, as many parts as
    /// the most split substep of the last few calls needed (scenes that need fewer idle); at
    /// the end it reads whether any substep needed more. If one did, the frame is taken again
    /// from a copy of its start, reading each substep's parts back before running them, so
    /// the result is always the CPU solver's split.
    ///
    /// # Errors
    /// The device's error.
    pub fn advance(&mut self, count: u32) -> Result<(), SimError> {
        if count == 0 {
            return Ok(());
        }
        if self.window == 0 {
            let most = self.exact(count)?;
            self.substeps_done += u64::from(count);
            self.recent = vec![most];
            return Ok(());
        }
        let guess = self.recent.iter().copied().max().unwrap_or(1);
        self.save(true);
        self.zero_most();
        for _ in 0..count {
            self.decide_parts();
            for part in 0..guess {
                self.part(part);
            }
        }
        let needed = self.read_most()?;
        let most = if needed <= guess {
            needed
        } else {
            self.redone += 1;
            self.save(false);
            self.exact(count)?
        };
        while self.recent.len() >= self.window {
            self.recent.remove(0);
        }
        self.recent.push(most);
        self.substeps_done += u64::from(count);
        Ok(())
    }

    /// `count` substeps, each one's parts read back before they run; returns the most parts a
    /// substep took.
    fn exact(&mut self, count: u32) -> Result<u32, SimError> {
        let mut most = 1;
        for _ in 0..count {
            self.zero_most();
            self.decide_parts();
            let parts = self.read_most()?;
            for part in 0..parts {
                self.part(part);
            }
            most = most.max(parts);
        }
        Ok(most)
    }

    /// Copies the particle state and tallies into `saved` (`forward`) or back.
    fn save(&self, forward: bool) {
        let buf = &self.buffers;
        let total = self.material.len();
        for (k, w) in WIDTHS.into_iter().enumerate() {
            let (src, dst) = match forward {
                true => (&buf.state[k], &buf.saved[k]),
                false => (&buf.saved[k], &buf.state[k]),
            };
            let len = total * w;
            let (cc, cd) = elementwise(&self.client, len);
            copy_f32_kernel::launch(&self.client, cc, cd, arr(src, len), arr(dst, len));
        }
        let (src, dst) = match forward {
            true => (&buf.tally, &buf.saved_tally),
            false => (&buf.saved_tally, &buf.tally),
        };
        let len = self.counts.len() * TALLY;
        let (cc, cd) = elementwise(&self.client, len);
        copy_u32_kernel::launch(&self.client, cc, cd, arr(src, len), arr(dst, len));
    }

    fn zero_most(&self) {
        let (cc, cd) = elementwise(&self.client, 1);
        zero_kernel::launch(&self.client, cc, cd, arr(&self.buffers.most, 1));
    }

    /// Reads `most` back (waits for the device).
    fn read_most(&self) -> Result<u32, SimError> {
        let bytes = self
            .client
            .read_one(self.buffers.most.clone())
            .map_err(|e| SimError::Invalid(format!("GPU solver: reading back: {e:?}")))?;
        Ok(u32::from_bytes(&bytes)[0].max(1))
    }

    /// Launches [`parts_kernel`]: each scene's parts of the next substep.
    fn decide_parts(&self) {
        let c = &self.config;
        let b = self.counts.len();
        let (cc, cd) = elementwise(&self.client, b);
        let buf = &self.buffers;
        parts_kernel::launch(
            &self.client,
            cc,
            cd,
            arr(&buf.tally, b * TALLY),
            arr(&buf.parts, b),
            arr(&buf.most, 1),
            c.dt,
            c.grid as u32,
            c.max_cfl,
            MAX_STRAIN_STEP,
        );
    }

    /// Part `part` of the substep: P2G, grid update, G2P and the maxima over every scene
    /// split at least `part + 1` ways.
    fn part(&mut self, part: u32) {
        self.passes += 1;
        let scale = FIXED_UNITS / (0.25 / (self.config.grid * self.config.grid) as f32);
        self.p2g(part, scale);
        let c = &self.config;
        let (b, n) = (self.counts.len(), c.grid);
        let nodes = b * n * n;
        let buf = &self.buffers;
        let (gc, gd) = elementwise(&self.client, nodes);
        grid_kernel::launch(
            &self.client,
            gc,
            gd,
            arr(&buf.acc, nodes * 3),
            arr(&buf.grid, nodes * 3),
            arr(&buf.parts, b),
            part,
            n as u32,
            c.dt,
            c.gravity[0],
            c.gravity[1],
            scale,
        );
        self.g2p(part);
    }

    /// Launches [`p2g_kernel`] for part `part` (`scale` fixed-point units per unit).
    fn p2g(&self, part: u32, scale: f32) {
        let c = &self.config;
        let (b, n) = (self.counts.len(), c.grid);
        let (p, nodes) = (self.material.len(), b * n * n);
        let (mu0, lambda0) = c.elasticity.lame();
        let buf = &self.buffers;
        let [x, v, cm, f, jp] = &buf.state;
        let (pc, pd) = elementwise(&self.client, p);
        p2g_kernel::launch(
            &self.client,
            pc,
            pd,
            arr(x, p * 2),
            arr(v, p * 2),
            arr(cm, p * 4),
            arr(f, p * 4),
            arr(jp, p),
            arr(&buf.material, p),
            arr(&buf.scene, p),
            arr(&buf.parts, b),
            arr(&buf.stiffness, p),
            arr(&buf.acc, nodes * 3),
            part,
            n as u32,
            c.dt,
            mu0,
            lambda0,
            scale,
        );
    }

    /// Launches [`g2p_kernel`] and [`maxima_kernel`] for part `part`.
    fn g2p(&self, part: u32) {
        let c = &self.config;
        let (b, n) = (self.counts.len(), c.grid);
        let (p, nodes) = (self.material.len(), b * n * n);
        let buf = &self.buffers;
        let [x, v, cm, f, jp] = &buf.state;
        let client = &self.client;
        let (pc, pd) = elementwise(client, p);
        let (snow_lo, snow_hi) = super::material::SNOW_LIMITS;
        g2p_kernel::launch(
            client,
            pc,
            pd,
            arr(x, p * 2),
            arr(v, p * 2),
            arr(cm, p * 4),
            arr(f, p * 4),
            arr(jp, p),
            arr(&buf.material, p),
            arr(&buf.scene, p),
            arr(&buf.parts, b),
            arr(&buf.stiffness, p),
            arr(&buf.grid, nodes * 3),
            arr(&buf.pmax, p * 3),
            arr(&buf.tally, b * TALLY),
            part,
            n as u32,
            c.dt,
            snow_lo,
            snow_hi,
            LIQUID_J_MIN,
        );
        maxima_kernel::launch(
            client,
            CubeCount::Static(b as u32, 1, 1),
            CubeDim::new_1d(REDUCE_THREADS),
            arr(&buf.pmax, p * 3),
            arr(&buf.offsets, b + 1),
            arr(&buf.parts, b),
            arr(&buf.tally, b * TALLY),
            part,
        );
    }

    /// Waits for the device and reads every scene's particles back, in order.
    ///
    /// # Errors
    /// The device's error.
    pub fn read(&self) -> Result<Vec<Particles>, SimError> {
        let bytes = self.client.read(self.buffers.state.to_vec());
        let [x, v, c, f, jp] = [0, 1, 2, 3, 4].map(|i| f32::from_bytes(&bytes[i]));
        let mut out = Vec::with_capacity(self.counts.len());
        let mut at = 0;
        for &count in &self.counts {
            let r = at..at + count;
            let rows = |a: &[f32], w: usize| a[r.start * w..r.end * w].to_vec();
            out.push(Particles {
                x: rows(x, 2).as_chunks::<2>().0.to_vec(),
                v: rows(v, 2).as_chunks::<2>().0.to_vec(),
                c: rows(c, 4).as_chunks::<4>().0.to_vec(),
                f: rows(f, 4).as_chunks::<4>().0.to_vec(),
                jp: jp[r.clone()].to_vec(),
                material: self.material[r].to_vec(),
            });
            at += count;
        }
        Ok(out)
    }

    /// Waits for the device and reads the particles' frame back, as a frame on the host
    /// needs it: every scene's positions (`[P, 2]`, scenes in order), then their velocities
    /// (`[P, 2]`), in one vector (what `bench rollout` times against a model's predicted
    /// frames read back; [`GpuSolver::read`] reads the whole state).
    ///
    /// # Errors
    /// The device's error.
    pub fn read_frame(&self) -> Result<Vec<f32>, SimError> {
        let bytes = self.client.read(self.buffers.state[..2].to_vec());
        let (x, v) = (f32::from_bytes(&bytes[0]), f32::from_bytes(&bytes[1]));
        let mut out = Vec::with_capacity(x.len() + v.len());
        out.extend_from_slice(x);
        out.extend_from_slice(v);
        Ok(out)
    }

    /// Per scene, `(escaped, splits)`: particle-substeps that ended outside the
    /// interpolation band (as [`Solver::escaped`]) and extra parts taken (as
    /// [`Solver::splits`]); waits for the device.
    ///
    /// # Errors
    /// The device's error.
    pub fn tallies(&self) -> Result<Vec<(u64, u64)>, SimError> {
        let bytes = self
            .client
            .read_one(self.buffers.tally.clone())
            .map_err(|e| SimError::Invalid(format!("GPU solver: reading back: {e:?}")))?;
        let words = u32::from_bytes(&bytes);
        Ok(words
            .chunks_exact(TALLY)
            .map(|t| (u64::from(t[3]), u64::from(t[4])))
            .collect())
    }
}

/// A launch argument over `len` elements of `h`.
fn arr(h: &Handle, len: usize) -> ArrayArg<CudaRuntime> {
    // SAFETY: every handle of a batch is allocated with at least `len` elements of the
    // kernel's type (`GpuSolver::new`).
    unsafe { ArrayArg::from_raw_parts(h.clone(), len) }
}

/// One thread per unit: the launch's cube count and size.
fn elementwise(client: &ComputeClient<CudaRuntime>, units: usize) -> (CubeCount, CubeDim) {
    let dim = CubeDim::new(client, units);
    (calculate_cube_count_elemwise(client, units, dim), dim)
}
