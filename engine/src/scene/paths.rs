//! Resolving file paths named inside a dataset so that they can never leave the dataset
//! folder: not through absolute paths, not through `..`, not through symbolic links.

use std::path::{Component, Path, PathBuf};

use crate::{EngineError, Result};

/// The canonical form of a dataset folder.
pub(crate) fn canonical_root(root: &Path) -> Result<PathBuf> {
    let canon = root.canonicalize().map_err(|e| EngineError::io(root, e))?;
    if canon.is_dir() {
        Ok(canon)
    } else {
        Err(EngineError::dataset(root, "(path)", "not a folder"))
    }
}

/// The folder holding `file` (`.` for a bare file name).
pub(crate) fn parent_dir(file: &Path) -> &Path {
    match file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Resolves `rel`, found in `field` of `file`, inside the canonical dataset folder `root`.
/// Returns the canonical path of an existing file.
pub(crate) fn resolve(root: &Path, rel: &str, file: &Path, field: &str) -> Result<PathBuf> {
    let err = |reason: String| EngineError::dataset(file, field, reason);
    if rel.is_empty() {
        return Err(err("empty path".into()));
    }
    let lexical = normalize(&root.join(rel));
    if !lexical.starts_with(root) {
        return Err(err(format!(
            "`{rel}` points outside the dataset folder {}",
            root.display()
        )));
    }
    let canon = lexical.canonicalize().map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => err(format!("`{rel}` does not exist")),
        _ => err(format!("cannot access `{rel}`: {e}")),
    })?;
    if !canon.starts_with(root) {
        return Err(err(format!(
            "`{rel}` resolves through a symbolic link to {}, outside the dataset folder {}",
            canon.display(),
            root.display()
        )));
    }
    if !canon.is_file() {
        return Err(err(format!("`{rel}` is not a file")));
    }
    Ok(canon)
}

/// Removes `.` and resolves `..` lexically (without touching the file system).
fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other),
        }
    }
    out
}

/// A path written in a dataset, in a canonical spelling for comparing names
/// (`./images/a.png` and `images/a.png` are the same frame).
pub(crate) fn same_name_key(rel: &str) -> String {
    let p = normalize(Path::new(rel));
    p.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn name_keys_ignore_dot_components() {
        assert_eq!(same_name_key("./images/a.png"), "images/a.png");
        assert_eq!(same_name_key("images/./x/../a.png"), "images/a.png");
    }
}
