//! Reading a launch file: its YAML form ([`LaunchFile`]), `$(var NAME)` substitution,
//! `NAME:=VALUE` overrides, and the checks that every node can start (unique names, known
//! `after`/`stop_after` nodes, no `after` cycle). Output: the nodes to run, for
//! [`super::run`].

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::LaunchError;

/// A launch file: `launch:` then a list of entries.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaunchFile {
    /// Entries in order.
    pub launch: Vec<Entry>,
}

/// One entry of a launch file: a one-key map, `arg:` or `node:`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Entry {
    /// A launch argument with a default, overridable as `name:=value`.
    pub arg: Option<ArgDecl>,
    /// A node to start.
    pub node: Option<NodeDecl>,
}

/// `- arg: {name, default, description}`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArgDecl {
    /// Argument name, used as `$(var name)`.
    pub name: String,
    /// Value when not given on the command line (required when absent).
    pub default: Option<String>,
    /// What the argument is for, for readers of the file (minflow does not print it).
    #[serde(default)]
    pub description: String,
}

/// How a node's stdout is shown.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Output {
    /// Every line prefixed with `[name]`.
    #[default]
    Prefixed,
    /// stdout as is (stderr still prefixed): for tables meant to be read.
    Plain,
}

/// `- node: {...}`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeDecl {
    /// Unique name.
    pub name: String,
    /// The minflow subcommand (`node`, `replay`, `record`, `simulate`, `eval`, ...).
    pub exec: String,
    /// Its arguments (`$(var NAME)` substituted).
    #[serde(default)]
    pub args: Vec<String>,
    /// Stop the launch when this node exits.
    #[serde(default)]
    pub required: bool,
    /// Start after these nodes exited successfully.
    #[serde(default)]
    pub after: Vec<String>,
    /// Send SIGINT after these nodes exited (and `grace` seconds passed).
    #[serde(default)]
    pub stop_after: Vec<String>,
    /// Seconds between `stop_after` and the SIGINT.
    #[serde(default)]
    pub grace: f64,
    /// Start the node again whenever it exits, crashed or not (ROS 2 launch's `respawn`),
    /// until the launch stops; its exits never stop the launch.
    #[serde(default)]
    pub respawn: bool,
    /// Seconds between an exit and the respawn.
    #[serde(default)]
    pub respawn_delay: f64,
    /// Extra environment variables.
    #[serde(default)]
    pub env: BTreeMap<String, String>,
    /// stdout handling.
    #[serde(default)]
    pub output: Output,
}
/// Parses a launch file and resolves its arguments with `overrides` (`name` -> value).
///
/// # Errors
/// Unreadable or invalid YAML, unknown or missing arguments, duplicate node names,
/// `after`/`stop_after` naming unknown nodes, a cycle of `after` lists.
pub fn load(
    path: &Path,
    overrides: &BTreeMap<String, String>,
) -> Result<Vec<NodeDecl>, LaunchError> {
    let text = std::fs::read_to_string(path).map_err(|source| LaunchError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let file: LaunchFile = serde_yaml_ng::from_str(&text).map_err(|source| LaunchError::Parse {
        path: path.to_path_buf(),
        source,
    })?;
    check_overrides(path, &file, overrides)?;
    let mut vars: BTreeMap<String, String> = BTreeMap::new();
    let mut nodes = Vec::new();
    for (index, entry) in file.launch.into_iter().enumerate() {
        match (entry.arg, entry.node) {
            (Some(a), None) => {
                let value = match overrides.get(&a.name).or(a.default.as_ref()) {
                    Some(v) => substitute(v, &vars)?,
                    None => {
                        return Err(LaunchError::NoDefault {
                            path: path.to_path_buf(),
                            name: a.name,
                        })
                    }
                };
                vars.insert(a.name, value);
            }
            (None, Some(mut n)) => {
                n.args = n
                    .args
                    .iter()
                    .map(|a| substitute(a, &vars))
                    .collect::<Result<_, _>>()?;
                for v in n.env.values_mut() {
                    *v = substitute(v, &vars)?;
                }
                nodes.push(n);
            }
            _ => {
                return Err(LaunchError::BadEntry {
                    path: path.to_path_buf(),
                    index: index + 1,
                })
            }
        }
    }
    check_nodes(path, &nodes)?;
    Ok(nodes)
}

/// Every override names a declared argument.
fn check_overrides(
    path: &Path,
    file: &LaunchFile,
    overrides: &BTreeMap<String, String>,
) -> Result<(), LaunchError> {
    let declared: BTreeSet<&str> = file
        .launch
        .iter()
        .filter_map(|e| e.arg.as_ref().map(|a| a.name.as_str()))
        .collect();
    match overrides.keys().find(|k| !declared.contains(k.as_str())) {
        Some(unknown) => Err(LaunchError::UnknownArg {
            path: path.to_path_buf(),
            name: unknown.clone(),
            declared: declared.iter().map(|d| d.to_string()).collect(),
        }),
        None => Ok(()),
    }
}

/// Node names are unique, `after`/`stop_after` name declared nodes, `after` has no cycle.
fn check_nodes(path: &Path, nodes: &[NodeDecl]) -> Result<(), LaunchError> {
    let mut names: BTreeSet<&str> = BTreeSet::new();
    if let Some(twice) = nodes.iter().find(|n| !names.insert(n.name.as_str())) {
        return Err(LaunchError::DuplicateNode {
            path: path.to_path_buf(),
            name: twice.name.clone(),
        });
    }
    for n in nodes {
        for (field, value) in [("grace", n.grace), ("respawn_delay", n.respawn_delay)] {
            if !(0.0..=1e6).contains(&value) {
                return Err(LaunchError::BadSeconds {
                    path: path.to_path_buf(),
                    node: n.name.clone(),
                    field,
                    value,
                });
            }
        }
        for (list, deps) in [("after", &n.after), ("stop_after", &n.stop_after)] {
            if let Some(bad) = deps.iter().find(|d| !names.contains(d.as_str())) {
                return Err(LaunchError::UnknownNode {
                    path: path.to_path_buf(),
                    node: n.name.clone(),
                    unknown: bad.clone(),
                    list,
                });
            }
        }
    }
    match after_cycle(nodes) {
        Some(cycle) => Err(LaunchError::Cycle {
            path: path.to_path_buf(),
            cycle,
        }),
        None => Ok(()),
    }
}

/// A cycle in the `after` graph (node -> the nodes it waits for), as the names along it with
/// the first repeated at the end; `None` when every node can start. Depth-first search with
/// the three colours of Cormen et al., "Introduction to Algorithms", section 22.3.
fn after_cycle(nodes: &[NodeDecl]) -> Option<Vec<String>> {
    fn visit<'a>(
        name: &'a str,
        nodes: &'a [NodeDecl],
        state: &mut BTreeMap<&'a str, bool>, // false: on the path, true: done
        path: &mut Vec<&'a str>,
    ) -> Option<Vec<String>> {
        match state.get(name) {
            Some(true) => return None,
            Some(false) => {
                let from = path.iter().position(|n| *n == name).unwrap_or(0);
                let mut cycle: Vec<String> = path[from..].iter().map(|n| n.to_string()).collect();
                cycle.push(name.to_owned());
                return Some(cycle);
            }
            None => {}
        }
        state.insert(name, false);
        path.push(name);
        let node = nodes.iter().find(|n| n.name == name)?;
        for dep in &node.after {
            if let Some(cycle) = visit(dep, nodes, state, path) {
                return Some(cycle);
            }
        }
        path.pop();
        state.insert(name, true);
        None
    }
    let mut state = BTreeMap::new();
    nodes
        .iter()
        .find_map(|n| visit(&n.name, nodes, &mut state, &mut Vec::new()))
}

