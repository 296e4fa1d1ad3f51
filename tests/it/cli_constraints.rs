//! `minflow constraints copy`: a model gets another model's constraints block as it is, and
//! keeps the rest of its `model.json`; a source without constraints is an error that leaves
//! the target as it was.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use minflow::model::store::parse_meta;

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// `model.json` of `dir` as JSON.
fn meta(dir: &Path) -> serde_json::Value {
    crate::json(&dir.join("model.json"))
}

/// `minflow constraints copy --from FROM --model TO`.
fn copy(from: &Path, to: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(["constraints", "copy", "--from"])
        .arg(from)
        .arg("--model")
        .arg(to)
        .output()
        .unwrap()
}

#[test]
fn copy_writes_the_block_and_keeps_the_rest() {
    let source = repo("models/all-grid-mingru-small-k4-mixed");
    // The target: the shipped small model's model.json without constraints.
    let target = crate::tmp::tempdir().unwrap();
    let mut before = meta(&repo("models/all-grid-mingru-small-k4"));
    before.as_object_mut().unwrap().remove("constraints");
    let json = serde_json::to_string(&before).unwrap();
    std::fs::write(target.path().join("model.json"), json).unwrap();
    let out = copy(&source, target.path());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let after = meta(target.path());
    let block = &meta(&source)["constraints"];
    assert!(
        block.is_object() && block["pressure"].is_object(),
        "{block}"
    );
    assert_eq!(&after["constraints"], block);
    // Everything else is the target's own, as the model reads it (fields it leaves out
    // written with their defaults, as `constraints fit` writes them).
    let mut rest = after.clone();
    rest.as_object_mut().unwrap().remove("constraints");
    let read = parse_meta(&serde_json::to_string(&before).unwrap()).unwrap();
    let read: serde_json::Value =
        serde_json::from_str(&serde_json::to_string(&read).unwrap()).unwrap();
    assert_eq!(rest, read);

    // A source without constraints: an error naming it, and the target untouched.
    let out = copy(target.path(), target.path()).status;
    assert!(out.success(), "copying a model's block onto itself");
    let empty = crate::tmp::tempdir().unwrap();
    std::fs::write(
        empty.path().join("model.json"),
        serde_json::to_string(&before).unwrap(),
    )
    .unwrap();
    let out = copy(empty.path(), target.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("no constraints"),
        "{stderr}"
    );
    assert_eq!(meta(target.path()), after);
}
