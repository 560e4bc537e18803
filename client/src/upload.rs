//! Preparing uploads: packing a scene folder into a deterministic tar archive (sorted members,
//! zeroed timestamps and owners, symbolic links followed, hidden files left out) in a temporary
//! file, hashing files with SHA-256, and turning a file from an offset into an `AppendUpload`
//! message stream (where to resume, then chunks of at most 1 MiB read as they are sent).

use crate::error::{ClientError, Result};
use futures::Stream;
use sha2::{Digest, Sha256};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use stylenerf_plan::scene_format::{find_photos, MIN_PHOTOS};
use stylenerf_proto::v1 as pb;

/// Size of each data message (the coordinator accepts at most 1 MiB).
pub const CHUNK_BYTES: usize = 1 << 20;

/// Files that mark a scene folder (nerfstudio, NeRF-synthetic/Blender, LLFF).
const SCENE_FILES: [&str; 3] = [
    "transforms.json",
    "transforms_train.json",
    "poses_bounds.npy",
];

/// A file ready to upload: its path, size and SHA-256. Holds the temporary archive, if any,
/// until it is dropped.
#[derive(Debug)]
pub struct PreparedUpload {
    pub path: PathBuf,
    pub filename: String,
    pub size: u64,
    pub sha256: String,
    _temp: Option<tempfile::TempPath>,
}

/// Hashes everything written through it.
struct HashingWriter<W> {
    inner: W,
    hasher: Sha256,
    written: u64,
}

impl<W: Write> Write for HashingWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.written += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// Size and lower-case hex SHA-256 of a file.
pub fn hash_file(path: &Path) -> Result<(u64, String)> {
    let mut file = std::fs::File::open(path).map_err(|e| ClientError::io(path, e))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; CHUNK_BYTES];
    let mut size = 0u64;
    loop {
        let n = file.read(&mut buf).map_err(|e| ClientError::io(path, e))?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
        size += n as u64;
    }
    Ok((size, hex::encode(hasher.finalize())))
}

fn is_hidden(name: &std::ffi::OsStr) -> bool {
    name.to_string_lossy().starts_with('.')
}

