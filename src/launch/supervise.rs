//! Running a launch: each node a child process of the `minflow` binary, its output
//! prefixed line by line, started when its `after` nodes succeeded, stopped by SIGINT
//! (`stop_after`, shutdown) and SIGKILL 10 s later; see the rules in [`super`].

use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use super::{LaunchError, NodeDecl, Output};

/// A started node: its process, when it started, the threads printing its output.
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
/// Each pass of the loop starts what can start, reaps what exited, sends the scheduled
/// (`stop_after`) and the shutdown SIGINTs, and ends when nothing runs and nothing can
/// start any more.
///
/// # Errors
/// A child that cannot be started or waited for.
pub fn run(
    nodes: &[NodeDecl],
    exe: &Path,
    stop: &AtomicBool,
) -> Result<Vec<NodeResult>, LaunchError> {
    let mut sup = Supervisor::new(nodes, exe);
    loop {
        if !sup.shutting_down {
            sup.start_ready()?;
            sup.respawn_due()?;
        }
        sup.reap()?;
        if stop.load(Ordering::Relaxed) && !sup.shutting_down {
            launch_log("signal received: stopping all nodes");
            sup.shutting_down = true;
        }
        sup.send_scheduled_stops();
        if sup.shutting_down {
            sup.stop_all();
        }
        if sup.running.is_empty() && !sup.pending_start() {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(sup.results())
}

/// What [`run`] knows about every node: running, finished (and when), sent SIGINT (and
/// when), never to start; and whether the launch is shutting down.
struct Supervisor<'a> {
    nodes: &'a [NodeDecl],
    exe: &'a Path,
    running: BTreeMap<String, Running>,
    finished: BTreeMap<String, ExitStatus>,
    exited_at: BTreeMap<String, Instant>,
    stop_sent: BTreeMap<String, Instant>,
    never_started: BTreeSet<String>,
    /// `respawn` nodes that exited, and when they start again.
    respawn_at: BTreeMap<String, Instant>,
    shutting_down: bool,
}

impl<'a> Supervisor<'a> {
    fn new(nodes: &'a [NodeDecl], exe: &'a Path) -> Self {
        Self {
            nodes,
            exe,
            running: BTreeMap::new(),
            finished: BTreeMap::new(),
            exited_at: BTreeMap::new(),
            stop_sent: BTreeMap::new(),
            never_started: BTreeSet::new(),
            respawn_at: BTreeMap::new(),
            shutting_down: false,
        }
    }

    /// Whether the node has not started yet and still may.
    fn waiting(&self, name: &str) -> bool {
        !self.running.contains_key(name)
            && !self.finished.contains_key(name)
            && !self.never_started.contains(name)
            && !self.respawn_at.contains_key(name)
    }

    /// Starts again every `respawn` node whose delay has passed.
    fn respawn_due(&mut self) -> Result<(), LaunchError> {
        let due: Vec<String> = self
            .respawn_at
            .iter()
            .filter(|(_, at)| Instant::now() >= **at)
            .map(|(name, _)| name.clone())
            .collect();
        for name in due {
            self.respawn_at.remove(&name);
            self.finished.remove(&name);
            let decl = self.decl(&name);
            launch_log(&format!("respawning {name}"));
            self.running.insert(name, start(decl, self.exe)?);
        }
        Ok(())
    }

    /// The declaration of node `name`.
    fn decl(&self, name: &str) -> &'a NodeDecl {
        self.nodes
            .iter()
            .find(|n| n.name == name)
            .expect("declared")
    }

    /// Starts every waiting node whose `after` nodes all succeeded; a node one of whose
    /// `after` nodes failed will never start.
    fn start_ready(&mut self) -> Result<(), LaunchError> {
        for n in self.nodes {
            if !self.waiting(&n.name) {
                continue;
            }
            let failed = |d: &String| self.finished.get(d).is_some_and(|s| !s.success());
            if n.after.iter().any(failed) {
                launch_log(&format!(
                    "{} not started: a node it waits for failed",
                    n.name
                ));
                self.never_started.insert(n.name.clone());
                continue;
            }
            let succeeded = |d: &String| self.finished.get(d).is_some_and(ExitStatus::success);
            if n.after.iter().all(succeeded) {
                self.running.insert(n.name.clone(), start(n, self.exe)?);
            }
        }
        Ok(())
    }

    /// Collects the nodes that exited; a failed or `required` node that the launch did not
    /// stop itself starts the shutdown.
    fn reap(&mut self) -> Result<(), LaunchError> {
        let mut exited = Vec::new();
        for (name, r) in self.running.iter_mut() {
            let status = r.child.try_wait().map_err(|source| LaunchError::Wait {
                node: name.clone(),
                source,
            })?;
            if let Some(status) = status {
                exited.push((name.clone(), status));
            }
        }
        for (name, status) in exited {
            let r = self.running.remove(&name).expect("present");
            for p in r.pumps {
                let _ = p.join();
            }
            launch_log(&format!(
                "{name} exited: {status} after {:.1} s",
                r.started.elapsed().as_secs_f64()
            ));
            let decl = self.decl(&name);
            if decl.respawn && !self.shutting_down && !self.stop_sent.contains_key(&name) {
                launch_log(&format!("{name}: respawn in {:.1} s", decl.respawn_delay));
                let delay = Duration::from_secs_f64(decl.respawn_delay);
                self.respawn_at.insert(name.clone(), Instant::now() + delay);
                // Its last status, should the launch stop before the respawn.
                self.finished.insert(name, status);
                continue;
            }
            let failed = !status.success();
            if (decl.required || failed)
                && !self.shutting_down
                && !self.stop_sent.contains_key(&name)
            {
                let how = if failed {
                    "failed"
                } else {
                    "(required) exited"
                };
                launch_log(&format!("{name} {how}: stopping all nodes"));
                self.shutting_down = true;
            }
            self.exited_at.insert(name.clone(), Instant::now());
            self.finished.insert(name, status);
        }
        Ok(())
    }

    /// SIGINT to each running node whose `stop_after` nodes have all exited at least
    /// `grace` seconds ago.
    fn send_scheduled_stops(&mut self) {
        for n in self.nodes {
            if self.stop_sent.contains_key(&n.name)
                || !self.running.contains_key(&n.name)
                || n.stop_after.is_empty()
            {
                continue;
            }
            let last = n
                .stop_after
                .iter()
                .map(|d| self.exited_at.get(d).copied())
                .collect::<Option<Vec<_>>>();
            if let Some(latest) = last.and_then(|times| times.into_iter().max()) {
                if latest.elapsed().as_secs_f64() >= n.grace {
                    interrupt(&self.running[&n.name].child, &n.name);
                    self.stop_sent.insert(n.name.clone(), Instant::now());
                }
            }
        }
    }

    /// During shutdown: SIGINT to every running node not yet sent one, SIGKILL to those
    /// still running 10 s after theirs.
    fn stop_all(&mut self) {
        for (name, r) in &self.running {
            if !self.stop_sent.contains_key(name) {
                interrupt(&r.child, name);
                self.stop_sent.insert(name.clone(), Instant::now());
            }
        }
        for (name, r) in self.running.iter_mut() {
            if self
                .stop_sent
                .get(name)
                .is_some_and(|t| t.elapsed() > Duration::from_secs(10))
            {
                launch_log(&format!("{name} did not stop within 10 s: killing it"));
                let _ = r.child.kill();
            }
        }
    }

    /// Whether some node may still start.
    fn pending_start(&self) -> bool {
        !self.shutting_down
            && (!self.respawn_at.is_empty() || self.nodes.iter().any(|n| self.waiting(&n.name)))
    }

    /// Every node's result, in declaration order.
    fn results(&self) -> Vec<NodeResult> {
        self.nodes
            .iter()
            .map(|n| NodeResult {
                name: n.name.clone(),
                status: self.finished.get(&n.name).copied(),
            })
            .collect()
    }
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

fn start(n: &NodeDecl, exe: &Path) -> Result<Running, LaunchError> {
    let mut cmd = Command::new(exe);
    cmd.arg(&n.exec)
        .args(&n.args)
        .envs(&n.env)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut child = cmd.spawn().map_err(|source| LaunchError::Start {
        node: n.name.clone(),
        source,
    })?;
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
