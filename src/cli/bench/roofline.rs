//! `bench rollout --stages`: the roofline table under each model's row: per part of a grid
//! call ([`crate::model::roofline`]) its milliseconds a call (each part waited for, so the
//! parts do not overlap), its share, its needs (GFLOP, MB moved) and the rates they give,
//! the time the part would take at the GPU's limits (`--peak-gbs`, `--peak-tflops`; the
//! read-back at PCIe's) and how many times that its measured time is.

use crate::model::roofline::{Part, Tally};

/// The GPU's limits the table compares with.
#[derive(Debug, Clone, Copy)]
pub(super) struct Peaks {
    /// Memory bandwidth, GB/s (H200 4,800; H100 SXM 3,350).
    pub(super) gbs: f64,
    /// Dense arithmetic, TFLOP/s (TF32 tensor cores: H100 and H200 495).
    pub(super) tflops: f64,
}

/// A host <-> device copy's practical rate over PCIe 5 x16, GB/s.
const PCIE_GBS: f64 = 55.0;

/// Prints the roofline of `calls` calls' `parts` under a row of the rollout table.
pub(super) fn print(parts: &[Tally; 9], calls: usize, peaks: Peaks) {
    let per = |x: f64| x / calls.max(1) as f64;
    let total: f64 = parts.iter().map(|t| t.seconds).sum();
    println!(
        "|   roofline, {calls} calls: part | ms a call | share | GFLOP | MB | GB/s | TFLOP/s | ms at the roof | x roof |"
    );
    for (part, t) in Part::ALL.iter().zip(parts) {
        let ms = per(t.seconds) * 1e3;
        let (gflop, mb) = (per(t.flops) * 1e-9, per(t.bytes) * 1e-6);
        let gbs = if part == &Part::ReadBack {
            PCIE_GBS
        } else {
            peaks.gbs
        };
        let roof = (mb * 1e-3 / gbs).max(gflop * 1e-3 / peaks.tflops) * 1e3;
        let rate = |x: f64| match ms > 0.0 && x > 0.0 {
            true => format!("{:.1}", x / ms),
            false => "-".into(),
        };
        let times = match roof > 0.0 {
            true => format!("{:.0}", ms / roof),
            false => "-".into(),
        };
        println!(
            "|   {} | {ms:.3} | {:.0} % | {gflop:.3} | {mb:.1} | {} | {} | {roof:.4} | {times} |",
            part.name(),
            100.0 * t.seconds / total.max(f64::MIN_POSITIVE),
            rate(mb),
            rate(gflop),
        );
    }
}
