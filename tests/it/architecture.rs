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
    &["tradeoff"],
    &["server"],
];

/// Which workspace crates each crate may depend on.
const CRATES: &[(&str, &[&str])] = &[
    ("crates/core", &[]),
    ("crates/proto", &[]),
    ("crates/sim", &["rigd-core", "rigd-proto"]),
    ("crates/process", &["rigd-core"]),
    (
        ".",
        &["rigd-core", "rigd-proto", "rigd-sim", "rigd-process"],
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
