//! The Python interpreter of the interop tests (`bag_python_interop`, `viz_foxglove`,
//! `interop_import_h5py`):
//! `$MINFLOW_PYTHON`; else a venv at `~/.cache/minflow/venv`, created and filled from
//! `tests/python/requirements.txt` on first use (so `cargo test --release` works on a fresh
//! machine). A test fails, never skips, when the packages cannot be had.

use std::path::Path;
use std::process::Command;

pub const INSTALL_HINT: &str = "python3 -m pip install -r tests/python/requirements.txt";

/// The modules requirements.txt provides, as one `import` statement.
const IMPORTS: &str = "import mcap, mcap_ros2, websockets, foxglove_schemas_protobuf, h5py";

/// `$MINFLOW_PYTHON`, else the project venv (created and filled from requirements.txt when
/// it lacks a package).
pub fn interpreter() -> String {
    if let Ok(python) = std::env::var("MINFLOW_PYTHON") {
        return python;
    }
    let home = std::env::var("HOME").unwrap_or_else(|_| "/tmp".to_owned());
    let venv = Path::new(&home).join(".cache/minflow/venv");
    let python = venv.join("bin/python");
    let has_packages = |p: &Path| {
        Command::new(p)
            .args(["-c", IMPORTS])
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false)
    };
    if !has_packages(&python) {
        let run = |cmd: &mut Command| {
            let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
            assert!(
                out.status.success(),
                "{cmd:?} failed; run `{INSTALL_HINT}`\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        };
        if !python.exists() {
            run(Command::new("python3").arg("-m").arg("venv").arg(&venv));
        }
        let req = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/requirements.txt");
        run(Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "-r",
            ])
            .arg(req));
    }
    python.to_string_lossy().into_owned()
}
