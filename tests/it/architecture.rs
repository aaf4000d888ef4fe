//! The layer rule, checked: every top-level module of the `rigd` library
//! uses only modules of lower layers, and the workspace's crates depend on
//! each other one way. A new cycle, or a module reaching up a layer, fails
//! here (and so in CI). `docs/architecture.md` explains the layers.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::common::repo_file;

/// The library's top-level modules, lowest layer first. A module may use
/// only modules of a strictly lower layer; modules of one layer know
/// nothing of each other.
const LAYERS: &[&[&str]] = &[
    &["model"],
    &["plan", "kinematics"],
    &["schedule"],
    &["rig"],
    &["store"],
    &["engine"],
    &["postprocess"],
    &["truth"],
    &["tradeoff"],
    &["server"],
];

/// Which workspace crates each crate may depend on.
const CRATES: &[(&str, &[&str])] = &[
    ("crates/core", &[]),
    ("crates/hal", &[]),
    ("crates/proto", &[]),
    ("crates/sim", &["rigd-core", "rigd-hal", "rigd-proto"]),
    ("crates/process", &["rigd-core"]),
    (
        ".",
        &[
            "rigd-core",
            "rigd-hal",
            "rigd-proto",
            "rigd-sim",
            "rigd-process",
        ],
    ),
];

fn layer_of(module: &str) -> Option<usize> {
    LAYERS.iter().position(|layer| layer.contains(&module))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .flatten()
        .map(|e| e.path())
        .collect();
    entries.sort();
    for path in entries {
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|x| x == "rs") {
            out.push(path);
        }
    }
}

/// The top-level modules a source file names through `crate::…`, in
/// paths and in `use crate::{a, b::c}` groups.
fn crate_references(source: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let code: String = source
        .lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n");
    let mut rest = code.as_str();
    while let Some(i) = rest.find("crate::") {
        let after = &rest[i + "crate::".len()..];
        if let Some(group) = after.strip_prefix('{') {
            // Top-level names of the group: split at depth-0 commas.
            let mut depth = 0;
            let mut item = String::new();
            for c in group.chars() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        push_head(&item, &mut out);
                        item.clear();
                        continue;
                    }
                    _ => {}
                }
                item.push(c);
            }
            push_head(&item, &mut out);
        } else {
            push_head(after, &mut out);
        }
        rest = after;
    }
    out
}

fn push_head(path: &str, out: &mut BTreeSet<String>) {
    let head: String = path
        .trim_start()
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    if !head.is_empty() && head != "self" {
        out.insert(head);
    }
}

#[test]
fn modules_use_only_lower_layers() {
    let src = repo_file("src");
    let lib = std::fs::read_to_string(src.join("lib.rs")).expect("lib.rs");
    let declared: BTreeSet<String> = lib
        .lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod "))
        .map(|m| m.trim_end_matches(';').to_string())
        .collect();
    let ranked: BTreeSet<String> = LAYERS
        .iter()
        .flat_map(|l| l.iter().map(|m| m.to_string()))
        .collect();
    assert_eq!(
        declared, ranked,
        "every top-level module of src/lib.rs has a layer in LAYERS, and only those"
    );
    let mut violations = Vec::new();
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for module in &declared {
        let root = src.join(module);
        let mut files = Vec::new();
        if root.is_dir() {
            rust_files(&root, &mut files);
        } else {
            files.push(src.join(format!("{module}.rs")));
        }
        let own = layer_of(module).unwrap_or(usize::MAX);
        for file in files {
            let text = std::fs::read_to_string(&file).expect("source");
            for used in crate_references(&text) {
                if &used == module {
                    continue;
                }
                edges
                    .entry(module.clone())
                    .or_default()
                    .insert(used.clone());
                match layer_of(&used) {
                    Some(l) if l < own => {}
                    _ => violations.push(format!(
                        "{} (layer {own}, `{module}`) uses `crate::{used}` (layer {:?})",
                        file.strip_prefix(repo_file("")).unwrap_or(&file).display(),
                        layer_of(&used)
                    )),
                }
            }
        }
    }
    assert!(
        violations.is_empty(),
        "the layer rule is broken:\n{}",
        violations.join("\n")
    );
    // The rule makes the module graph acyclic; the graph is also not empty
    // (the check reads what it should).
    assert!(edges.get("server").is_some_and(|e| e.contains("engine")));
    assert!(edges.get("engine").is_some_and(|e| e.contains("rig")));
}

