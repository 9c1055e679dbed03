//! The library's layers point one way: a module may use modules on lower
//! layers only (ARCHITECTURE.md has the map). This test reads every source
//! file under `src/`, collects its `crate::<module>` references (code only,
//! not comments) and lists every edge that points sideways or up.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Top-level modules by layer, lowest first. A module may use any module on a
/// lower layer; modules on the same layer are independent of each other.
const LAYERS: &[&[&str]] = &[
    &["frame"],
    &["math", "telemetry", "wire"],
    &["dsp"],
    &["scene"],
    &["detect"],
    &["physics"],
    &["pipeline"],
    &["calibrate", "capture", "plot"],
    &["service"],
    &["bench"],
];

fn layer_of(module: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&module))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The top-level module a file belongs to (`src/detect/cfar.rs` -> `detect`).
fn module_of(src: &Path, file: &Path) -> String {
    let rel = file.strip_prefix(src).unwrap();
    let first = rel.components().next().unwrap().as_os_str().to_string_lossy().to_string();
    first.trim_end_matches(".rs").to_string()
}

/// `crate::x` references in the code of `text` (line comments and doc comments skipped).
fn crate_references(text: &str) -> BTreeSet<String> {
    let mut refs = BTreeSet::new();
    for line in text.lines() {
        let code = match line.find("//") {
            Some(i) => &line[..i],
            None => line,
        };
        let mut rest = code;
        while let Some(i) = rest.find("crate::") {
            let after = &rest[i + "crate::".len()..];
            if let Some(group) = after.strip_prefix('{') {
                // `use crate::{a::x, b}`: the first segment of each item at depth 1.
                let mut depth = 0;
                let mut at_item_start = true;
                for (k, c) in group.char_indices() {
                    match c {
                        '{' => depth += 1,
                        '}' if depth == 0 => break,
                        '}' => depth -= 1,
                        ',' if depth == 0 => at_item_start = true,
                        c if at_item_start && depth == 0 && (c.is_ascii_alphanumeric() || c == '_') => {
                            refs.insert(identifier(&group[k..]));
                            at_item_start = false;
                        }
                        _ => {}
                    }
                }
            } else {
                let name = identifier(after);
                if !name.is_empty() {
                    refs.insert(name);
                }
            }
            rest = after;
        }
    }
    refs
}

fn identifier(text: &str) -> String {
    text.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect()
}

#[test]
fn no_module_uses_a_module_on_its_own_or_a_higher_layer() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    files.sort();
    let mut violations = Vec::new();
    let mut unknown = BTreeSet::new();
    for file in &files {
        let module = module_of(&src, file);
        if module == "main" || module == "lib" {
            continue;
        }
        let Some(own) = layer_of(&module) else {
            unknown.insert(module.clone());
            continue;
        };
        let text = std::fs::read_to_string(file).unwrap();
        for used in crate_references(&text) {
            if used == module {
                continue;
            }
            match layer_of(&used) {
                Some(l) if l < own => {}
                Some(_) => violations.push(format!(
                    "{} ({module}) uses crate::{used}",
                    file.strip_prefix(&src).unwrap().display()
                )),
                None => {
                    unknown.insert(used);
                }
            }
        }
    }
    assert!(unknown.is_empty(), "modules missing from LAYERS (add them to the map and ARCHITECTURE.md): {unknown:?}");
    assert!(violations.is_empty(), "{} edges point sideways or up:\n{}", violations.len(), violations.join("\n"));
}

#[test]
fn the_layer_map_matches_the_module_list_in_lib_rs() {
    let lib = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/lib.rs")).unwrap();
    let declared: BTreeSet<String> = lib
        .lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod "))
        .map(|m| m.trim_end_matches(';').to_string())
        .collect();
    let mapped: BTreeSet<String> = LAYERS.iter().flat_map(|l| l.iter().map(|m| m.to_string())).collect();
    assert_eq!(declared, mapped, "src/lib.rs modules vs the layer map");
}

#[test]
fn the_reference_scanner_ignores_comments_and_sees_paths() {
    let refs = crate_references("use crate::dsp::pulse; // crate::service\n/// [`crate::bench`]\nlet x = crate::math::q(1.0);\nuse crate::{frame::Frame, wire::{a, b}};");
    let refs: Vec<String> = refs.into_iter().collect();
    assert_eq!(refs, ["dsp", "frame", "math", "wire"]);
}
