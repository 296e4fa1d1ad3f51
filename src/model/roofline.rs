//! A grid model call's roofline by part, while `bench rollout --stages` has it on ([`enable`];
//! off otherwise: no clock is read and nothing waits). At each part's end the call waits for
//! its device ([`mark`]: `Backend::sync`), so a part's time is its own work (the host's
//! recording and the GPU's kernels, not overlapped with the next part's): the sum of the
//! parts is a call timed without overlap, and a part's needs set against its time say how
//! far it is from the GPU's limits (Williams et al. 2009, "Roofline: an insightful visual
//! performance model for multicore architectures": a kernel takes at least its bytes over
//! the memory bandwidth and its FLOPs over the arithmetic rate).
//!
//! The parts ([`Part`]), in a call's order: the host's work between calls (the rollout's
//! bookkeeping, a read-back behind the last call), the input (the frame uploaded, the
//! velocity history and rest features built), P2G (stencil weights and the splat onto the
//! grid's channels), the U-Net, the first G2P (the latent field gathered at the particles),
//! the memory (the per-particle minGRU / minLSTM update on its inputs), the head (the later
//! frames' G2P, the head's layers and the integration), the projection, and the read-back.
//! [`count`] adds a part's needs: the FLOPs and the fewest bytes it must move (each input
//! read and each output written once), counted from the tensors' shapes where the part runs.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;

/// The parts of a call, in order ([module doc](self)).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Part {
    Host,
    Input,
    P2g,
    UNet,
    G2p,
    Memory,
    Head,
    Projection,
    ReadBack,
}

impl Part {
    /// Every part, in a call's order.
    pub const ALL: [Part; 9] = [
        Part::Host,
        Part::Input,
        Part::P2g,
        Part::UNet,
        Part::G2p,
        Part::Memory,
        Part::Head,
        Part::Projection,
        Part::ReadBack,
    ];

    /// The part's name in `bench rollout --stages`' table.
    pub fn name(self) -> &'static str {
        match self {
            Part::Host => "host, between calls",
            Part::Input => "input assembly",
            Part::P2g => "P2G",
            Part::UNet => "U-Net",
            Part::G2p => "G2P (first frame)",
            Part::Memory => "memory (per particle)",
            Part::Head => "head, later G2P, integration",
            Part::Projection => "projection",
            Part::ReadBack => "read-back",
        }
    }
}

/// One part's totals since the last [`take`]: seconds, FLOPs, bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Tally {
    pub seconds: f64,
    pub flops: f64,
    pub bytes: f64,
}

/// The tallies by part and what [`mark`] needs between calls.
struct Profile {
    parts: [Tally; 9],
    /// FLOPs and bytes counted since the last mark: the next marked part's.
    pending: (f64, f64),
    last: Option<Instant>,
    calls: usize,
}

static ON: AtomicBool = AtomicBool::new(false);
static PROFILE: Mutex<Profile> = Mutex::new(Profile {
    parts: [Tally {
        seconds: 0.0,
        flops: 0.0,
        bytes: 0.0,
    }; 9],
    pending: (0.0, 0.0),
    last: None,
    calls: 0,
});

/// Turns the roofline on or off for the whole process.
pub fn enable(on: bool) {
    ON.store(on, Ordering::Relaxed);
}

/// Whether the roofline is on.
pub fn on() -> bool {
    ON.load(Ordering::Relaxed)
}

/// Ends `part` of the current call: waits for `device`'s queued work, adds the time since
/// the last mark and the needs counted since then to `part` ([`begin`] starts a call).
/// Nothing when the roofline is off.
pub fn mark<B: Backend>(device: &B::Device, part: Part) {
    if !on() {
        return;
    }
    let _ = B::sync(device);
    let now = Instant::now();
    let mut p = PROFILE.lock().unwrap_or_else(|e| e.into_inner());
    let (flops, bytes) = std::mem::take(&mut p.pending);
    let since = p.last.map_or(0.0, |t| (now - t).as_secs_f64());
    let tally = &mut p.parts[part as usize];
    tally.seconds += since;
    tally.flops += flops;
    tally.bytes += bytes;
    p.last = Some(now);
}

/// Starts a call: the time since the last call's last mark goes to [`Part::Host`].
pub fn begin<B: Backend>(device: &B::Device) {
    if !on() {
        return;
    }
    mark::<B>(device, Part::Host);
    PROFILE.lock().unwrap_or_else(|e| e.into_inner()).calls += 1;
}

