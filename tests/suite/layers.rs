//! The crate's layers import only downwards (docs/architecture.md, "Layout"): a module may use the layers
//! listed before its own, never those after it, and two layers of the same rank (the solver
//! and the deep features) not each other. Checked on the sources, so a new `use` that breaks
//! the layering fails here.

use std::path::{Path, PathBuf};

/// Each top-level module of `src/` and its rank: lower ranks are further down.
const RANKS: [(&str, usize); 12] = [
    ("error", 0),
    ("read", 1),
    ("host_memory", 1),
    ("fuzz", 0),
    ("backend", 1),
    ("model", 2),
    ("solver", 3),
    ("features", 3),
    ("io", 4),
    ("eval", 5),
    ("app", 6),
    ("check", 6),
];

fn rank(module: &str) -> Option<usize> {
    RANKS.iter().find(|(m, _)| *m == module).map(|&(_, r)| r)
}

fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn modules_import_only_from_lower_layers() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    sources(&src, &mut files);
    let mut violations = Vec::new();
    let mut checked = 0;
    for file in files {
        let relative = file.strip_prefix(&src).unwrap();
        let first = relative
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy();
        let own = first.trim_end_matches(".rs").to_string();
        if own == "bin" || own == "lib" {
            continue; // the program uses the library's public API; lib.rs lists the modules
        }
        let own_rank = rank(&own).unwrap_or_else(|| panic!("src/{own} has no layer in RANKS"));
        let text = std::fs::read_to_string(&file).unwrap();
        for (n, line) in text.lines().enumerate() {
            // Comments (doc links included) name other layers without depending on them.
            if line.trim_start().starts_with("//") {
                continue;
            }
            let mut rest = line;
            while let Some(at) = rest.find("crate::") {
                rest = &rest[at + "crate::".len()..];
                let module: String = rest
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                // The re-exports at the root stand for their modules.
                let module = match module.as_str() {
                    "Backend" | "Precision" => "backend".to_string(),
                    "Error" | "Result" => "error".to_string(),
                    "Grid" | "EnergyParams" => "model".to_string(),
                    _ => module,
                };
                if module == own {
                    continue;
                }
                checked += 1;
                match rank(&module) {
                    Some(r) if r < own_rank => {}
                    _ => violations.push(format!(
                        "src/{}:{}: `{own}` uses `crate::{module}`",
                        relative.display(),
                        n + 1
                    )),
                }
            }
        }
    }
    assert!(
        checked > 50,
        "only {checked} imports found: is the scan broken?"
    );
    assert!(
        violations.is_empty(),
        "imports against the layering:\n{}",
        violations.join("\n")
    );
}
