//! Temporary folders for the tests, on a RAM file system (`/dev/shm`) where the machine has
//! one with room. The trainings checkpoint every epoch and every model save and bag
//! `sync_all`s its files; on a disk that other work keeps busy (a build beside the tests)
//! each sync waits for the disk: `train_loop`'s 12,500 epoch checkpoints took 78 s under
//! `/tmp` beside a build and 25 s under `/dev/shm`. Nothing the tests check depends on the
//! file system (the full-disk tests limit file sizes with `RLIMIT_FSIZE`, which tmpfs
//! honours). `TMPDIR`, when set, wins: the folders go where it says.

use std::path::Path;
use std::sync::OnceLock;

/// Free bytes the RAM file system must have to be used: the tests running at once write a
/// few hundred MB at most (the soak's recording is the largest, ~40 MB), so room for several
/// times that, and a small `/dev/shm` (64 MB in a default Docker container) is passed over.
const ROOM: u64 = 1 << 30;

/// A new temporary folder, removed on drop: under `/dev/shm` when that is a writable
/// folder with [`ROOM`] free and `TMPDIR` is not set, else in the system's temporary folder
/// (`tempfile::tempdir`).
///
/// # Errors
/// The folder could not be created.
pub fn tempdir() -> std::io::Result<tempfile::TempDir> {
    match ram() {
        Some(dir) => tempfile::tempdir_in(dir),
        None => crate::tmp::tempdir(),
    }
}

/// `/dev/shm` if the tests may use it (decided once per process).
fn ram() -> Option<&'static Path> {
    static RAM: OnceLock<Option<&'static Path>> = OnceLock::new();
    *RAM.get_or_init(|| {
        let dir = Path::new("/dev/shm");
        let usable = std::env::var_os("TMPDIR").is_none()
            && free_bytes(dir).is_some_and(|b| b >= ROOM)
            && tempfile::tempdir_in(dir).is_ok();
        usable.then_some(dir)
    })
}

/// Bytes an unprivileged user may still write on the file system of `dir` (statvfs).
fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let path = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    // SAFETY: statvfs is plain data; the call fills it from a NUL-terminated path.
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    let ok = unsafe { libc::statvfs(path.as_ptr(), &mut s) } == 0;
    ok.then(|| u64::from(s.f_bavail) * u64::from(s.f_frsize))
}
