//! `MINFLOW_HOST_PROFILE=FILE` (feature `host-profile`): a sampling profile of every thread
//! of the process, for the GPU machines, which have no `perf`. pprof-rs samples on SIGPROF
//! (process CPU time, so a thread is sampled in proportion to the CPU it uses, spinning in
//! our code and our dependencies' included) at 999 Hz. Samples whose innermost frame lies in
//! libc, libgcc, libpthread or the vdso are dropped (pprof-rs's advice: unwinding from there
//! can deadlock), so time in `memcpy`, `sched_yield` or `clock_gettime` is not counted; the
//! libraries loaded later (libcuda, cuDNN, cuBLAS) are not matched by that list.
//! [`HostProfile`]'s drop writes the samples as folded stacks, one line `thread;root;...;leaf
//! COUNT` a distinct stack (Brendan Gregg's `stackcollapse` format, which flame-graph tools
//! read). `%p` in `FILE` becomes the process id, as in
//! `LLVM_PROFILE_FILE`, so that the processes `bench node` and `launch` start (which inherit
//! the variable) write a file each. Without the feature, or the variable, nothing runs.

/// The running profile; writes its file when dropped (see the module doc).
pub struct HostProfile {
    #[cfg(feature = "host-profile")]
    run: Option<(pprof::ProfilerGuard<'static>, std::path::PathBuf)>,
}

impl HostProfile {
    /// Starts profiling when `MINFLOW_HOST_PROFILE` names a file (and the feature is on).
    pub fn start() -> Self {
        #[cfg(feature = "host-profile")]
        {
            let run = crate::switches::host_profile().and_then(|path| {
                let path = path.replace("%p", &std::process::id().to_string());
                let guard = pprof::ProfilerGuardBuilder::default()
                    .frequency(999)
                    .blocklist(&["libc", "libgcc", "pthread", "vdso"])
                    .build();
                match guard {
                    Ok(guard) => Some((guard, path.into())),
                    Err(e) => {
                        tracing::warn!("MINFLOW_HOST_PROFILE: the profiler did not start: {e}");
                        None
                    }
                }
            });
            Self { run }
        }
        #[cfg(not(feature = "host-profile"))]
        Self {}
    }
}

#[cfg(feature = "host-profile")]
impl Drop for HostProfile {
    fn drop(&mut self) {
        use std::fmt::Write as _;
        let Some((guard, path)) = self.run.take() else {
            return;
        };
        let report = match guard.report().build() {
            Ok(report) => report,
            Err(e) => return tracing::warn!("MINFLOW_HOST_PROFILE: no report: {e}"),
        };
        let mut folded = String::new();
        for (frames, count) in &report.data {
            let mut line = frames.thread_name_or_id().replace([';', ' '], "_");
            // pprof-rs keeps each address's symbols innermost first, the leaf first.
            for symbols in frames.frames.iter().rev() {
                for symbol in symbols.iter().rev() {
                    line.push(';');
                    line.push_str(&symbol.name().replace([';', ' '], "_"));
                }
            }
            let _ = writeln!(folded, "{line} {count}");
        }
        if let Err(e) = std::fs::write(&path, folded) {
            tracing::warn!("MINFLOW_HOST_PROFILE: {}: {e}", path.display());
        }
    }
}
