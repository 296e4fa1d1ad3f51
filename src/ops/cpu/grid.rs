//! The grid model's inference glue on the CPU, one pass each: the grid channels from P2G's
//! splat, the U-Net's 2x2 average pooling and its nearest 2x upsampling (channels last).
//!
//! Why: burn composes them from narrows, divisions, concatenations along the last axis,
//! reshapes of strided views and two `mean_dim`s, each a pass that copies element by element
//! through ndarray's strided iterators. With the convolutions' parallel passes fixed
//! (`pool.rs`), these were 1.7 ms of the full-size model's 11.6 ms step on 2 cores (grid
//! channels 0.86 ms, three poolings 0.53 ms, three upsamplings 0.35 ms; timers around each
//! stage of `bench node --skip-node`). Inference only: training keeps the composed
//! operations, which autodiff differentiates.

use super::{dense, tensor, CpuTensor};
use crate::ops::composed_grid::is_wall;

/// [`NetOps::grid_channels`](crate::ops::NetOps::grid_channels) on the CPU; None for
/// operands it does not take (not f32, not rank 3, fewer than `1 + own` channels).
pub(crate) fn grid_channels(splat: &CpuTensor, n: usize, own: usize) -> Option<CpuTensor> {
    let (data, shape) = dense(splat)?;
    let [b, cells, c_s] = <[usize; 3]>::try_from(shape.as_slice()).ok()?;
    if cells != n * n || c_s < 1 + own || b * cells == 0 {
        return None;
    }
    let extra = c_s - 1 - own;
    let c = c_s + 2;
    let mut out = Vec::with_capacity(b * cells * c);
    for (k, row) in data.chunks_exact(c_s).enumerate() {
        let cell = k % cells;
        let mass = row[0];
        // burn's `clamp_min`: a NaN mass stays NaN (f32::max would return the bound).
        let divisor = if mass < 1e-6 { 1e-6 } else { mass };
        out.push(mass * 0.25);
        out.extend(row[1..1 + own].iter().map(|v| v / divisor));
        out.push(f32::from(u8::from(is_wall(cell / n, n))));
        out.push(f32::from(u8::from(is_wall(cell % n, n))));
        out.extend(row[1 + own..1 + own + extra].iter().map(|v| v / divisor));
    }
    Some(tensor(out, &[b, cells, c]))
}

/// [`NetOps::pool2`](crate::ops::NetOps::pool2) on the CPU; None for operands it does not
/// take (not f32, not rank 4, odd sides).
pub(crate) fn pool2(x: &CpuTensor) -> Option<CpuTensor> {
    let (data, shape) = dense(x)?;
    let [b, h, w, c] = <[usize; 4]>::try_from(shape.as_slice()).ok()?;
    if h % 2 != 0 || w % 2 != 0 || b * h * w * c == 0 {
        return None;
    }
    let (ho, wo) = (h / 2, w / 2);
    let mut out = vec![0f32; b * ho * wo * c];
    let at = |bb: usize, y: usize, x: usize| &data[((bb * h + y) * w + x) * c..][..c];
    for (k, dst) in out.chunks_exact_mut(c).enumerate() {
        let (bb, y, x) = (k / (ho * wo), k / wo % ho, k % wo);
        let rows = [
            at(bb, 2 * y, 2 * x),
            at(bb, 2 * y, 2 * x + 1),
            at(bb, 2 * y + 1, 2 * x),
            at(bb, 2 * y + 1, 2 * x + 1),
        ];
        // In the order of the composed pooling (the mean over x, then over y), each mean a
        // sum from 0 as ndarray's `mean_axis` takes it (so -0 + -0 gives +0 there too).
        for (i, d) in dst.iter_mut().enumerate() {
            let top = (0.0 + rows[0][i] + rows[1][i]) / 2.0;
            let bottom = (0.0 + rows[2][i] + rows[3][i]) / 2.0;
            *d = (0.0 + top + bottom) / 2.0;
        }
    }
    Some(tensor(out, &[b, ho, wo, c]))
}

