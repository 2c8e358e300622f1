//! ARCHITECTURE.md's layering, checked on the source: each core module refers only to core
//! modules of lower layers, and no core module uses an IO crate, the file system, the network
//! or the wall clock. (Test modules are not part of the layering and are skipped.)

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// The core, bottom up: a module may use the modules of lower layers only.
const CORE_LAYERS: &[&[&str]] = &[
    &["words", "geometry"],
    &["chain", "deformation", "stats"],
    &["filter", "vision", "alarms", "acceptance"],
    &["model"],
    &["bank"],
    &["sim"],
];

/// What the core never touches: IO, async runtimes, adapters' crates, the wall clock.
const FORBIDDEN_IN_CORE: &[&str] = &[
    "tokio::",
    "sqlx::",
    "axum::",
    "hyper::",
    "tower",
    "reqwest::",
    "rerun::",
    "std::fs",
    "std::net",
    "std::env",
    "std::io",
    "SystemTime",
    "Instant::now",
    "tracing::",
];

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// The top-level modules of `src/`.
fn modules() -> BTreeSet<String> {
    std::fs::read_dir(src())
        .expect("src/")
        .filter_map(|e| {
            let e = e.ok()?;
            let name = e.file_name().into_string().ok()?;
            if e.path().is_dir() {
                Some(name)
            } else {
                let stem = name.strip_suffix(".rs")?;
                (stem != "lib" && stem != "main").then(|| stem.to_owned())
            }
        })
        .collect()
}

/// The code of a module's files: test modules and comments left out.
fn code_of(module: &str) -> Vec<(PathBuf, String)> {
    let dir = src().join(module);
    let mut files = Vec::new();
    if dir.is_dir() {
        let mut stack = vec![dir];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).expect("module folder").flatten() {
                let p = e.path();
                if p.is_dir() {
                    stack.push(p);
                } else if p.extension().is_some_and(|x| x == "rs") {
                    files.push(p);
                }
            }
        }
    } else {
        files.push(src().join(format!("{module}.rs")));
    }
    files
        .into_iter()
        .map(|p| {
            let text = std::fs::read_to_string(&p).expect("source file");
            let before_tests = text.split("#[cfg(test)]").next().unwrap_or("");
            let code: Vec<&str> = before_tests
                .lines()
                .filter(|l| !l.trim_start().starts_with("//"))
                .collect();
            (p, code.join("\n"))
        })
        .collect()
}

/// The modules a piece of code names as `crate::m` or inside `crate::{...}`.
fn referenced(code: &str, modules: &BTreeSet<String>) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for (i, _) in code.match_indices("crate::") {
        let rest = &code[i + "crate::".len()..];
        let names: Vec<&str> = if let Some(group) = rest.strip_prefix('{') {
            let end = group.find('}').unwrap_or(group.len());
            group[..end]
                .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == ':'))
                .filter_map(|path| path.split("::").next())
                .collect()
        } else {
            let end = rest
                .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                .unwrap_or(rest.len());
            vec![&rest[..end]]
        };
        out.extend(
            names
                .into_iter()
                .filter(|n| modules.contains(*n))
                .map(str::to_owned),
        );
    }
    out
}

#[test]
fn every_core_module_is_in_a_layer_and_exists() {
    let modules = modules();
    for layer in CORE_LAYERS {
        for m in *layer {
            assert!(modules.contains(*m), "core module `{m}` is not in src/");
        }
    }
}

#[test]
fn core_modules_use_only_lower_core_layers() {
    let modules = modules();
    let mut violations = Vec::new();
    for (level, layer) in CORE_LAYERS.iter().enumerate() {
        let below: BTreeSet<&str> = CORE_LAYERS[..level]
            .iter()
            .flat_map(|l| l.iter().copied())
            .collect();
        for m in *layer {
            for (path, code) in code_of(m) {
                for r in referenced(&code, &modules) {
                    if r != *m && !below.contains(r.as_str()) {
                        violations.push(format!("{} uses `crate::{r}`", path.display()));
                    }
                }
            }
        }
    }
    assert!(
        violations.is_empty(),
        "the core must not reach up or sideways:\n{}",
        violations.join("\n")
    );
}

