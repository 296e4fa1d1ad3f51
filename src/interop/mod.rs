//! Datasets in and out of minflow's bags for other tools. Export: the trajectories of bags
//! as numpy `.npz` archives, one per trajectory ([`npz`]), for Python users (`np.load`).
//! Used by `minflow export`. Import: HDF5 datasets of other tools as one
//! bag per trajectory — LagrangeBench's layout ([`lagrangebench`]) and the paper's
//! ([`paper`]), with what they share in [`import`]; read with the pure-Rust `hdf5-pure`, so no
//! system HDF5 library is needed. Used by `minflow import`.

pub mod import;
pub mod lagrangebench;
pub mod npz;
pub mod paper;

use std::path::PathBuf;

use crate::data::DataError;

/// Why an export could not be done.
#[derive(Debug, thiserror::Error)]
pub enum InteropError {
    /// Reading the input bags failed.
    #[error(transparent)]
    Data(#[from] DataError),
    /// The file system refused to create or write an output file (a full disk).
    #[error("writing {path}: {source}")]
    WriteIo {
        /// The output file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// Creating, writing or finishing an output file failed.
    #[error("writing {path}: {reason}")]
    Write {
        /// The output file.
        path: PathBuf,
        /// The underlying error.
        reason: String,
    },
}
