//! `minflow launch FILE`: starts the nodes of a launch file as child processes of the
//! `minflow` binary, in the spirit of ROS 2 launch YAML (`launch:` list of `arg` and `node`
//! entries, `$(var NAME)` substitution, `NAME:=VALUE` overrides on the command line).
//!
//! ```yaml
//! launch:
//!   - arg: {name: transport, default: zenoh}
//!   - node:
//!       name: surrogate            # log prefix and handle for after/stop_after
//!       exec: node                 # a minflow subcommand
//!       args: [--model, runs/demo, --transport, $(var transport)]
//!       required: true             # when it exits, everything stops
//!       stop_after: [replay]       # SIGINT once these have exited (after `grace` seconds)
//!       grace: 2.0
//!   - node: {name: eval, exec: eval, args: [...], after: [recorder], output: plain}
//! ```
//!
//! Rules: a node starts at launch unless it names `after` nodes, then it starts once all of
//! them exited successfully (never, if one failed). Child output is printed line by line
//! with a `[name]` prefix (`output: plain` passes stdout through unprefixed). Ctrl-C or
//! SIGTERM, a `required` node exiting, or a node failing stops every running node (SIGINT,
//! then SIGKILL after 10 s). The launch exits 0 only if every node that ran exited 0 and
//! every node started; a node stopped by the launch itself counts by its own exit code.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use serde::Deserialize;

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
    /// Shown by `launch --help-args`.
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
/// `after`/`stop_after` naming unknown nodes.
pub fn load(path: &Path, overrides: &BTreeMap<String, String>) -> anyhow::Result<Vec<NodeDecl>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let file: LaunchFile =
        serde_yaml_ng::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let mut vars: BTreeMap<String, String> = BTreeMap::new();
    let mut nodes = Vec::new();
    let declared: BTreeSet<&str> = file
        .launch
        .iter()
        .filter_map(|e| e.arg.as_ref().map(|a| a.name.as_str()))
        .collect();
    if let Some(unknown) = overrides.keys().find(|k| !declared.contains(k.as_str())) {
        bail!(
            "{}: no launch argument {unknown:?} (declared: {})",
            path.display(),
            declared.iter().copied().collect::<Vec<_>>().join(", ")
        );
    }
    for entry in file.launch {
        match (entry.arg, entry.node) {
            (Some(a), None) => {
                let value = match overrides.get(&a.name).or(a.default.as_ref()) {
                    Some(v) => substitute(v, &vars)?,
                    None => bail!(
                        "launch argument {:?} has no default; give it as {}:=VALUE",
                        a.name,
                        a.name
                    ),
                };
                vars.insert(a.name, value);
            }
            (None, Some(mut n)) => {
                n.args = n
                    .args
                    .iter()
                    .map(|a| substitute(a, &vars))
                    .collect::<anyhow::Result<_>>()?;
                for v in n.env.values_mut() {
                    *v = substitute(v, &vars)?;
                }
                nodes.push(n);
            }
            _ => bail!(
                "{}: each launch entry is exactly one of `arg:` or `node:`",
                path.display()
            ),
        }
    }
    let names: BTreeSet<&str> = nodes.iter().map(|n| n.name.as_str()).collect();
    if names.len() != nodes.len() {
        bail!("{}: node names must be unique", path.display());
    }
    for n in &nodes {
        if let Some(bad) = n
            .after
            .iter()
            .chain(&n.stop_after)
            .find(|d| !names.contains(d.as_str()))
        {
            bail!("node {:?} refers to unknown node {bad:?}", n.name);
        }
    }
    if let Some(cycle) = after_cycle(&nodes) {
        bail!(
            "{}: the `after` lists form a cycle ({}): none of these nodes could ever start",
            path.display(),
            cycle.join(" -> ")
        );
    }
    Ok(nodes)
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
fn substitute(s: &str, vars: &BTreeMap<String, String>) -> anyhow::Result<String> {
    let mut out = String::new();
    let mut rest = s;
    while let Some(at) = rest.find("$(var ") {
        out.push_str(&rest[..at]);
        let tail = &rest[at + 6..];
        let end = tail
            .find(')')
            .with_context(|| format!("unclosed $(var ...) in {s:?}"))?;
        let name = tail[..end].trim();
        out.push_str(
            vars.get(name)
                .with_context(|| format!("$(var {name}) is not declared before use"))?,
        );
        rest = &tail[end + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

struct Running {
    child: Child,
    started: Instant,
    pumps: Vec<std::thread::JoinHandle<()>>,
}

/// How a node ended.
#[derive(Debug, Clone)]
pub struct NodeResult {
    /// Node name.
    pub name: String,
    /// Exit status; None if it never started.
    pub status: Option<ExitStatus>,
}

/// Starts the nodes and supervises them until all have exited. `exe` is the minflow
/// binary. Returns every node's result; the launch failed if any is not a success.
///
/// # Errors
/// A child that cannot be started.
pub fn run(nodes: &[NodeDecl], exe: &Path, stop: &AtomicBool) -> anyhow::Result<Vec<NodeResult>> {
    let mut running: BTreeMap<String, Running> = BTreeMap::new();
    let mut finished: BTreeMap<String, ExitStatus> = BTreeMap::new();
    let mut stop_sent: BTreeMap<String, Instant> = BTreeMap::new();
    let mut exited_at: BTreeMap<String, Instant> = BTreeMap::new();
    let mut shutting_down = false;
    let mut never_started: BTreeSet<String> = BTreeSet::new();
    loop {
        // Start what can start.
        if !shutting_down {
            for n in nodes {
                if running.contains_key(&n.name)
                    || finished.contains_key(&n.name)
                    || never_started.contains(&n.name)
                {
                    continue;
                }
                if n.after
                    .iter()
                    .any(|d| finished.get(d).is_some_and(|s| !s.success()))
                {
                    launch_log(&format!(
                        "{} not started: a node it waits for failed",
                        n.name
                    ));
                    never_started.insert(n.name.clone());
                    continue;
                }
                if n.after
                    .iter()
                    .all(|d| finished.get(d).is_some_and(ExitStatus::success))
                {
                    running.insert(n.name.clone(), start(n, exe)?);
                }
            }
        }
        // Reap.
        let mut exited = Vec::new();
        for (name, r) in running.iter_mut() {
            if let Some(status) = r.child.try_wait()? {
                exited.push((name.clone(), status));
            }
        }
        for (name, status) in exited {
            let r = running.remove(&name).expect("present");
            for p in r.pumps {
                let _ = p.join();
            }
            launch_log(&format!(
                "{name} exited: {status} after {:.1} s",
                r.started.elapsed().as_secs_f64()
            ));
            let decl = nodes.iter().find(|n| n.name == name).expect("declared");
            let failed = !status.success();
            if (decl.required || failed) && !shutting_down && !stop_sent.contains_key(&name) {
                launch_log(&format!(
                    "{name} {}: stopping all nodes",
                    if failed {
                        "failed"
                    } else {
                        "(required) exited"
                    }
                ));
                shutting_down = true;
            }
            exited_at.insert(name.clone(), Instant::now());
            finished.insert(name, status);
        }
        if stop.load(Ordering::Relaxed) && !shutting_down {
            launch_log("signal received: stopping all nodes");
            shutting_down = true;
        }
        // Scheduled stops.
        for n in nodes {
            if stop_sent.contains_key(&n.name)
                || !running.contains_key(&n.name)
                || n.stop_after.is_empty()
            {
                continue;
            }
            let last = n
                .stop_after
                .iter()
                .map(|d| exited_at.get(d).copied())
                .collect::<Option<Vec<_>>>();
            if let Some(times) = last {
                let latest = times.into_iter().max().expect("non-empty");
                if latest.elapsed().as_secs_f64() >= n.grace {
                    interrupt(&running[&n.name].child, &n.name);
                    stop_sent.insert(n.name.clone(), Instant::now());
                }
            }
        }
        if shutting_down {
            for (name, r) in &running {
                if !stop_sent.contains_key(name) {
                    interrupt(&r.child, name);
                    stop_sent.insert(name.clone(), Instant::now());
                }
            }
            for (name, r) in running.iter_mut() {
                if stop_sent
                    .get(name)
                    .is_some_and(|t| t.elapsed() > Duration::from_secs(10))
                {
                    launch_log(&format!("{name} did not stop within 10 s: killing it"));
                    let _ = r.child.kill();
                }
            }
        }
        let pending_start = !shutting_down
            && nodes.iter().any(|n| {
                !finished.contains_key(&n.name)
                    && !running.contains_key(&n.name)
                    && !never_started.contains(&n.name)
            });
        if running.is_empty() && !pending_start {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(nodes
        .iter()
        .map(|n| NodeResult {
            name: n.name.clone(),
            status: finished.get(&n.name).copied(),
        })
        .collect())
}

fn launch_log(msg: &str) {
    eprintln!("[launch] {msg}");
}

fn interrupt(child: &Child, name: &str) {
    launch_log(&format!("stopping {name} (SIGINT)"));
    // SAFETY: kill(2) with a pid we own and a valid signal number.
    unsafe {
        libc::kill(child.id() as libc::pid_t, libc::SIGINT);
    }
}

fn start(n: &NodeDecl, exe: &Path) -> anyhow::Result<Running> {
    let mut cmd = Command::new(exe);
    cmd.arg(&n.exec)
        .args(&n.args)
        .envs(&n.env)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut child = cmd
        .spawn()
        .with_context(|| format!("starting node {}", n.name))?;
    launch_log(&format!(
        "started {} (pid {}): minflow {} {}",
        n.name,
        child.id(),
        n.exec,
        n.args.join(" ")
    ));
    let mut pumps = Vec::new();
    let out = child.stdout.take().expect("piped");
    let err = child.stderr.take().expect("piped");
    let prefix = format!("[{}] ", n.name);
    let plain = n.output == Output::Plain;
    let p = prefix.clone();
    pumps.push(std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            let mut stdout = std::io::stdout().lock();
            let _ = if plain {
                writeln!(stdout, "{line}")
            } else {
                writeln!(stdout, "{p}{line}")
            };
        }
    }));
    pumps.push(std::thread::spawn(move || {
        for line in BufReader::new(err).lines().map_while(Result::ok) {
            // Progress bars redraw with carriage returns; keep the last state of the line.
            let line = line.rsplit('\r').next().unwrap_or_default().to_owned();
            if !line.trim().is_empty() {
                eprintln!("{prefix}{line}");
            }
        }
    }));
    Ok(Running {
        child,
        started: Instant::now(),
        pumps,
    })
}

/// Parses `name:=value` command-line overrides.
///
/// # Errors
/// An item without `:=`.
pub fn parse_overrides(items: &[String]) -> anyhow::Result<BTreeMap<String, String>> {
    items
        .iter()
        .map(|s| {
            s.split_once(":=")
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .with_context(|| format!("launch argument {s:?}: expected NAME:=VALUE"))
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
        assert!(substitute("$(var b)", &vars).is_err());
        assert!(substitute("$(var a", &vars).is_err());
        let o = parse_overrides(&["model:=runs/x".into()]).unwrap();
        assert_eq!(o["model"], "runs/x");
        assert!(parse_overrides(&["model=runs/x".into()]).is_err());
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
            let err = load(&file, &BTreeMap::new()).unwrap_err().to_string();
            assert!(err.contains("unknown node \"b\""), "{list}: {err}");
        }
    }
}
