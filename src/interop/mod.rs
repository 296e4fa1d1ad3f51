//! Datasets in and out of minflow's bags for other tools (issue 17, part 3). Export: the
//! trajectories of bags as numpy `.npz` archives, one per trajectory ([`npz`]), for Python
//! users (`np.load`). Used by `minflow export`.

pub mod npz;

use std::path::PathBuf;

use crate::data::DataError;

/// Why an export could not be done.
#[derive(Debug, thiserror::Error)]
pub enum InteropError {
    /// Reading the input bags failed.
    #[error(transparent)]
    Data(#[from] DataError),
    /// Creating, writing or finishing an output file failed.
    #[error("writing {path}: {reason}")]
    Write {
        /// The output file.
        path: PathBuf,
        /// The underlying error.
        reason: String,
    },
}
