//! Unpacking a job's dataset archive (an uncompressed tar, validated by the coordinator at
//! submission) into a scratch folder without trusting it again: only regular files and
//! folders, every path kept inside the destination, sizes and member count bounded. Then
//! finding the scene in it (at the root or in one folder), or the photos of an upload of plain
//! photos. [`check_dataset`] does all that and
//! loads the scene, for a coordinator to refuse at submission what a worker would refuse.

use std::io::Read;
use std::path::{Path, PathBuf};

use stylenerf_engine::scene::{LoadOptions, Scene};
use stylenerf_plan::scene_format::{
    find_photos, find_scene, DatasetFacts, MAX_SCENE_DEPTH, MIN_PHOTOS, NO_SCENE,
};

use crate::error::TaskError;

/// Bounds on what an archive may unpack to.
#[derive(Debug, Clone, Copy)]
pub struct ArchiveLimits {
    pub max_members: u64,
    pub max_total_bytes: u64,
}

impl Default for ArchiveLimits {
    /// The coordinator's default submission limits.
    fn default() -> Self {
        Self {
            max_members: 100_000,
            max_total_bytes: 2 << 30,
        }
    }
}

/// Unpacks the tar archive read from `reader` into `dest`. `name` names the archive in errors.
pub fn unpack(
    reader: impl Read,
    dest: &Path,
    name: &str,
    limits: ArchiveLimits,
) -> Result<(), TaskError> {
    let bad = |why: String| TaskError::permanent(format!("dataset archive {name}: {why}"));
    std::fs::create_dir_all(dest)
        .map_err(|e| TaskError::retryable(format!("{}: {e}", dest.display())))?;
    let mut archive = tar::Archive::new(reader);
    archive.set_preserve_permissions(false);
    archive.set_unpack_xattrs(false);
    let entries = archive
        .entries()
        .map_err(|e| bad(format!("not a tar archive: {e}")))?;
    let (mut count, mut total) = (0u64, 0u64);
    for entry in entries {
        let mut entry = entry.map_err(|e| bad(format!("corrupt tar archive: {e}")))?;
        let kind = entry.header().entry_type();
        if kind.is_pax_global_extensions() || kind.is_pax_local_extensions() {
            continue;
        }
        let path = String::from_utf8_lossy(&entry.path_bytes()).into_owned();
        if !(kind.is_file() || kind.is_dir() || kind.is_contiguous()) {
            return Err(bad(format!(
                "member {path:?}: only regular files and folders are allowed"
            )));
        }
        count += 1;
        total += entry.size();
        if count > limits.max_members || total > limits.max_total_bytes {
            return Err(bad(format!(
                "more than {} members or {} bytes",
                limits.max_members, limits.max_total_bytes
            )));
        }
        // `unpack_in` refuses absolute paths and `..`; it returns false for those.
        let inside = entry
            .unpack_in(dest)
            .map_err(|e| TaskError::retryable(format!("unpacking member {path:?}: {e}")))?;
        if !inside {
            return Err(bad(format!("member {path:?} points outside the archive")));
        }
    }
    Ok(())
}

/// The folder holding the scene, by the catalogue's rule ([`find_scene`]): `dir` itself or the
/// shallowest folder below it (two levels at most) with a scene file.
pub fn scene_root(dir: &Path) -> Result<PathBuf, TaskError> {
    let files = relative_files(dir);
    let (_, marker) = find_scene(files.iter().map(String::as_str))
        .ok_or_else(|| TaskError::permanent(format!("dataset archive: {NO_SCENE}")))?;
    Ok(dir.join(marker).parent().unwrap_or(dir).to_path_buf())
}

/// The folder holding the photos of an unpacked upload of plain photos, by the catalogue's
/// rule ([`find_photos`]).
pub fn photos_root(dir: &Path) -> Result<PathBuf, TaskError> {
    let files = relative_files(dir);
    match find_photos(files.iter().map(String::as_str)) {
        Some((folder, n)) if n >= MIN_PHOTOS => Ok(dir.join(folder)),
        found => Err(TaskError::permanent(format!(
            "photos archive: {} PNG/JPEG photos in one folder; camera poses need at least \
             {MIN_PHOTOS}",
            found.map_or(0, |(_, n)| n)
        ))),
    }
}