/// [`NetOps::upsample2`](crate::ops::NetOps::upsample2) on the CPU; None for operands it does
/// not take (not f32, not rank 4).
pub(crate) fn upsample2(x: &CpuTensor) -> Option<CpuTensor> {
    let (data, shape) = dense(x)?;
    let [b, h, w, c] = <[usize; 4]>::try_from(shape.as_slice()).ok()?;
    if b * h * w * c == 0 {
        return None;
    }
    let mut out = Vec::with_capacity(b * 4 * h * w * c);
    for source_row in data.chunks_exact(w * c) {
        for _ in 0..2 {
            for pixel in source_row.chunks_exact(c) {
                out.extend_from_slice(pixel);
                out.extend_from_slice(pixel);
            }
        }
    }
    Some(tensor(out, &[b, 2 * h, 2 * w, c]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::composed_grid::{composed_grid_channels, composed_pool2, composed_upsample2};
    use burn::backend::NdArray;
    use burn::tensor::{Tensor, TensorData, TensorPrimitive};

    type B = NdArray<f32>;

    fn tensor_of<const D: usize>(shape: [usize; D], k: f32) -> CpuTensor {
        let n = shape.iter().product::<usize>();
        let data: Vec<f32> = (0..n).map(|i| (i as f32 * k).sin() * 3.0).collect();
        Tensor::<B, D>::from_data(TensorData::new(data, shape), &Default::default())
            .into_primitive()
            .tensor()
    }

    fn values<const D: usize>(x: CpuTensor) -> (Vec<usize>, Vec<f32>) {
        let t = Tensor::<B, D>::from_primitive(TensorPrimitive::Float(x));
        (
            t.dims().to_vec(),
            t.into_data().to_vec::<f32>().expect("f32"),
        )
    }

    /// Shape and bit patterns (so -0 differs from +0 and NaN equals itself).
    fn bits<const D: usize>(x: CpuTensor) -> (Vec<usize>, Vec<u32>) {
        let (shape, v) = values::<D>(x);
        (shape, v.into_iter().map(f32::to_bits).collect())
    }

    /// Bit for bit the composed channels, with and without the reference channels, over a
    /// batch of two and cells with no mass (mass 0 and negative sums included).
    #[test]
    fn grid_channels_equal_the_composed_ones() {
        for (n, own, extra) in [(8, 8, 0), (8, 8, 2), (12, 3, 2)] {
            let splat = tensor_of([2, n * n, 1 + own + extra], 0.731);
            // Zero the mass of every fifth cell, and make one mass NaN.
            let (shape, mut data) = values::<3>(splat);
            for cell in data.chunks_exact_mut(1 + own + extra).step_by(5) {
                cell[0] = 0.0;
            }
            data[(1 + own + extra) * 3] = f32::NAN;
            let splat = Tensor::<B, 3>::from_data(
                TensorData::new(data, [shape[0], shape[1], shape[2]]),
                &Default::default(),
            )
            .into_primitive()
            .tensor();
            let cpu = grid_channels(&splat, n, own).expect("f32, rank 3");
            let composed = composed_grid_channels::<B>(splat, n, own);
            assert_eq!(
                bits::<3>(cpu),
                bits::<3>(composed),
                "n {n} own {own} extra {extra}"
            );
        }
    }

    /// Bit for bit the composed pooling and upsampling, on a batch of two and a non-square
    /// grid.
    #[test]
    fn pool_and_upsample_equal_the_composed_ones() {
        let (shape, mut data) = values::<4>(tensor_of([2, 6, 10, 5], 0.377));
        data[..20].fill(-0.0); // a 2x2 block of negative zeros (SiLU's output far below 0)
        let x = Tensor::<B, 4>::from_data(
            TensorData::new(data, [shape[0], shape[1], shape[2], shape[3]]),
            &Default::default(),
        )
        .into_primitive()
        .tensor();
        let pooled = pool2(&x).expect("even sides");
        assert_eq!(bits::<4>(pooled), bits::<4>(composed_pool2::<B>(x.clone())));
        let up = upsample2(&x).expect("f32");
        assert_eq!(bits::<4>(up), bits::<4>(composed_upsample2::<B>(x)));
        assert!(
            pool2(&tensor_of([1, 5, 4, 2], 0.1)).is_none(),
            "odd side declined"
        );
    }
}
