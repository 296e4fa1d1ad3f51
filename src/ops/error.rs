//! [`OpsError`]: how a GPU library call of `ops` fails (feature `cuda`: the CUDA driver,
//! cuBLAS, cuDNN, cubecl's memory), as a value the internal functions return and propagate
//! with `?`. Where a caller can do without the library it falls back instead (cuDNN that does
//! not start: the convolutions run as im2col, `cuda/mod.rs`).
//!
//! burn's backend operations ([`super::NetOps`]'s methods, burn's `Operation::execute` of a
//! recorded custom operation) return no `Result`: a failed GPU operation there can only stop
//! the caller. [`OpsError::raise`] is the single place `ops` panics for one, naming the
//! operation and the library's status, as burn's own kernels panic on a device error. On
//! cubecl's device thread, where a panic would be caught and only logged by cubecl (and the
//! operation's output, never written, read as a result), [`OpsError::abort`] ends the process
//! instead, as it did before. (Broken contracts of the callers, such as mismatched shapes,
//! stay assertions, documented under each function's `# Panics`.)

/// A failed GPU library call of `ops` (see the module doc).
#[derive(Debug, thiserror::Error)]
pub enum OpsError {
    /// A library call returned an error: the library (`CUDA driver`, `cuBLAS`, `cuDNN`,
    /// `cubecl`), what was asked of it, and its status as the library reports it.
    #[error("{library} {what}: {status}")]
    Call {
        /// The library: `CUDA driver`, `cuBLAS`, `cuDNN` or `cubecl`.
        library: &'static str,
        /// What the call was for (`handle`, `stream`, `convolution`, ...).
        what: String,
        /// The library's status (its error, debug-formatted).
        status: String,
    },
    /// A size does not fit the integer type a library takes it as.
    #[error("{what} {value} does not fit {ty}")]
    Size {
        /// Which size.
        what: &'static str,
        /// Its value.
        value: usize,
        /// The library's type (`i32`, `u32`).
        ty: &'static str,
    },
    /// cuDNN timed no algorithm that runs (deterministic, for the gradients) for a shape.
    #[error("cuDNN has no {pass} algorithm for [B, H, W, C_in, C_out] = {dims:?}")]
    NoAlgorithm {
        /// The pass: forward, data gradient or filter gradient.
        pass: &'static str,
        /// The convolution's sizes.
        dims: [usize; 5],
    },
    /// A read back ([`super::NetOps::read_ahead`]) was not queued by cubecl's device thread
    /// in time.
    #[error("the read was not queued within {0:?}")]
    NotQueued(std::time::Duration),
}

impl OpsError {
    /// [`OpsError::Call`] of the CUDA driver.
    pub fn driver(what: impl Into<String>, status: impl std::fmt::Debug) -> Self {
        Self::call("CUDA driver", what, status)
    }

    /// [`OpsError::Call`] of cuBLAS.
    pub fn cublas(what: impl Into<String>, status: impl std::fmt::Debug) -> Self {
        Self::call("cuBLAS", what, status)
    }

    /// [`OpsError::Call`] of cuDNN.
    pub fn cudnn(what: impl Into<String>, status: impl std::fmt::Debug) -> Self {
        Self::call("cuDNN", what, status)
    }

    /// [`OpsError::Call`] of cubecl (its memory, its kernels).
    pub fn cubecl(what: impl Into<String>, status: impl std::fmt::Debug) -> Self {
        Self::call("cubecl", what, status)
    }

    fn call(library: &'static str, what: impl Into<String>, status: impl std::fmt::Debug) -> Self {
        Self::Call {
            library,
            what: what.into(),
            status: format!("{status:?}"),
        }
    }

    /// `value` as the `i32` a library takes (`what` names it).
    ///
    /// # Errors
    /// [`OpsError::Size`] when it does not fit.
    pub fn fit_i32(what: &'static str, value: usize) -> Result<i32, Self> {
        i32::try_from(value).map_err(|_| Self::Size {
            what,
            value,
            ty: "i32",
        })
    }

    /// `value` as the `u32` a kernel takes (`what` names it).
    ///
    /// # Errors
    /// [`OpsError::Size`] when it does not fit.
    pub fn fit_u32(what: &'static str, value: usize) -> Result<u32, Self> {
        u32::try_from(value).map_err(|_| Self::Size {
            what,
            value,
            ty: "u32",
        })
    }

    /// Stops the caller: the single panic point of `ops` for a failed GPU operation, where
    /// burn's infallible backend API leaves no error to return (see the module doc). The
    /// message names `operation` and the library's status.
    ///
    /// # Panics
    /// Always.
    #[track_caller]
    pub fn raise(self, operation: &str) -> ! {
        panic!("minflow ops: {operation} failed: {self}")
    }

    /// Ends the process on cubecl's device thread (see the module doc): logs `operation` and
    /// the error, prints them to stderr, and aborts.
    pub fn abort(self, operation: &str) -> ! {
        let why = format!("{operation} failed on the device thread: {self}");
        tracing::error!("{why}");
        eprintln!("minflow: {why}");
        std::process::abort()
    }
}

#[cfg(test)]
mod tests {
    use super::OpsError;

    #[test]
    fn messages_name_the_library_the_call_and_the_status() {
        let e = OpsError::cudnn("handle", "CUDNN_STATUS_NOT_INITIALIZED");
        assert_eq!(
            e.to_string(),
            "cuDNN handle: \"CUDNN_STATUS_NOT_INITIALIZED\""
        );
        let e = OpsError::fit_i32("cuBLAS dimension", 1 << 31).unwrap_err();
        assert_eq!(
            e.to_string(),
            "cuBLAS dimension 2147483648 does not fit i32"
        );
        assert_eq!(OpsError::fit_u32("channels", 7).unwrap(), 7);
    }

    #[test]
    #[should_panic(expected = "minflow ops: cuBLAS product failed: cuBLAS sgemm")]
    fn raise_panics_naming_the_operation() {
        OpsError::cublas("sgemm", 13).raise("cuBLAS product");
    }
}