/// The simulator is wired in above the core: the profile and its checks,
/// plans, kinematics, schedules and the run directory know nothing of it
/// (the `[sim]` table's scene and faults are checked by `rig::sim`).
/// Processing reads everything it needs from the run (the holder from the
/// run's profile): it works on a hardware run exactly as on a simulated
/// one, and never links the simulator. Ground truth lives in `src/truth.rs`.
#[test]
fn the_core_and_processing_never_import_the_simulator() {
    let mut files = Vec::new();
    for dir in [
        "src/model",
        "src/plan",
        "src/kinematics",
        "src/schedule",
        "src/store",
        "src/engine",
        "src/postprocess",
        "crates/process/src",
    ] {
        rust_files(&repo_file(dir), &mut files);
    }
    assert!(files.len() > 40, "the check reads the core's sources");
    // Nor do they reach the simulated rig or build differently without it:
    // the command line and the daemon wire it in (`rig::Simulator`).
    let offending: Vec<String> = files
        .iter()
        .filter(|f| {
            let source = std::fs::read_to_string(f).expect("source");
            ["rigd_sim", "rig::sim", "feature = \"sim\""]
                .iter()
                .any(|name| source.contains(name))
        })
        .map(|f| f.display().to_string())
        .collect();
    assert!(
        offending.is_empty(),
        "the core or processing imports the simulator: {offending:?}"
    );
    let manifest =
        std::fs::read_to_string(repo_file("crates/process/Cargo.toml")).expect("manifest");
    assert!(
        !manifest.contains("rigd-sim"),
        "rigd-process depends on rigd-sim"
    );
}

/// The places that may name the simulator's crate: the simulated rig
/// (`rig::sim`, which re-exports what the command line and the daemon
/// name), the `rigd sim` commands, the trade-off report and the ground
/// truth, which are the simulated scene's by what they are.
const SIMULATOR_EDGE: &[&str] = &[
    "src/rig/sim/",
    "src/cli/sim.rs",
    "src/tradeoff/",
    "src/truth.rs",
];

/// Outside its edge no code of rigd imports `rigd_sim` (unit tests may).
#[test]
fn the_simulator_is_reached_only_through_its_edge() {
    let mut files = Vec::new();
    rust_files(&repo_file("src"), &mut files);
    let root = repo_file("");
    let offending: Vec<String> = files
        .iter()
        .filter_map(|f| {
            let name = f.strip_prefix(&root).unwrap_or(f).display().to_string();
            let inside = SIMULATOR_EDGE.iter().any(|edge| name.starts_with(edge));
            let source = std::fs::read_to_string(f).expect("source");
            (!inside && code_of(&source).contains("rigd_sim")).then_some(name)
        })
        .collect();
    assert!(files.len() > 100, "the check reads rigd's sources");
    assert!(
        offending.is_empty(),
        "these import the simulator outside rig::sim, cli/sim, tradeoff and truth: {offending:?}"
    );
}

#[test]
fn crates_depend_one_way() {
    for (dir, allowed) in CRATES {
        let manifest = repo_file(dir).join("Cargo.toml");
        let text = std::fs::read_to_string(&manifest).expect("Cargo.toml");
        let table: toml::Table = text.parse().expect("Cargo.toml parses");
        let deps = table
            .get("dependencies")
            .and_then(|d| d.as_table())
            .cloned()
            .unwrap_or_default();
        let used: BTreeSet<&str> = deps
            .keys()
            .map(String::as_str)
            .filter(|k| k.starts_with("rigd"))
            .collect();
        let allowed: BTreeSet<&str> = allowed.iter().copied().collect();
        assert!(
            used.is_subset(&allowed),
            "{dir} depends on {used:?}; allowed: {allowed:?}"
        );
    }
}

