//! The house's limits as a test (rust-analyzer's `tidy` test reads its own sources the same
//! way): every `src` file under [`FILE_LINES`] lines and opening with a `//!` paragraph,
//! every function under [`FN_LINES`], the README under [`README_LINES`] and each doc under
//! [`DOC_LINES`], environment variables read only in `src/switches.rs`, `clap` only in
//! `src/cli/` (and the binaries' `main`), no script in `docs/`, and no import cycle between
//! the files of one folder. Each failure names the file and the limit.

use std::path::{Path, PathBuf};

/// Most lines a `src` file may have.
const FILE_LINES: usize = 500;
/// Most lines a function may span, from its `fn` line to its closing brace.
const FN_LINES: usize = 80;
/// Most lines of the README.
const README_LINES: usize = 200;
/// Most lines of a page in `docs/`.
const DOC_LINES: usize = 400;
/// The one module that reads environment variables.
const SWITCHES: &str = "src/switches.rs";

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every file under `dir` with extension `ext` (any extension when empty), sorted.
fn files(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if ext.is_empty() || path.extension().is_some_and(|e| e == ext) {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// `path` relative to the crate root, `/`-separated.
fn rel(path: &Path) -> String {
    let r = path.strip_prefix(root()).unwrap_or(path);
    r.to_string_lossy().replace('\\', "/")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Panics with every problem found, one a line.
fn report(problems: Vec<String>) {
    assert!(
        problems.is_empty(),
        "tidy found {} problem(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

/// The source with comments, string and char literals blanked to spaces (line breaks
/// kept), so braces and names inside them are not counted.
fn code_only(src: &str) -> String {
    let b = src.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    let blank = |c: u8| if c == b'\n' { b'\n' } else { b' ' };
    while i < b.len() {
        let rest = &b[i..];
        if rest.starts_with(b"//") {
            while i < b.len() && b[i] != b'\n' {
                out.push(b' ');
                i += 1;
            }
        } else if rest.starts_with(b"/*") {
            let mut depth = 0;
            while i < b.len() {
                if b[i..].starts_with(b"/*") {
                    depth += 1;
                    out.extend(b"  ");
                    i += 2;
                } else if b[i..].starts_with(b"*/") {
                    depth -= 1;
                    out.extend(b"  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    out.push(blank(b[i]));
                    i += 1;
                }
            }
        } else if let Some(len) = raw_string_len(rest) {
            out.extend(rest[..len].iter().map(|&c| blank(c)));
            i += len;
        } else if b[i] == b'"' {
            out.push(b' ');
            i += 1;
            while i < b.len() && b[i] != b'"' {
                let step = if b[i] == b'\\' { 2 } else { 1 };
                for k in 0..step.min(b.len() - i) {
                    out.push(blank(b[i + k]));
                }
                i += step;
            }
            out.push(b' ');
            i += 1;
        } else if let Some(len) = char_literal_len(rest) {
            out.extend(std::iter::repeat_n(b' ', len));
            i += len;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The length of a raw string literal (`r"..."`, `r#"..."#`, `br"..."`) at the start of
/// `s`, if one starts there.
fn raw_string_len(s: &[u8]) -> Option<usize> {
    let start = if s.starts_with(b"br") {
        2
    } else if s.starts_with(b"r") {
        1
    } else {
        return None;
    };
    let hashes = s[start..].iter().take_while(|&&c| c == b'#').count();
    if s.get(start + hashes) != Some(&b'"') {
        return None;
    }
    let close: Vec<u8> = std::iter::once(b'"')
        .chain(std::iter::repeat_n(b'#', hashes))
        .collect();
    let body = start + hashes + 1;
    let end = s[body..]
        .windows(close.len())
        .position(|w| w == close.as_slice())?;
    Some(body + end + close.len())
}

/// The length of a char literal (`'x'`, `'\n'`, `'\u{..}'`) at the start of `s`; None for a
/// lifetime.
fn char_literal_len(s: &[u8]) -> Option<usize> {
    if s.first() != Some(&b'\'') {
        return None;
    }
    if s.get(1) == Some(&b'\\') {
        let end = s[2..].iter().position(|&c| c == b'\'')?;
        return Some(end + 3);
    }
    let text = std::str::from_utf8(&s[1..s.len().min(6)])
        .ok()
        .or_else(|| {
            (1..s.len().min(6))
                .rev()
                .find_map(|k| std::str::from_utf8(&s[1..k]).ok())
        })?;
    let c = text.chars().next()?;
    let len = c.len_utf8();
    (s.get(1 + len) == Some(&b'\'')).then_some(len + 2)
}

/// The functions of `src` longer than [`FN_LINES`]: `(name, first line, lines)`.
fn long_functions(src: &str) -> Vec<(String, usize, usize)> {
    let code = code_only(src);
    let lines: Vec<&str> = code.lines().collect();
    let mut out = Vec::new();
    for (start, line) in lines.iter().enumerate() {
        let Some(name) = fn_name(line) else { continue };
        let mut depth = 0i32;
        let mut opened = false;
        for (k, l) in lines.iter().enumerate().skip(start) {
            for c in l.chars() {
                match c {
                    '{' => {
                        depth += 1;
                        opened = true;
                    }
                    '}' => depth -= 1,
                    ';' if !opened && depth == 0 => break,
                    _ => {}
                }
            }
            if !opened && l.contains(';') && depth == 0 {
                break; // a declaration without a body
            }
            if opened && depth == 0 {
                let len = k - start + 1;
                if len > FN_LINES {
                    out.push((name.clone(), start + 1, len));
                }
                break;
            }
        }
    }
    out
}

/// The name of the function a line declares, if it declares one.
fn fn_name(line: &str) -> Option<String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    let at = words.iter().position(|&w| w == "fn")?;
    let before_ok = words[..at].iter().all(|w| {
        w.starts_with("pub")
            || ["const", "async", "unsafe", "extern", "\"C\"", "default"].contains(w)
    });
    let name = words.get(at + 1)?;
    let name: String = name
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    (before_ok && !name.is_empty()).then_some(name)
}

#[test]
fn source_files_and_functions_stay_within_their_limits() {
    let mut problems = Vec::new();
    for path in files(&root().join("src"), "rs") {
        let src = read(&path);
        let n = src.lines().count();
        if n > FILE_LINES {
            problems.push(format!(
                "{}: {n} lines, over the limit of {FILE_LINES}",
                rel(&path)
            ));
        }
        let first = src.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
        if !first.starts_with("//!") {
            problems.push(format!(
                "{}: does not open with a `//!` paragraph saying what it is",
                rel(&path)
            ));
        }
        for (name, line, len) in long_functions(&src) {
            problems.push(format!(
                "{}:{line}: fn {name} spans {len} lines, over the limit of {FN_LINES}",
                rel(&path)
            ));
        }
    }
    report(problems);
}

#[test]
fn the_readme_and_docs_stay_short_and_docs_hold_no_script() {
    let mut problems = Vec::new();
    let readme = read(&root().join("README.md")).lines().count();
    if readme > README_LINES {
        problems.push(format!(
            "README.md: {readme} lines, over the limit of {README_LINES}"
        ));
    }
    for path in files(&root().join("docs"), "") {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
        if ext == "md" {
            let n = read(&path).lines().count();
            if n > DOC_LINES {
                problems.push(format!(
                    "{}: {n} lines, over the limit of {DOC_LINES}",
                    rel(&path)
                ));
            }
            continue;
        }
        let script_ext = ["sh", "py", "rs", "js", "pl", "rb", "bash"].contains(&ext);
        let shebang = std::fs::read(&path).is_ok_and(|b| b.starts_with(b"#!"));
        if script_ext || shebang {
            problems.push(format!(
                "{}: a script in docs/ (scripts live in tools/)",
                rel(&path)
            ));
        }
    }
    report(problems);
}

#[test]
fn environment_variables_are_read_in_one_module_and_clap_only_in_cli() {
    let reads = ["env::var(", "env::var_os(", "env::vars(", "env::vars_os("];
    let mut problems = Vec::new();
    for path in files(&root().join("src"), "rs") {
        let r = rel(&path);
        let code = code_only(&read(&path));
        for (k, line) in code.lines().enumerate() {
            if r != SWITCHES && reads.iter().any(|p| line.contains(p)) {
                problems.push(format!(
                    "{r}:{}: reads an environment variable outside {SWITCHES}",
                    k + 1
                ));
            }
            let cli = r.starts_with("src/cli/") || r == "src/main.rs" || r.starts_with("src/bin/");
            if !cli && line.contains("clap::") {
                problems.push(format!("{r}:{}: uses clap outside src/cli/", k + 1));
            }
        }
    }
    report(problems);
}

/// The sibling modules file `src` of folder `dir` names through `super::NAME` (not mod.rs's
/// own items: a sibling is a file or folder of `dir`).
fn sibling_uses(code: &str, siblings: &[String]) -> Vec<String> {
    let mut out: Vec<String> = siblings
        .iter()
        .filter(|s| {
            code.contains(&format!("super::{s}::")) || {
                // `use super::{a, s::Item}` and `use super::{s, ...}` forms.
                code.split("super::{").skip(1).any(|group| {
                    let group = group.split('}').next().unwrap_or("");
                    group
                        .split(',')
                        .any(|item| item.trim().split("::").next() == Some(s.as_str()))
                })
            }
        })
        .cloned()
        .collect();
    out.sort();
    out
}

#[test]
fn the_files_of_a_folder_import_each_other_without_cycles() {
    let mut problems = Vec::new();
    let mut dirs: Vec<PathBuf> = files(&root().join("src"), "rs")
        .iter()
        .filter_map(|p| p.parent().map(Path::to_path_buf))
        .collect();
    dirs.dedup();
    for dir in dirs {
        let modules: Vec<(String, PathBuf)> = std::fs::read_dir(&dir)
            .unwrap()
            .filter_map(|e| {
                let p = e.ok()?.path();
                let name = p.file_stem()?.to_string_lossy().into_owned();
                let file = if p.is_dir() {
                    p.join("mod.rs")
                } else {
                    p.clone()
                };
                let rust = p.is_dir() || p.extension().is_some_and(|e| e == "rs");
                (rust && file.exists() && name != "mod" && name != "lib" && name != "main")
                    .then_some((name, file))
            })
            .collect();
        let names: Vec<String> = modules.iter().map(|m| m.0.clone()).collect();
        let edges: Vec<Vec<usize>> = modules
            .iter()
            .map(|(_, file)| {
                sibling_uses(&without_tests(&code_only(&read(file))), &names)
                    .iter()
                    .filter_map(|s| names.iter().position(|n| n == s))
                    .collect()
            })
            .collect();
        if let Some(cycle) = find_cycle(&edges) {
            let path: Vec<&str> = cycle.iter().map(|&i| names[i].as_str()).collect();
            problems.push(format!("{}: import cycle {}", rel(&dir), path.join(" -> ")));
        }
    }
    report(problems);
}

/// `code` up to its test module (`#[cfg(test)] mod ...`): a test may use what depends on
/// the file it tests without making a cycle of the library's.
fn without_tests(code: &str) -> String {
    let mut at = 0;
    while let Some(k) = code[at..].find("#[cfg(test)]") {
        let start = at + k;
        let after = code[start + 12..].trim_start();
        if after.starts_with("mod ") || after.starts_with("pub mod ") {
            return code[..start].to_owned();
        }
        at = start + 12;
    }
    code.to_owned()
}

/// A cycle of the directed graph `edges` (node -> successors) as its nodes, the first one
/// repeated at the end; None when it has none.
fn find_cycle(edges: &[Vec<usize>]) -> Option<Vec<usize>> {
    fn visit(n: usize, edges: &[Vec<usize>], state: &mut [u8], path: &mut Vec<usize>) -> bool {
        state[n] = 1;
        path.push(n);
        for &m in &edges[n] {
            if state[m] == 1 {
                let at = path.iter().position(|&p| p == m).unwrap();
                path.drain(..at);
                path.push(m);
                return true;
            }
            if state[m] == 0 && visit(m, edges, state, path) {
                return true;
            }
        }
        state[n] = 2;
        path.pop();
        false
    }
    let mut state = vec![0u8; edges.len()];
    for n in 0..edges.len() {
        let mut path = Vec::new();
        if state[n] == 0 && visit(n, edges, &mut state, &mut path) {
            return Some(path);
        }
    }
    None
}

#[test]
fn the_checks_themselves_catch_what_they_look_for() {
    let long = format!("fn big() {{\n{}}}\n", "    let _ = 1;\n".repeat(FN_LINES));
    assert_eq!(
        long_functions(&long),
        vec![("big".to_owned(), 1, FN_LINES + 2)]
    );
    let braces = "fn f() {\n    let s = \"}}}\";\n    let c = '}';\n    // }\n}\n";
    assert!(long_functions(braces).is_empty());
    assert_eq!(code_only("let s = r#\"}\"#;").matches('}').count(), 0);
    assert_eq!(
        fn_name("    pub(crate) fn go<T>(x: T) {"),
        Some("go".to_owned())
    );
    assert_eq!(fn_name("    let f = |x| x; // fn not"), None);
    let names = vec!["a".to_owned(), "b".to_owned()];
    assert_eq!(sibling_uses("use super::{b::X, c};", &names), vec!["b"]);
    assert_eq!(sibling_uses("let y = super::a::f();", &names), vec!["a"]);
    assert_eq!(find_cycle(&[vec![1], vec![0]]), Some(vec![0, 1, 0]));
    assert_eq!(find_cycle(&[vec![1], vec![]]), None);
}