/// The files of `dir` and of its folders down to [`MAX_SCENE_DEPTH`] levels, as
/// `/`-separated relative paths.
fn relative_files(dir: &Path) -> Vec<String> {
    let mut files = Vec::new();
    let mut level = vec![PathBuf::new()];
    for _ in 0..=MAX_SCENE_DEPTH {
        let mut next = Vec::new();
        for rel in &level {
            let Ok(entries) = std::fs::read_dir(dir.join(rel)) else {
                continue;
            };
            for entry in entries.filter_map(|e| e.ok()) {
                let path = rel.join(entry.file_name());
                match entry.file_type() {
                    Ok(t) if t.is_dir() => next.push(path),
                    Ok(t) if t.is_file() => files.push(path.to_string_lossy().replace('\\', "/")),
                    _ => {}
                }
            }
        }
        level = next;
    }
    files
}

/// Working resolution of [`check_dataset`]: every image and depth map is still decoded, but
/// held small.
const CHECK_SIDE: u32 = 64;

/// What a worker would make of the dataset archive at `archive`: unpacked into a temporary
/// folder beside it (the coordinator's spool folder, which the operator sized for uploads),
/// its scene found and loaded with the stages' loader and their default options (every
/// image decoded, at a small working resolution). The error names the file (relative to the
/// archive), the field and the reason. Returns what settings depend on.
pub fn check_dataset(archive: &Path) -> Result<DatasetFacts, String> {
    let beside = archive.parent().unwrap_or(Path::new("."));
    let dir = tempfile::tempdir_in(beside)
        .map_err(|e| format!("a temporary folder in {}: {e}", beside.display()))?;
    let file = std::fs::File::open(archive).map_err(|e| format!("{}: {e}", archive.display()))?;
    let loaded = unpack(
        std::io::BufReader::new(file),
        dir.path(),
        "upload",
        ArchiveLimits::default(),
    )
    .and_then(|()| scene_root(dir.path()))
    .map_err(|e| e.reason)
    .and_then(|root| {
        let options = LoadOptions {
            max_side: Some(CHECK_SIDE),
            ..LoadOptions::default()
        };
        Scene::load(&root, &options).map_err(|e| e.to_string())
    });
    // Paths in the archive, not in the temporary folder (as given, and resolved).
    let canonical = dir
        .path()
        .canonicalize()
        .unwrap_or(dir.path().to_path_buf());
    let facts = |scene: Scene| DatasetFacts {
        train_depth: scene.train.iter().any(|&i| scene.frames[i].depth.is_some()),
    };
    loaded.map(facts).map_err(|why| {
        [dir.path(), canonical.as_path()]
            .iter()
            .fold(why, |why, d| why.replace(&format!("{}/", d.display()), ""))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tar_with(entries: &[(&str, tar::EntryType, &[u8])]) -> Vec<u8> {
        let mut builder = tar::Builder::new(Vec::new());
        for (path, kind, data) in entries {
            let mut header = tar::Header::new_gnu();
            header.set_entry_type(*kind);
            header.set_size(data.len() as u64);
            header.set_mode(0o644);
            // Bypass `set_path`'s own checks to build hostile archives.
            let name = &mut header.as_gnu_mut().unwrap().name;
            name[..path.len()].copy_from_slice(path.as_bytes());
            header.set_cksum();
            builder.append(&header, *data).unwrap();
        }
        builder.into_inner().unwrap()
    }

    #[test]
    fn unpacks_and_finds_the_scene_folder() {
        let dir = tempfile_dir("ok");
        let tar = tar_with(&[
            ("lego/transforms.json", tar::EntryType::Regular, b"{}"),
            ("lego/images/a.png", tar::EntryType::Regular, b"x"),
        ]);
        unpack(&tar[..], &dir, "scene.tar", ArchiveLimits::default()).unwrap();
        assert_eq!(scene_root(&dir).unwrap(), dir.join("lego"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn refuses_links_escapes_and_missing_scenes() {
        let dir = tempfile_dir("bad");
        let link = tar_with(&[("evil", tar::EntryType::Symlink, b"")]);
        let err = unpack(&link[..], &dir, "s.tar", ArchiveLimits::default()).unwrap_err();
        assert!(
            !err.retryable && err.reason.contains("regular files"),
            "{err}"
        );
        let escape = tar_with(&[("../evil", tar::EntryType::Regular, b"x")]);
        let err = unpack(&escape[..], &dir, "s.tar", ArchiveLimits::default()).unwrap_err();
        assert!(!err.retryable && err.reason.contains("outside"), "{err}");
        assert!(!dir.parent().unwrap().join("evil").exists());
        let err = scene_root(&dir).unwrap_err();
        assert!(err.reason.contains("no scene file"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn tempfile_dir(tag: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("stylenerf-archive-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }
}