/// Replaces every `$(var NAME)` in `s`.
fn substitute(s: &str, vars: &BTreeMap<String, String>) -> Result<String, LaunchError> {
    let mut out = String::new();
    let mut rest = s;
    while let Some(at) = rest.find("$(var ") {
        out.push_str(&rest[..at]);
        let tail = &rest[at + 6..];
        let end = tail
            .find(')')
            .ok_or_else(|| LaunchError::UnclosedVar { text: s.to_owned() })?;
        let name = tail[..end].trim();
        let value = vars.get(name).ok_or_else(|| LaunchError::UndeclaredVar {
            name: name.to_owned(),
        })?;
        out.push_str(value);
        rest = &tail[end + 1..];
    }
    out.push_str(rest);
    Ok(out)
}
/// Parses `name:=value` command-line overrides.
///
/// # Errors
/// An item without `:=`.
pub fn parse_overrides(items: &[String]) -> Result<BTreeMap<String, String>, LaunchError> {
    items
        .iter()
        .map(|s| {
            s.split_once(":=")
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .ok_or_else(|| LaunchError::BadOverride { item: s.clone() })
        })
        .collect()
}

/// A bundled launch file by name (`launch NAME`): `launch_configs/NAME.yaml` under the
/// current folder, else in the source tree minflow was built from.
pub fn bundled(name: &str) -> PathBuf {
    let file = if name.ends_with(".yaml") {
        name.to_owned()
    } else {
        format!("{name}.yaml")
    };
    let here = Path::new("launch_configs").join(&file);
    if here.is_file() {
        return here;
    }
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("launch_configs")
        .join(file)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn substitution_and_overrides() {
        let vars = BTreeMap::from([("a".to_string(), "x".to_string())]);
        assert_eq!(
            substitute("--m=$(var a)/$(var a)", &vars).unwrap(),
            "--m=x/x"
        );
        assert!(matches!(
            substitute("$(var b)", &vars),
            Err(LaunchError::UndeclaredVar { name }) if name == "b"
        ));
        assert!(matches!(
            substitute("$(var a", &vars),
            Err(LaunchError::UnclosedVar { .. })
        ));
        let o = parse_overrides(&["model:=runs/x".into()]).unwrap();
        assert_eq!(o["model"], "runs/x");
        assert!(matches!(
            parse_overrides(&["model=runs/x".into()]),
            Err(LaunchError::BadOverride { item }) if item == "model=runs/x"
        ));
    }

    /// An `after` cycle is an error when the file is loaded (it used to wait forever).
    #[test]
    fn after_cycles_are_refused_at_load() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("cycle.yaml");
        let yaml = "launch:\n  - node: {name: a, exec: replay, after: [c]}\n  - node: {name: b, exec: record, after: [a]}\n  - node: {name: c, exec: eval, after: [b]}\n  - node: {name: d, exec: eval}\n";
        std::fs::write(&file, yaml).unwrap();
        let err = load(&file, &BTreeMap::new()).unwrap_err().to_string();
        assert!(err.contains("cycle (a -> c -> b -> a)"), "{err}");
        let chain = "launch:\n  - node: {name: a, exec: replay}\n  - node: {name: b, exec: record, after: [a]}\n  - node: {name: c, exec: eval, after: [a, b]}\n";
        std::fs::write(&file, chain).unwrap();
        assert_eq!(load(&file, &BTreeMap::new()).unwrap().len(), 3);
        // A node waiting for itself, and a wait for a node that does not exist.
        let own = "launch:\n  - node: {name: a, exec: replay, after: [a]}\n";
        std::fs::write(&file, own).unwrap();
        let err = load(&file, &BTreeMap::new()).unwrap_err().to_string();
        assert!(err.contains("cycle (a -> a)"), "{err}");
        for list in ["after", "stop_after"] {
            let unknown = format!("launch:\n  - node: {{name: a, exec: replay, {list}: [b]}}\n");
            std::fs::write(&file, unknown).unwrap();
            let err = load(&file, &BTreeMap::new()).unwrap_err();
            assert!(
                matches!(&err, LaunchError::UnknownNode { node, unknown, list: l, .. }
                    if node == "a" && unknown == "b" && *l == list),
                "{list}: {err}"
            );
            assert!(
                err.to_string().contains("unknown node \"b\""),
                "{list}: {err}"
            );
        }
    }

    /// Each malformed file gives the variant that names what is wrong, with the file.
    #[test]
    fn load_errors_are_structured() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("bad.yaml");
        let load_text = |yaml: &str, overrides: &[(&str, &str)]| {
            std::fs::write(&file, yaml).unwrap();
            let o = overrides
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect();
            load(&file, &o).unwrap_err()
        };
        let twice = "launch:\n  - node: {name: a, exec: replay}\n  - node: {name: a, exec: eval}\n";
        assert!(
            matches!(load_text(twice, &[]), LaunchError::DuplicateNode { name, .. } if name == "a")
        );
        let no_default = "launch:\n  - arg: {name: model}\n";
        let err = load_text(no_default, &[]);
        assert!(matches!(&err, LaunchError::NoDefault { name, .. } if name == "model"));
        assert!(err.to_string().contains("give it as model:=VALUE"), "{err}");
        let err = load_text(no_default, &[("modle", "x")]);
        assert!(
            matches!(&err, LaunchError::UnknownArg { name, declared, .. }
            if name == "modle" && declared == &["model"])
        );
        let both = "launch:\n  - arg: {name: a, default: x}\n    node: {name: a, exec: eval}\n";
        assert!(matches!(
            load_text(both, &[]),
            LaunchError::BadEntry { index: 1, .. }
        ));
        assert!(matches!(
            load_text("launch: 3\n", &[]),
            LaunchError::Parse { .. }
        ));
        let missing = dir.path().join("missing.yaml");
        let err = load(&missing, &BTreeMap::new()).unwrap_err();
        assert!(matches!(&err, LaunchError::Read { path, .. } if *path == missing));
        assert!(std::error::Error::source(&err).is_some());
    }
}