#[test]
fn the_reference_scanner_reads_groups_and_paths() {
    let found = crate_references(
        "use crate::{model::profile::Profile, plan::{self, Plan}};\n\
         let x = crate::store::processed::btf_dir(r); // crate::server in a comment\n",
    );
    let want: BTreeSet<String> = ["model", "plan", "store"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    assert_eq!(found, want);
}

/// The folders of the repository a doc may name a path in; a crate's
/// package name (`rigd-proto/…`) is read as a claim too, so that a path
/// written from a crate's name is caught as the wrong path it is.
const NAMED_ROOTS: &[&str] = &[
    "src",
    "tests",
    "crates",
    "docs",
    "scripts",
    "benches",
    "firmware-protocols",
    "rig-profiles",
    ".ci",
    "rigd-core",
    "rigd-proto",
    "rigd-sim",
    "rigd-process",
];

/// The documents whose paths are checked: the README, `docs/`,
/// `firmware-protocols/`, the benches' README, and the doc comments
/// (`//!`, `///`) of every Rust file.
fn documents() -> Vec<PathBuf> {
    let root = repo_file("");
    let mut out = vec![root.join("README.md"), root.join("benches/README.md")];
    let mut walk = vec![
        root.join("docs"),
        root.join("firmware-protocols"),
        root.join("src"),
        root.join("crates"),
        root.join("tests"),
        root.join("benches"),
    ];
    while let Some(dir) = walk.pop() {
        let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        for path in entries.flatten().map(|e| e.path()) {
            if path.is_dir() {
                if !path.ends_with("target") {
                    walk.push(path);
                }
            } else if path.extension().is_some_and(|x| x == "rs")
                || (path.extension().is_some_and(|x| x == "md")
                    && !out.contains(&path)
                    && !path.starts_with(root.join("src")))
            {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// The paths a document's text claims: `code spans` that start at one of
/// [`NAMED_ROOTS`], and relative Markdown link targets. A `:line` suffix
/// and an `#anchor` are cut off; globs, placeholders and URLs are not
/// claims, nor are Rust paths (`crate::…`).
fn claimed_paths(text: &str) -> Vec<(String, bool)> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find(['`', ']']) {
        let after = &rest[i + 1..];
        let (token, relative, used) = if rest[i..].starts_with('`') {
            match after.find('`') {
                Some(end) => (&after[..end], false, end + 1),
                None => break,
            }
        } else if let Some(link) = after.strip_prefix('(') {
            match link.find(')') {
                Some(end) => (&link[..end], true, end + 2),
                None => ("", false, 0),
            }
        } else {
            ("", false, 0)
        };
        rest = &after[used..];
        if token.contains("::") || token.contains("://") || token.starts_with("mailto:") {
            // A Rust path (an intra-doc link) or a URL, not a file.
            continue;
        }
        let token = token.split(['#', ':']).next().unwrap_or_default();
        let token = token.trim_end_matches('/');
        if token.is_empty() || token.contains(['*', '{', '<', '$', ' ', '…', '|']) {
            continue;
        }
        let first = token.split('/').next().unwrap_or_default();
        if relative || (token.contains('/') && NAMED_ROOTS.contains(&first)) {
            out.push((token.to_string(), relative));
        }
    }
    out
}

#[test]
fn every_path_the_docs_name_exists() {
    let root = repo_file("");
    let mut missing = Vec::new();
    let mut checked = 0;
    for doc in documents() {
        let text =
            std::fs::read_to_string(&doc).unwrap_or_else(|e| panic!("{}: {e}", doc.display()));
        let is_rust = doc.extension().is_some_and(|x| x == "rs");
        for (n, line) in text.lines().enumerate() {
            let line = if is_rust {
                let t = line.trim_start();
                match t.strip_prefix("//!").or_else(|| t.strip_prefix("///")) {
                    Some(doc_text) => doc_text,
                    None => continue,
                }
            } else {
                line
            };
            for (path, relative) in claimed_paths(line) {
                checked += 1;
                let base = if relative {
                    doc.parent().unwrap_or(&root).to_path_buf()
                } else {
                    root.clone()
                };
                if !base.join(&path).exists() {
                    missing.push(format!(
                        "{}:{}: `{path}`",
                        doc.strip_prefix(&root).unwrap_or(&doc).display(),
                        n + 1
                    ));
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "paths named in the docs that do not exist:\n{}",
        missing.join("\n")
    );
    // The scan reads what it should: the docs name many paths.
    assert!(checked > 100, "only {checked} paths found in the docs");
}

#[test]
fn the_path_scanner_reads_spans_and_links() {
    let found = claimed_paths(
        "see `src/rig/mod.rs:240-260`, `tests/it/clock.rs`, [grbl](grbl.md#wait), \
         `rigd-proto/src/modbus.rs`, `docs/x/*.svg`, `./rigd-data`, `rigd run`, \
         [site](https://example.org/a), [`Plan`](crate::plan::Plan)",
    );
    let want: Vec<(String, bool)> = vec![
        ("src/rig/mod.rs".into(), false),
        ("tests/it/clock.rs".into(), false),
        ("grbl.md".into(), true),
        ("rigd-proto/src/modbus.rs".into(), false),
    ];
    assert_eq!(found, want);
}

/// A Rust source with its comments and its unit tests cut off: test code
/// may reach anywhere in its crate.
fn code_of(source: &str) -> String {
    let mut out = String::new();
    let mut lines = source.lines().peekable();
    while let Some(line) = lines.next() {
        if line.trim() == "#[cfg(test)]"
            && lines
                .peek()
                .is_some_and(|next| next.trim_start().starts_with("mod "))
        {
            break;
        }
        out.push_str(match line.find("//") {
            Some(i) => &line[..i],
            None => line,
        });
        out.push('\n');
    }
    out
}

/// The paths a use tree names, each from its first segment: `a::{b, c::d}`
/// gives `a::b` and `a::c::d`.
fn expand_use_tree(tree: &str, prefix: &[String], out: &mut Vec<Vec<String>>) {
    let tree = tree.trim();
    let Some(open) = tree.find('{') else {
        let mut path = prefix.to_vec();
        path.extend(
            tree.split("::")
                .map(|s| s.split_whitespace().next().unwrap_or_default())
                .filter(|s| !s.is_empty() && *s != "self" && *s != "*")
                .map(str::to_string),
        );
        out.push(path);
        return;
    };
    let mut head = prefix.to_vec();
    head.extend(
        tree[..open]
            .split("::")
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(str::to_string),
    );
    let body = &tree[open + 1..tree.rfind('}').unwrap_or(tree.len())];
    let (mut depth, mut start) = (0, 0);
    for (i, c) in body.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            ',' if depth == 0 => {
                expand_use_tree(&body[start..i], &head, out);
                start = i + 1;
            }
            _ => {}
        }
    }
    if !body[start..].trim().is_empty() {
        expand_use_tree(&body[start..], &head, out);
    }
}

/// The module paths (from the crate root) that a file of module `module`
/// names through `crate::…`, `super::…` and `self::…`.
fn module_references(code: &str, module: &[String]) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let bytes = code.as_bytes();
    let mut i = 0;
    while i < code.len() {
        let rest = &code[i..];
        let starts_word = i == 0
            || !(bytes[i - 1].is_ascii_alphanumeric()
                || bytes[i - 1] == b'_'
                || bytes[i - 1] == b':');
        let root = ["crate::", "super::", "self::"]
            .into_iter()
            .find(|r| starts_word && rest.starts_with(r));
        let Some(root) = root else {
            i += rest.chars().next().map_or(1, char::len_utf8);
            continue;
        };
        // The path or use tree that starts here.
        let mut end = 0;
        let mut depth = 0;
        for (j, c) in rest.char_indices() {
            match c {
                '{' => depth += 1,
                '}' if depth == 0 => break,
                '}' => depth -= 1,
                c if depth == 0 && !(c.is_alphanumeric() || c == '_' || c == ':') => break,
                _ => {}
            }
            end = j + c.len_utf8();
        }
        let tree = &rest[..end];
        let mut base: Vec<String> = match root {
            "crate::" => Vec::new(),
            "self::" => module.to_vec(),
            _ => module[..module.len().saturating_sub(1)].to_vec(),
        };
        let mut tail = &tree[root.len()..];
        while let Some(more) = tail.strip_prefix("super::") {
            base.pop();
            tail = more;
        }
        expand_use_tree(tail, &base, &mut out);
        i += end.max(1);
    }
    out
}

/// The import loops among the files of each module of a crate: file A
/// names something of its sibling B, and B (perhaps through others) of A.
/// Each loop is given as its files' module paths.
fn import_loops(src: &Path) -> Vec<Vec<String>> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let module_of = |file: &Path| -> Vec<String> {
        let rel = file.strip_prefix(src).unwrap_or(file).with_extension("");
        let mut parts: Vec<String> = rel
            .components()
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect();
        if matches!(
            parts.last().map(String::as_str),
            Some("mod" | "lib" | "main")
        ) {
            parts.pop();
        }
        parts
    };
    let modules: BTreeSet<Vec<String>> = files.iter().map(|f| module_of(f)).collect();
    let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for file in &files {
        let module = module_of(file);
        let text =
            std::fs::read_to_string(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        for target in module_references(&code_of(&text), &module) {
            let k = module
                .iter()
                .zip(&target)
                .take_while(|(a, b)| a == b)
                .count();
            if k < module.len() && k < target.len() {
                let (from, to) = (module[..=k].to_vec(), target[..=k].to_vec());
                if modules.contains(&to) {
                    edges.entry(from).or_default().insert(to);
                }
            }
        }
    }
    // Strongly connected components of more than one module are loops.
    let nodes: Vec<Vec<String>> = edges.keys().cloned().collect();
    let reaches = |from: &Vec<String>| -> BTreeSet<Vec<String>> {
        let mut seen = BTreeSet::new();
        let mut stack = vec![from.clone()];
        while let Some(n) = stack.pop() {
            for next in edges.get(&n).into_iter().flatten() {
                if seen.insert(next.clone()) {
                    stack.push(next.clone());
                }
            }
        }
        seen
    };
    let reach: BTreeMap<&Vec<String>, BTreeSet<Vec<String>>> =
        nodes.iter().map(|n| (n, reaches(n))).collect();
    let mut loops: Vec<Vec<String>> = Vec::new();
    let mut placed = BTreeSet::new();
    for n in &nodes {
        if placed.contains(n) || !reach[n].contains(n) {
            continue;
        }
        let component: Vec<Vec<String>> = nodes
            .iter()
            .filter(|m| reach[n].contains(*m) && reach[*m].contains(n))
            .cloned()
            .collect();
        placed.extend(component.iter().cloned());
        loops.push(component.iter().map(|m| m.join("::")).collect());
    }
    loops
}

#[test]
fn no_module_has_an_import_loop_among_its_files() {
    let mut found = Vec::new();
    for src in [
        "src",
        "crates/core/src",
        "crates/proto/src",
        "crates/sim/src",
        "crates/process/src",
    ] {
        for l in import_loops(&repo_file(src)) {
            found.push(format!("{src}: {}", l.join(" ↔ ")));
        }
    }
    assert!(
        found.is_empty(),
        "import loops inside modules:\n{}",
        found.join("\n")
    );
}

#[test]
fn the_loop_finder_finds_a_loop_and_reads_use_trees() {
    let dir = tempfile::tempdir().expect("tempdir");
    let src = dir.path();
    std::fs::create_dir_all(src.join("m")).expect("mkdir");
    std::fs::write(src.join("lib.rs"), "pub mod m;\n").expect("write");
    std::fs::write(src.join("m/mod.rs"), "mod a;\nmod b;\nmod c;\n").expect("write");
    std::fs::write(
        src.join("m/a.rs"),
        "use super::b::B; // crate::m::c in a comment\n",
    )
    .expect("write");
    std::fs::write(
        src.join("m/b.rs"),
        "use crate::{m::{c::C, a}, x};\n#[cfg(test)]\nmod tests { use super::super::c::*; }\n",
    )
    .expect("write");
    std::fs::write(src.join("m/c.rs"), "pub struct C;\n").expect("write");
    assert_eq!(
        import_loops(src),
        vec![vec!["m::a".to_string(), "m::b".to_string()]]
    );
    let mut paths = Vec::new();
    expand_use_tree("m::{c::C, a as A, d::{e, f}}", &[], &mut paths);
    let want: Vec<Vec<String>> = [
        &["m", "c", "C"][..],
        &["m", "a"],
        &["m", "d", "e"],
        &["m", "d", "f"],
    ]
    .iter()
    .map(|p| p.iter().map(|s| s.to_string()).collect())
    .collect();
    assert_eq!(paths, want);
}
