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
//!       respawn: true              # started again whenever it exits (ROS 2 launch's respawn)
//!       respawn_delay: 1.0         # seconds before each restart
//!   - node: {name: eval, exec: eval, args: [...], after: [recorder], output: plain}
//! ```
//!
//! Rules: a node starts at launch unless it names `after` nodes, then it starts once all of
//! them exited successfully (never, if one failed). Child output is printed line by line
//! with a `[name]` prefix (`output: plain` passes stdout through unprefixed). Ctrl-C or
//! SIGTERM, a `required` node exiting, or a node failing stops every running node (SIGINT,
//! then SIGKILL after 10 s), except a `respawn` node: whatever its exit, it is started again
//! `respawn_delay` seconds later, until the launch stops or a `stop_after` SIGINT stopped it.
//! The launch exits 0 only if every node that ran exited 0 and every node started; a node
//! stopped by the launch itself counts by its own exit code.
//!
//! Layout: `file.rs` reads and checks a launch file ([`load`]), `supervise.rs` runs its
//! nodes ([`run`]); both fail with [`LaunchError`].

mod file;
mod supervise;

use std::path::PathBuf;

pub use file::{bundled, load, parse_overrides, ArgDecl, Entry, LaunchFile, NodeDecl, Output};
pub use supervise::{run, NodeResult};

/// Every way loading or running a launch file can fail. Where another error caused it, the
/// message names what was being done and the cause is kept as the error's source.
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    /// The launch file could not be read.
    #[error("reading {}", path.display())]
    Read {
        /// The launch file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The launch file is not valid YAML of the launch format.
    #[error("parsing {}", path.display())]
    Parse {
        /// The launch file.
        path: PathBuf,
        /// The YAML error (line and column).
        #[source]
        source: serde_yaml_ng::Error,
    },
    /// A `NAME:=VALUE` override names an argument the file does not declare.
    #[error("{}: no launch argument {name:?} (declared: {})", path.display(), declared.join(", "))]
    UnknownArg {
        /// The launch file.
        path: PathBuf,
        /// The name given on the command line.
        name: String,
        /// The arguments the file declares.
        declared: Vec<String>,
    },
    /// An argument without a default was not given on the command line.
    #[error(
        "{}: launch argument {name:?} has no default; give it as {name}:=VALUE",
        path.display()
    )]
    NoDefault {
        /// The launch file.
        path: PathBuf,
        /// The argument.
        name: String,
    },
    /// An entry that is neither exactly `arg:` nor exactly `node:`.
    #[error(
        "{}: each launch entry is exactly one of `arg:` or `node:` (entry {index})",
        path.display()
    )]
    BadEntry {
        /// The launch file.
        path: PathBuf,
        /// The entry's position in the `launch:` list, from 1.
        index: usize,
    },
    /// Two nodes share a name.
    #[error("{}: node names must be unique ({name:?} is used twice)", path.display())]
    DuplicateNode {
        /// The launch file.
        path: PathBuf,
        /// The repeated name.
        name: String,
    },
    /// `after` or `stop_after` names a node the file does not declare.
    #[error("{}: node {node:?} refers to unknown node {unknown:?} in `{list}`", path.display())]
    UnknownNode {
        /// The launch file.
        path: PathBuf,
        /// The node whose list is wrong.
        node: String,
        /// The name that matches no node.
        unknown: String,
        /// `after` or `stop_after`.
        list: &'static str,
    },
    /// The `after` lists form a cycle, so none of its nodes could start.
    #[error(
        "{}: the `after` lists form a cycle ({}): none of these nodes could ever start",
        path.display(),
        cycle.join(" -> ")
    )]
    Cycle {
        /// The launch file.
        path: PathBuf,
        /// The names along the cycle, the first repeated at the end.
        cycle: Vec<String>,
    },
    /// A node's `grace` or `respawn_delay` is not a number of seconds from 0 to 1e6.
    #[error("{}: node {node:?}: `{field}` must be seconds from 0 to 1e6, not {value}", path.display())]
    BadSeconds {
        /// The launch file.
        path: PathBuf,
        /// The node.
        node: String,
        /// The field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// A `$(var ...)` substitution without its closing parenthesis.
    #[error("unclosed $(var ...) in {text:?}")]
    UnclosedVar {
        /// The text holding it.
        text: String,
    },
    /// A `$(var NAME)` naming an argument not declared before it.
    #[error("$(var {name}) is not declared before use")]
    UndeclaredVar {
        /// The argument name.
        name: String,
    },
    /// A command-line override without `:=`.
    #[error("launch argument {item:?}: expected NAME:=VALUE")]
    BadOverride {
        /// The override as given.
        item: String,
    },
    /// A node's process could not be started.
    #[error("starting node {node}")]
    Start {
        /// The node.
        node: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A node's process could not be waited for.
    #[error("waiting for node {node}")]
    Wait {
        /// The node.
        node: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
}