/// Regular files under `dir` (following symbolic links), relative `/`-separated paths in
/// sorted order, hidden entries skipped.
fn folder_members(dir: &Path) -> Result<Vec<(String, PathBuf)>> {
    let mut out = Vec::new();
    let mut stack = vec![(String::new(), dir.to_path_buf())];
    while let Some((prefix, folder)) = stack.pop() {
        let entries = std::fs::read_dir(&folder).map_err(|e| ClientError::io(&folder, e))?;
        for entry in entries {
            let entry = entry.map_err(|e| ClientError::io(&folder, e))?;
            let name = entry.file_name();
            if is_hidden(&name) {
                continue;
            }
            let name = name.into_string().map_err(|name| {
                ClientError::InvalidInput(format!(
                    "{}: file names must be UTF-8",
                    folder.join(name).display()
                ))
            })?;
            let path = entry.path();
            let relative = if prefix.is_empty() {
                name
            } else {
                format!("{prefix}/{name}")
            };
            // `metadata` follows symbolic links: the archive holds their targets' content.
            let meta = std::fs::metadata(&path).map_err(|e| ClientError::io(&path, e))?;
            if meta.is_dir() {
                stack.push((relative, path));
            } else if meta.is_file() {
                out.push((relative, path));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// Packs the scene folder `dir` into a temporary tar archive (members relative to `dir`).
/// Fails early when no scene file is at the folder's root or one level down.
pub fn pack_scene(dir: &Path) -> Result<PreparedUpload> {
    let members = folder_members(dir)?;
    let has_scene = members.iter().any(|(relative, _)| {
        let depth = relative.matches('/').count();
        let name = relative.rsplit('/').next().unwrap_or_default();
        depth <= 1 && SCENE_FILES.contains(&name)
    });
    if !has_scene {
        return Err(ClientError::InvalidInput(format!(
            "{} is not a scene folder: expected {} at its root or in one sub-folder",
            dir.display(),
            SCENE_FILES.join(", ")
        )));
    }
    pack(dir, &members, "scene")
}

/// Packs a folder of plain photos into a temporary tar archive (members relative to `dir`).
/// Fails early when no folder in it holds the photos poses need (the catalogue's rule).
pub fn pack_photos(dir: &Path) -> Result<PreparedUpload> {
    let members = folder_members(dir)?;
    let found = find_photos(members.iter().map(|(relative, _)| relative.as_str()));
    match found {
        Some((_, n)) if n >= MIN_PHOTOS => pack(dir, &members, "photos"),
        found => Err(ClientError::InvalidInput(format!(
            "{} holds {} PNG/JPEG photos in one folder; camera poses need at least {MIN_PHOTOS}",
            dir.display(),
            found.map_or(0, |(_, n)| n)
        ))),
    }
}

/// Packs `members` of `dir` into a temporary tar archive named after the folder (`fallback`
/// when it has no usable name).
fn pack(dir: &Path, members: &[(String, PathBuf)], fallback: &str) -> Result<PreparedUpload> {
    let temp = tempfile::Builder::new()
        .prefix("stylenerf-scene-")
        .suffix(".tar")
        .tempfile()
        .map_err(|e| ClientError::io(std::env::temp_dir(), e))?;
    let (file, temp_path) = temp.into_parts();
    let writer = HashingWriter {
        inner: std::io::BufWriter::new(file),
        hasher: Sha256::new(),
        written: 0,
    };
    let mut builder = tar::Builder::new(writer);
    builder.mode(tar::HeaderMode::Deterministic);
    builder.follow_symlinks(true);
    for (relative, path) in members {
        builder
            .append_path_with_name(path, relative)
            .map_err(|e| ClientError::io(path, e))?;
    }
    let mut writer = builder
        .into_inner()
        .map_err(|e| ClientError::io(&*temp_path, e))?;
    writer
        .flush()
        .map_err(|e| ClientError::io(&*temp_path, e))?;
    let name = dir
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .filter(|n| !n.starts_with('.') && !n.is_empty())
        .unwrap_or_else(|| fallback.into());
    Ok(PreparedUpload {
        path: temp_path.to_path_buf(),
        filename: format!("{name}.tar"),
        size: writer.written,
        sha256: hex::encode(writer.hasher.finalize()),
        _temp: Some(temp_path),
    })
}

/// A file uploaded as it is (a style image, or a dataset that is already a `.tar`).
pub fn prepare_file(path: &Path) -> Result<PreparedUpload> {
    let meta = std::fs::metadata(path).map_err(|e| ClientError::io(path, e))?;
    if !meta.is_file() {
        return Err(ClientError::InvalidInput(format!(
            "{} is not a file",
            path.display()
        )));
    }
    let filename = path
        .file_name()
        .map(|n| n.to_string_lossy().trim_start_matches('.').to_string())
        .filter(|n| !n.is_empty())
        .unwrap_or_else(|| "upload".into());
    let (size, sha256) = hash_file(path)?;
    Ok(PreparedUpload {
        path: path.to_path_buf(),
        filename,
        size,
        sha256,
        _temp: None,
    })
}

/// A dataset: a scene folder is packed, a file (tar archive) is sent as it is.
pub fn prepare_dataset(path: &Path) -> Result<PreparedUpload> {
    if path.is_dir() {
        pack_scene(path)
    } else {
        prepare_file(path)
    }
}

/// Plain photos: a folder is packed, a file (a tar archive of photos, or a video) is sent as
/// it is.
pub fn prepare_photos(path: &Path) -> Result<PreparedUpload> {
    if path.is_dir() {
        pack_photos(path)
    } else {
        prepare_file(path)
    }
}

/// An `AppendUpload` request stream: where to resume, then the file from `offset` in
/// [`CHUNK_BYTES`] pieces. Read errors end the stream early (the coordinator commits what
/// arrived), and the caller learns the cause from the `io_error` slot.
pub(crate) async fn append_stream(
    upload: &PreparedUpload,
    session_id: &str,
    offset: u64,
    io_error: std::sync::Arc<std::sync::Mutex<Option<std::io::Error>>>,
) -> Result<impl Stream<Item = pb::UploadSessionChunk> + Send + 'static> {
    use tokio::io::AsyncSeekExt;
    let mut file = tokio::fs::File::open(&upload.path)
        .await
        .map_err(|e| ClientError::io(&upload.path, e))?;
    file.seek(std::io::SeekFrom::Start(offset))
        .await
        .map_err(|e| ClientError::io(&upload.path, e))?;
    let resume = pb::UploadSessionChunk {
        part: Some(pb::upload_session_chunk::Part::Resume(pb::UploadResume {
            session_id: session_id.to_string(),
            offset,
        })),
    };
    let data = futures::StreamExt::map(
        stylenerf_proto::chunks::file_chunks(file, CHUNK_BYTES, io_error),
        |buf| pb::UploadSessionChunk {
            part: Some(pb::upload_session_chunk::Part::Data(buf)),
        },
    );
    Ok(futures::StreamExt::chain(
        futures::stream::iter([resume]),
        data,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packing_is_deterministic_and_skips_hidden_files() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("images")).unwrap();
        std::fs::write(dir.path().join("transforms.json"), b"{}").unwrap();
        std::fs::write(dir.path().join("images/b.png"), b"b").unwrap();
        std::fs::write(dir.path().join("images/a.png"), b"a").unwrap();
        std::fs::write(dir.path().join(".DS_Store"), b"x").unwrap();
        let first = pack_scene(dir.path()).unwrap();
        let second = pack_scene(dir.path()).unwrap();
        assert_eq!(first.sha256, second.sha256);
        assert_eq!(
            hash_file(&first.path).unwrap(),
            (first.size, first.sha256.clone())
        );
        let mut archive = tar::Archive::new(std::fs::File::open(&first.path).unwrap());
        let names: Vec<String> = archive
            .entries()
            .unwrap()
            .map(|e| e.unwrap().path().unwrap().display().to_string())
            .collect();
        assert_eq!(names, ["images/a.png", "images/b.png", "transforms.json"]);
        let temp = first.path.clone();
        drop(first);
        assert!(!temp.exists(), "the temporary archive is removed");
    }

    #[test]
    fn folders_without_a_scene_file_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("photo.png"), b"x").unwrap();
        let err = pack_scene(dir.path()).unwrap_err().to_string();
        assert!(err.contains("not a scene folder"), "{err}");
    }
}
