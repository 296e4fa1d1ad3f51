//! The output folder of a recording (`minflow record -o OUT`): created, locked against a
//! second recorder (an OS advisory lock on [`LOCK_FILE`] holding the writer's process id),
//! and, with `--overwrite`, emptied of bags and `metadata.yaml`.

use std::path::Path;

use super::{RecordError, RecordOptions};

/// The name of the lock file a recorder holds in its output folder.
pub const LOCK_FILE: &str = ".minflow-record.lock";

/// Takes the output folder's exclusive lock (an OS advisory lock on [`LOCK_FILE`], released
/// by the kernel when the process ends, however it ends) and writes this process's id
/// into it, so a second recorder on the same folder fails naming the holder instead of
/// interleaving writes or deleting the first one's open bag.
///
/// # Errors
/// [`RecordError::Locked`]: the folder is held by another process (its id);
/// [`RecordError::File`]: the lock file could not be opened or locked.
fn lock_folder(out: &Path) -> Result<std::fs::File, RecordError> {
    use std::io::{Read, Seek, Write};
    let path = out.join(LOCK_FILE);
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|source| RecordError::File {
            path: path.clone(),
            source,
        })?;
    if let Err(e) = file.try_lock() {
        let mut holder = String::new();
        let _ = file.read_to_string(&mut holder);
        let holder = holder.trim();
        return Err(match e {
            std::fs::TryLockError::WouldBlock => RecordError::Locked {
                path: out.to_path_buf(),
                holder: if holder.is_empty() { "unknown" } else { holder }.to_owned(),
            },
            std::fs::TryLockError::Error(source) => RecordError::File { path, source },
        });
    }
    let _ = file.set_len(0);
    let _ = file.rewind();
    let _ = write!(file, "{}", std::process::id());
    let _ = file.flush();
    Ok(file)
}

/// Creates the output folder and takes its lock (held while the returned file is open);
/// with `overwrite`, deletes its bags and metadata.yaml.
///
/// # Errors
/// [`RecordError::Out`]: the folder cannot be created or read, or still holds bags;
/// [`RecordError::Locked`]: another recorder holds it.
pub(super) fn prepare_folder(options: &RecordOptions) -> Result<std::fs::File, RecordError> {
    let out = &options.out;
    let out_err = |reason: String| RecordError::Out {
        path: out.clone(),
        reason,
    };
    std::fs::create_dir_all(out).map_err(|e| out_err(e.to_string()))?;
    let lock = lock_folder(out)?;
    if options.overwrite {
        for entry in std::fs::read_dir(out)
            .map_err(|e| out_err(e.to_string()))?
            .filter_map(Result::ok)
        {
            let path = entry.path();
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if name.ends_with(".mcap") || name == "metadata.yaml" {
                std::fs::remove_file(&path)
                    .map_err(|e| out_err(format!("removing {}: {e}", path.display())))?;
            }
        }
    }
    let has_bags = std::fs::read_dir(out)
        .map_err(|e| out_err(e.to_string()))?
        .filter_map(Result::ok)
        .any(|e| e.path().extension().is_some_and(|x| x == "mcap"));
    if has_bags {
        return Err(out_err(
            "holds .mcap files already; choose a new folder or --overwrite".into(),
        ));
    }
    Ok(lock)
}