/// Adds `flops` and `bytes` to the part the next [`mark`] ends.
pub fn count(flops: f64, bytes: f64) {
    if !on() {
        return;
    }
    let mut p = PROFILE.lock().unwrap_or_else(|e| e.into_inner());
    p.pending.0 += flops;
    p.pending.1 += bytes;
}

/// A dense layer's needs on `rows` rows: `2 rows in out` FLOPs; its input and output rows
/// and its weight, f32.
pub fn count_dense(rows: usize, inputs: usize, outputs: usize) {
    let (r, i, o) = (rows as f64, inputs as f64, outputs as f64);
    count(2.0 * r * i * o, 4.0 * (r * (i + o) + i * o));
}

/// The U-Net's needs for a call on `b` grids of `n x n` nodes: each convolution's `2 k^2
/// C_in C_out` FLOPs a node at its level's resolution, and its input, output and weight read
/// or written once (what an implicit-GEMM convolution moves). The levels come from the
/// order burn visits the weights: the way down (two convolutions a level), the way up (two a
/// level but the lowest), the 1 x 1 output convolution.
pub fn count_unet<B: Backend, M: Module<B>>(unet: &M, b: usize, n: usize) {
    if !on() {
        return;
    }
    let mut shapes = Weights(Vec::new());
    unet.visit(&mut shapes);
    let (flops, bytes) = unet_needs(&shapes.0, b, n);
    count(flops, bytes);
}

/// [`count_unet`]'s FLOPs and bytes from the U-Net's convolution weights' shapes
/// (`[C_out, C_in, k, k]`, in visiting order).
fn unet_needs(convs: &[[usize; 4]], b: usize, n: usize) -> (f64, f64) {
    let levels = (convs.len() + 1) / 4;
    let (mut flops, mut bytes) = (0.0, 0.0);
    for (i, &[c_out, c_in, k, _]) in convs.iter().enumerate() {
        let level = match i {
            i if i < 2 * levels => i / 2,
            i if i + 1 < convs.len() => (i - 2 * levels) / 2,
            _ => 0,
        };
        let nodes = (b * (n >> level) * (n >> level)) as f64;
        let (ci, co, kk) = (c_in as f64, c_out as f64, (k * k) as f64);
        flops += 2.0 * nodes * kk * ci * co;
        bytes += 4.0 * (nodes * (ci + co) + kk * ci * co);
    }
    (flops, bytes)
}

/// The shapes of a module's 4-D weights, in visiting order.
struct Weights(Vec<[usize; 4]>);

impl<B: Backend> ModuleVisitor<B> for Weights {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        if D == 4 {
            let dims = param.val().dims();
            self.0.push([dims[0], dims[1], dims[2], dims[3]]);
        }
    }
}

/// Every part's tallies and the calls since the last take, then zeroed (the clock
/// restarts at the next call); None when off or no call was timed.
pub fn take() -> Option<([Tally; 9], usize)> {
    if !on() {
        return None;
    }
    let mut p = PROFILE.lock().unwrap_or_else(|e| e.into_inner());
    let calls = std::mem::take(&mut p.calls);
    let parts = std::mem::take(&mut p.parts);
    p.pending = (0.0, 0.0);
    p.last = None;
    (calls > 0).then_some((parts, calls))
}

#[cfg(test)]
mod tests {
    use burn::backend::NdArray;

    use super::{unet_needs, Weights};
    use crate::model::grid::UNetConfig;

    #[test]
    fn the_unets_flops_are_its_convolutions_at_their_levels() {
        // Two levels of widths 4 and 8 on 8 x 8 grids, 5 channels in, 3 out.
        let config = UNetConfig::new(5, 3).with_width(4).with_levels(2);
        let unet = config.init::<NdArray<f32>>(&Default::default());
        let mut shapes = Weights(Vec::new());
        burn::module::Module::visit(&unet, &mut shapes);
        let (flops, _) = unet_needs(&shapes.0, 2, 8);
        // Down: 5 -> 4, 4 -> 4 on 8^2 and 4 -> 8, 8 -> 8 on 4^2; up: 12 -> 4, 4 -> 4 on
        // 8^2; the 1 x 1 head 4 -> 3 on 8^2.
        let macs = 64 * 9 * (20 + 16 + 48 + 16) + 16 * 9 * (32 + 64) + 64 * 12;
        assert_eq!(flops, (2 * 2 * macs) as f64);
    }
}