#[test]
fn core_modules_do_no_io() {
    let mut violations = Vec::new();
    for m in CORE_LAYERS.iter().flat_map(|l| l.iter()) {
        for (path, code) in code_of(m) {
            for f in FORBIDDEN_IN_CORE {
                if code.contains(f) {
                    violations.push(format!("{} uses `{f}`", path.display()));
                }
            }
        }
    }
    assert!(
        violations.is_empty(),
        "the core is pure:\n{}",
        violations.join("\n")
    );
}

/// The check itself can fail: an upward reference in a sample of code is found.
#[test]
fn the_reference_scan_finds_plain_and_grouped_paths() {
    let modules: BTreeSet<String> = ["config", "geometry", "store"]
        .iter()
        .map(|s| (*s).to_owned())
        .collect();
    let code = "use crate::config::Installation;\nuse crate::{geometry::Pose, store::Store};";
    let found: Vec<String> = referenced(code, &modules).into_iter().collect();
    assert_eq!(found, ["config", "geometry", "store"]);
}

/// No two top-level modules of `src/` import each other (the core's layering, above, already
/// forbids it there; this holds for the adapters too): a pair that does is one module in two
/// files, or a dependency to turn around.
#[test]
fn no_two_modules_import_each_other() {
    let modules = modules();
    let imports: std::collections::BTreeMap<String, BTreeSet<String>> = modules
        .iter()
        .map(|m| {
            let mut refs = BTreeSet::new();
            for (_, code) in code_of(m) {
                refs.extend(referenced(&code, &modules));
            }
            refs.remove(m);
            (m.clone(), refs)
        })
        .collect();
    let mutual: Vec<String> = imports
        .iter()
        .flat_map(|(a, refs)| {
            refs.iter()
                .filter(|b| a < *b && imports[*b].contains(a))
                .map(|b| format!("{a} <-> {b}"))
                .collect::<Vec<_>>()
        })
        .collect();
    assert!(
        mutual.is_empty(),
        "modules that import each other: {mutual:?}"
    );
}

/// What imports a module, over the whole of `src/`.
fn importers_of(target: &str) -> BTreeSet<String> {
    let modules = modules();
    modules
        .iter()
        .filter(|m| m.as_str() != target)
        .filter(|m| {
            code_of(m)
                .iter()
                .any(|(_, code)| referenced(code, &modules).contains(target))
        })
        .cloned()
        .collect()
}

/// The HTTP layer is an adapter at the top: only the composition root builds it. The CLI,
/// the simulator's feed and the service read and write the documents they share with it
/// through `wire`, never through `api`.
#[test]
fn only_the_composition_root_uses_the_http_layer() {
    let users = importers_of("api");
    assert_eq!(
        users,
        BTreeSet::from(["app".to_owned()]),
        "modules that use `api`"
    );
}

/// The shared documents convert to and from the core's types and nothing else: no adapter
/// (store, service, HTTP) sits under them.
#[test]
fn the_shared_documents_use_only_the_core() {
    let modules = modules();
    let core: BTreeSet<&str> = CORE_LAYERS.iter().flat_map(|l| l.iter().copied()).collect();
    let outside: BTreeSet<String> = code_of("wire")
        .iter()
        .flat_map(|(_, code)| referenced(code, &modules))
        .filter(|m| m != "wire" && !core.contains(m.as_str()))
        .collect();
    assert!(outside.is_empty(), "`wire` uses {outside:?}");
}

/// `scripts/module-graph` passes on the tree and fails (exit 1, naming the pair) on a tree
/// where two modules import each other.
#[test]
fn the_module_graph_script_fails_on_a_cycle() {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/module-graph");
    let run = |src: &Path| {
        std::process::Command::new("python3")
            .arg(&script)
            .arg(src)
            .output()
            .expect("python3 runs the script")
    };
    let out = run(&src());
    assert!(out.status.success(), "{out:?}");
    let dir = tempfile::tempdir().unwrap();
    let made = dir.path().join("src");
    std::fs::create_dir(&made).unwrap();
    std::fs::write(made.join("a.rs"), "use crate::b::B;\npub struct A;\n").unwrap();
    std::fs::write(made.join("b.rs"), "use crate::a::A;\npub struct B;\n").unwrap();
    std::fs::write(made.join("c.rs"), "use crate::a::A;\n").unwrap();
    let out = run(&made);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("mutual imports: a <-> b"), "{text}");
}
