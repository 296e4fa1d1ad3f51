//! The environment switches: every environment variable minflow reads, in one typed place
//! (no other module calls `std::env::var`). minflow's own switches (`MINFLOW_*`) pick another
//! form of one operation, to compare two forms in one binary, or turn on a diagnostic; each is
//! read once, on first use, and an unknown value of an enum-like switch is reported (a
//! warning naming the valid values) and read as unset: the default. The standard variables of
//! the tools minflow works with (ROS 2, zenoh, the CUDA toolkit, mimalloc) are read through
//! plain accessors, each time they are asked, as those tools read them. `docs/guide.md`,
//! "Environment switches", lists them all; `docs/speed.md` has the measurements behind the
//! defaults.

use std::sync::OnceLock;

/// `var`'s value when it is one of `values`; None when unset, empty or not UTF-8. Any other
/// value is reported (see [`pick`]) and read as unset.
fn choice(var: &str, values: &[&'static str], default: &str) -> Option<&'static str> {
    let value = std::env::var(var).ok()?;
    pick(var, &value, values, default)
}

/// `value` of `var` when it is one of `values`, None when it is empty; any other value is
/// None too, with a warning naming the valid values and `default`, what is taken instead.
fn pick(var: &str, value: &str, values: &[&'static str], default: &str) -> Option<&'static str> {
    if value.is_empty() {
        return None;
    }
    let found = values.iter().copied().find(|v| *v == value);
    if found.is_none() {
        tracing::warn!(
            "{var}={value}: not one of {}; {default} instead",
            values.join(", ")
        );
    }
    found
}

/// Whether `var` is `values[1]` (read once into `cell`): a two-valued switch whose default is
/// `values[0]` (also what unset, empty and unknown values mean).
fn flag(cell: &'static OnceLock<bool>, var: &str, values: [&'static str; 2]) -> bool {
    *cell.get_or_init(|| choice(var, &values, values[0]) == Some(values[1]))
}

/// How the grid model's 3x3 convolutions are asked to run on CUDA (`MINFLOW_CUDA_CONV`; the
/// form taken when it is unset: [`cuda_conv`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CudaConv {
    /// `im2col`: im2col and a product (cuBLAS for the large ones), col2im in the backward,
    /// for inference and training.
    Im2col,
    /// `cudnn`: cuDNN's kernels, forward and backward (im2col with a warning where
    /// `libcudnn.so.9` does not load).
    Cudnn,
    /// `implicit`: burn-cubecl's implicit-GEMM convolution for inference, im2col for
    /// training.
    Implicit,
}

/// `MINFLOW_CUDA_CONV=im2col | cudnn | implicit` (read once): the form of the grid model's
/// 3x3 convolutions on CUDA ([`CudaConv`]). None when unset (or unknown, with a warning): the
/// default, cuDNN for inference and im2col for training where `libcudnn.so.9` loads, im2col
/// where it does not (`ops::cuda`'s `conv_form`).
pub fn cuda_conv() -> Option<CudaConv> {
    static ASKED: OnceLock<Option<CudaConv>> = OnceLock::new();
    *ASKED.get_or_init(|| {
        let values = ["im2col", "cudnn", "implicit"];
        let default = "the default (cuDNN for inference where it loads, else im2col)";
        match choice("MINFLOW_CUDA_CONV", &values, default)? {
            "cudnn" => Some(CudaConv::Cudnn),
            "implicit" => Some(CudaConv::Implicit),
            _ => Some(CudaConv::Im2col),
        }
    })
}

/// `MINFLOW_CUDA_TRANSFERS=sparse | dense` (read once): whether the grid model's
/// particle-grid transfers on CUDA take the separable dense products (`dense`) instead of
/// the sparse stencil kernels (`sparse`, the default), to compare the two in one binary
/// (docs/scale.md).
pub fn cuda_dense_transfers() -> bool {
    static DENSE: OnceLock<bool> = OnceLock::new();
    flag(&DENSE, "MINFLOW_CUDA_TRANSFERS", ["sparse", "dense"])
}

/// `MINFLOW_CUDA_ADAM=kernel | composed` (read once): whether the Adam step on CUDA is
/// composed from burn's operations (`composed`) instead of one kernel a parameter (`kernel`,
/// the default), to compare the two in one binary (docs/train_speed.md).
pub fn cuda_composed_adam() -> bool {
    static COMPOSED: OnceLock<bool> = OnceLock::new();
    flag(&COMPOSED, "MINFLOW_CUDA_ADAM", ["kernel", "composed"])
}

/// `MINFLOW_CUDA_MINRNN=kernel | composed` (read once): whether the minGRU's and minLSTM's
/// inference updates on CUDA are composed from burn's operations (`composed`) instead of one
/// kernel each (`kernel`, the default), to compare the two in one binary (docs/speed.md).
pub fn cuda_composed_minrnn() -> bool {
    static COMPOSED: OnceLock<bool> = OnceLock::new();
    flag(&COMPOSED, "MINFLOW_CUDA_MINRNN", ["kernel", "composed"])
}

/// `MINFLOW_CUDA_FRAMES=composed | kernel` (read once): whether a grid call's per-particle
/// frames (G2P, head, integration) run for inference on CUDA as one kernel (`kernel`) instead
/// of burn's operations (`composed`, the default: the kernel measured at their speed, 1-5 %
/// ahead at 10,000 particles; docs/speed.md), to compare the two in one binary.
pub fn cuda_fused_frames() -> bool {
    static FUSED: OnceLock<bool> = OnceLock::new();
    flag(&FUSED, "MINFLOW_CUDA_FRAMES", ["composed", "kernel"])
}

/// `MINFLOW_CUDA_PROJECTION=device | host` (read once): whether the projection of a CUDA
/// call runs on the host after the read-back (`host`) instead of on the device
/// (`device`, the default, where every scene of the call has only the parts the device
/// projects and the call is not pipelined), to compare the two in one binary (docs/cuda.md).
pub fn cuda_host_projection() -> bool {
    static HOST: OnceLock<bool> = OnceLock::new();
    flag(&HOST, "MINFLOW_CUDA_PROJECTION", ["device", "host"])
}

/// `MINFLOW_CUDNN_FILTER=transposed | permuted` (read once): whether training's cuDNN
/// convolutions copy the weight matrix into cuDNN's `KRSC` layout each pass (`permuted`, the
/// form before) instead of reading it in place as the filter of the transposed convolution
/// (`transposed`, the default), to compare the two in one binary (docs/train_speed.md).
pub fn cudnn_permuted_filter() -> bool {
    static PERMUTED: OnceLock<bool> = OnceLock::new();
    flag(
        &PERMUTED,
        "MINFLOW_CUDNN_FILTER",
        ["transposed", "permuted"],
    )
}

/// `MINFLOW_TRAIN_PREFETCH=on | off` (read once): whether the grid trainer prepares the next
/// batch on a thread of its own while a step runs (anything but `off`: the default) or each
/// batch only when the step loop asks for it (`off`), to compare the two (docs/train_speed.md,
/// "Where a training step's host time goes").
pub fn train_prefetch() -> bool {
    static OFF: OnceLock<bool> = OnceLock::new();
    !flag(&OFF, "MINFLOW_TRAIN_PREFETCH", ["on", "off"])
}

/// `MINFLOW_CALL_STAGES=0 | 1` (read once): whether `bench rollout` prints where a grid
/// call's wall time goes (`1`; off by default: `model::store`'s `stages`).
pub fn call_stages() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    flag(&ON, "MINFLOW_CALL_STAGES", ["0", "1"])
}

/// `MINFLOW_FEEDBACK_BYTES=N` (read once): the bytes of predicted frames a device-side
/// closed-loop rollout holds before reading them back (`0`: every call's frames through the
/// host). None when unset, empty or not a number (a warning for the last): the default,
/// `model::store::FEEDBACK_BYTES`.
pub fn feedback_bytes() -> Option<usize> {
    static BYTES: OnceLock<Option<usize>> = OnceLock::new();
    *BYTES.get_or_init(|| {
        let value = std::env::var("MINFLOW_FEEDBACK_BYTES").ok()?;
        let bytes = value.parse().ok();
        if bytes.is_none() && !value.is_empty() {
            tracing::warn!("MINFLOW_FEEDBACK_BYTES={value}: not a byte count; the default instead");
        }
        bytes
    })
}

/// `MINFLOW_HOST_PROFILE=FILE` (feature `host-profile`; read when asked, at start): the file
/// a sampling profile of every thread is written to at exit (`%p`: the process id), or None
/// (unset or not UTF-8: no profile). `cli::host_profile`.
pub fn host_profile() -> Option<String> {
    std::env::var("MINFLOW_HOST_PROFILE").ok()
}

/// Whether `MIMALLOC_PURGE_DELAY` is set (any value): mimalloc's own setting, which then
/// wins over the delay `cli::tune_allocator` would set.
pub fn mimalloc_purge_delay_set() -> bool {
    std::env::var_os("MIMALLOC_PURGE_DELAY").is_some()
}

/// Whether `CUDA_PATH` is set (any value): the CUDA toolkit's folder, whose headers NVRTC
/// compiles burn's kernels with; `--device cuda` sets it to `/usr/local/cuda` when unset and
/// that folder exists (`cli::device`).
pub fn cuda_path_set() -> bool {
    std::env::var_os("CUDA_PATH").is_some()
}

/// `ROS_DISTRO`, ROS 2's name of its distribution (`jazzy`, `kilted`, ...), or None when
/// unset or not UTF-8 (`transport::ros2`'s `distro::select`).
pub fn ros_distro() -> Option<String> {
    std::env::var("ROS_DISTRO").ok()
}

/// `ROS_DOMAIN_ID`, ROS 2's domain, as text (parsed by
/// [`crate::transport::ros2::domain_id_from_env`]).
///
/// # Errors
/// [`std::env::VarError::NotPresent`] when unset (domain 0), `NotUnicode` when not UTF-8.
pub fn ros_domain_id() -> Result<String, std::env::VarError> {
    std::env::var("ROS_DOMAIN_ID")
}

/// `ZENOH_CONFIG_OVERRIDE`, rmw_zenoh's `key=value;...` overrides of the zenoh session
/// configuration, or None when unset or not UTF-8 (`transport::ros2`'s `rmw_zenoh`).
pub fn zenoh_config_override() -> Option<String> {
    std::env::var("ZENOH_CONFIG_OVERRIDE").ok()
}

/// `ZENOH_SESSION_CONFIG_URI`, rmw_zenoh's zenoh session configuration file, or None when
/// unset or not UTF-8 (ros2-client loads the file itself; `transport::ros2`'s `rmw_zenoh`).
pub fn zenoh_session_config_uri() -> Option<String> {
    std::env::var("ZENOH_SESSION_CONFIG_URI").ok()
}

#[cfg(test)]
mod tests {
    use super::pick;

    #[test]
    fn a_known_value_is_taken_and_others_read_as_unset() {
        let values = ["im2col", "cudnn", "implicit"];
        assert_eq!(pick("V", "cudnn", &values, "d"), Some("cudnn"));
        assert_eq!(pick("V", "", &values, "d"), None, "empty reads as unset");
        assert_eq!(
            pick("V", "CUDNN", &values, "d"),
            None,
            "unknown: the default"
        );
    }

    #[test]
    fn the_guide_lists_every_switch() {
        let guide = include_str!("../docs/guide.md");
        let source = include_str!("switches.rs");
        // Every variable named here: each quoted all-caps name with an underscore.
        let names: Vec<&str> = (source.split('"').skip(1))
            .filter(|t| t.contains('_') && t.chars().all(|c| c.is_ascii_uppercase() || c == '_'))
            .collect();
        assert!(names.len() >= 15, "{names:?}");
        for name in names {
            assert!(
                guide.contains(&format!("`{name}")),
                "docs/guide.md lacks {name}"
            );
        }
    }
}
