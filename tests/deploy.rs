//! deploy/ agrees with the binary it deploys: every `STYLENERF_*` variable the manifests,
//! compose file and Dockerfiles set, and every `--option` they pass, is one that
//! `stylenerf` (coordinator, worker, health) reads. Schema checks of the same files are in
//! scripts/check-deploy.sh, which needs tools from PyPI and npm.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let path = entry.path();
        if path.is_dir() {
            files(&path, out);
        } else {
            out.push(path);
        }
    }
}

fn help(args: &[&str]) -> String {
    let output = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args(args)
        .arg("--help")
        .output()
        .unwrap();
    assert!(output.status.success(), "stylenerf {args:?} --help");
    String::from_utf8(output.stdout).unwrap()
}

/// Tokens starting with `prefix`, except shell and compose references (`$NAME`, `${NAME}`:
/// the operator's variables, not the binary's).
fn names_after(text: &str, prefix: &str, allowed: impl Fn(char) -> bool) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for (at, _) in text.match_indices(prefix) {
        if text[..at].ends_with('$') || text[..at].ends_with("${") {
            continue;
        }
        let rest = &text[at + prefix.len()..];
        let end = rest.find(|c: char| !allowed(c)).unwrap_or(rest.len());
        if end > 0 {
            names.insert(format!("{prefix}{}", &rest[..end]));
        }
    }
    names
}

#[test]
fn deploy_files_use_only_options_the_binary_has() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut paths = Vec::new();
    files(&root.join("deploy"), &mut paths);
    let helps = [
        help(&[]),
        help(&["coordinator"]),
        help(&["worker"]),
        help(&["health"]),
    ]
    .join("\n");
    let mut variables = BTreeSet::new();
    let mut options = BTreeSet::new();
    for path in &paths {
        let name = path.file_name().unwrap().to_string_lossy();
        // The example env file defines the operator's compose variables.
        if name == "compose.env.example" || name == ".hadolint.yaml" {
            continue;
        }
        let text = std::fs::read_to_string(path).unwrap();
        variables.extend(names_after(&text, "STYLENERF_", |c| {
            c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'
        }));
        // Options appear as "--name" in the exec-form lists that run stylenerf (`args:`,
        // `command:`, `CMD`, health checks); other programs' lists (MinIO's) are theirs.
        for line in text.lines() {
            let Some((_, list)) = line.split_once("[\"") else {
                continue;
            };
            let first = list.split('"').next().unwrap_or_default();
            if ["stylenerf", "coordinator", "worker", "CMD"].contains(&first) {
                options.extend(names_after(list, "\"--", |c| {
                    c.is_ascii_lowercase() || c == '-'
                }));
            }
        }
    }
    assert!(variables.len() >= 10, "{variables:?}");
    assert!(options.len() >= 3, "{options:?}");
    for variable in &variables {
        assert!(
            helps.contains(&format!("[env: {variable}")),
            "deploy/ sets {variable}, which no stylenerf command reads"
        );
    }
    for option in &options {
        let option = option.trim_start_matches('"');
        assert!(
            helps.contains(&format!("{option} ")) || helps.contains(&format!("{option}\n")),
            "deploy/ passes {option}, which no stylenerf command takes"
        );
    }
}
