//! A network call's predictions as [`Surrogate`](super::Surrogate)'s steps hand them on:
//! read back now ([`Outs::Host`]), or on their way to the host behind the work recorded
//! after the call ([`Outs::Ahead`], [`NetOps::read_ahead`]), which the surrogate node's
//! pipelined calls wait for only after recording the next call (`batch.rs`).
//!
//! [`NetOps::read_ahead`]: crate::ops::NetOps::read_ahead

use super::StoreError;
use crate::model::DownloadError;
use crate::ops::ReadAhead;

/// How a call's predictions come back to the host.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Read {
    /// Read back before the call returns (the host waits for the device).
    Now,
    /// Read back behind the call where the backend can ([`ReadAhead`]); the caller waits.
    Ahead,
}

/// K predicted frames of `[B, N, 4]` (physical), on the host or on their way.
#[derive(Debug)]
pub(super) enum Outs {
    /// The frames, oldest first.
    Host(Vec<Vec<f32>>),
    /// One read of `shape` `[K B, N, 4]` (frame k's rows `k B..(k + 1) B`), `k` frames.
    Ahead {
        read: ReadAhead,
        k: usize,
        shape: [usize; 3],
    },
}

impl Outs {
    /// The frames on the host, oldest first (waits for a read on its way).
    ///
    /// # Errors
    /// [`StoreError::Download`] when the read failed.
    pub(super) fn wait(self) -> Result<Vec<Vec<f32>>, StoreError> {
        match self {
            Outs::Host(frames) => Ok(frames),
            Outs::Ahead { read, k, shape } => read.wait_parts(k).map_err(|e| {
                StoreError::from(DownloadError {
                    shape: shape.to_vec(),
                    source: e.into(),
                })
            }),
        }
    }
}

/// `[K B, N, 4]` values as K frames of `[B, N, 4]` (the buffer itself when K = 1).
pub(super) fn split_frames(all: Vec<f32>, k: usize) -> Vec<Vec<f32>> {
    match k {
        0 | 1 => vec![all],
        _ => {
            let per_frame = all.len() / k;
            all.chunks_exact(per_frame.max(1))
                .map(<[f32]>::to_vec)
                .collect()
        }
    }
}
