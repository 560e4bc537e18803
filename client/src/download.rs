//! Downloading artifacts to files: each object is streamed into a hidden temporary file next to
//! its destination, checked (contiguous offsets, size, SHA-256 when the coordinator knows it),
//! and renamed into place, so a destination file is either absent, the previous version, or
//! complete. Files already present with the expected checksum are skipped.

use crate::error::{ClientError, Result};
use crate::transport::AuthedChannel;
use crate::upload::hash_file;
use futures::StreamExt;
use sha2::{Digest, Sha256};
use std::path::{Component, Path, PathBuf};
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::job_service_client::JobServiceClient;
use tokio::io::AsyncWriteExt;

/// Which artifacts `Client::download_with` fetches.
#[derive(Debug, Clone, Default)]
pub struct DownloadOptions {
    /// Only keys under `jobs/<job>/<prefix>` (e.g. `render_stylized/`; empty = all).
    pub prefix: String,
    /// Also fetch the job's inputs (`inputs/`: the dataset archive and style images).
    pub include_inputs: bool,
    /// Also fetch training checkpoints (`.../ckpt/...`).
    pub include_checkpoints: bool,
}

impl DownloadOptions {
    /// Whether the key (relative to `jobs/<job>/`) is wanted.
    pub fn wants(&self, relative: &str) -> bool {
        if !self.include_inputs && relative.split('/').next() == Some("inputs") {
            return false;
        }
        if !self.include_checkpoints && relative.split('/').any(|p| p == "ckpt") {
            return false;
        }
        true
    }
}

/// One artifact written (or found up to date) on disk.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DownloadedFile {
    pub key: String,
    pub path: PathBuf,
    pub size: u64,
    /// SHA-256 of the file on disk.
    pub sha256: String,
    /// True when the file was already present with the expected checksum.
    pub skipped: bool,
}

/// The key relative to `jobs/<job>/`, checked to be a plain relative path.
pub(crate) fn relative_key<'a>(job_id: &str, key: &'a str) -> Result<&'a str> {
    let prefix = format!("jobs/{job_id}/");
    let relative = key
        .strip_prefix(&prefix)
        .filter(|r| !r.is_empty())
        .ok_or_else(|| {
            ClientError::Protocol(format!("artifact key {key:?} is not under {prefix}"))
        })?;
    let plain = Path::new(relative)
        .components()
        .all(|c| matches!(c, Component::Normal(_)));
    if !plain || relative.contains('\\') {
        return Err(ClientError::Protocol(format!(
            "artifact key {key:?} is not a plain relative path"
        )));
    }
    Ok(relative)
}

/// Whether `path` already holds the artifact (same size and a known, matching SHA-256).
fn up_to_date(path: &Path, artifact: &pb::Artifact) -> Option<String> {
    if artifact.sha256.is_empty() {
        return None;
    }
    let meta = std::fs::metadata(path).ok()?;
    if !meta.is_file() || meta.len() != artifact.size {
        return None;
    }
    let (_, sha) = hash_file(path).ok()?;
    (sha == artifact.sha256).then_some(sha)
}

/// Downloads one artifact of `job_id` to `dest`, atomically.
pub(crate) async fn download_file(
    jobs: &mut JobServiceClient<AuthedChannel>,
    endpoint: &str,
    job_id: &str,
    artifact: &pb::Artifact,
    dest: &Path,
) -> Result<DownloadedFile> {
    if let Some(sha256) = up_to_date(dest, artifact) {
        return Ok(DownloadedFile {
            key: artifact.key.clone(),
            path: dest.to_path_buf(),
            size: artifact.size,
            sha256,
            skipped: true,
        });
    }
    let parent = dest.parent().unwrap_or(Path::new("."));
    tokio::fs::create_dir_all(parent)
        .await
        .map_err(|e| ClientError::io(parent, e))?;
    let name = dest
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let temp = tempfile::Builder::new()
        .prefix(&format!(".{name}."))
        .suffix(".part")
        .tempfile_in(parent)
        .map_err(|e| ClientError::io(parent, e))?;
    let (file, temp_path) = temp.into_parts();
    let mut file = tokio::fs::File::from_std(file);

    let mut stream = jobs
        .download_artifact(pb::DownloadArtifactRequest {
            job_id: job_id.to_string(),
            key: artifact.key.clone(),
            offset: 0,
        })
        .await
        .map_err(|s| ClientError::from_status(s, endpoint))?
        .into_inner();
    let mut hasher = Sha256::new();
    let mut written = 0u64;
    let mut expected = artifact.size;
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|s| ClientError::from_status(s, endpoint))?;
        if written == 0 && chunk.total_size > 0 {
            expected = chunk.total_size;
        }
        if chunk.offset != written {
            return Err(ClientError::Protocol(format!(
                "{}: chunk at offset {} after {written} bytes",
                artifact.key, chunk.offset
            )));
        }
        hasher.update(&chunk.data);
        file.write_all(&chunk.data)
            .await
            .map_err(|e| ClientError::io(&*temp_path, e))?;
        written += chunk.data.len() as u64;
    }
    file.flush()
        .await
        .map_err(|e| ClientError::io(&*temp_path, e))?;
    file.sync_all()
        .await
        .map_err(|e| ClientError::io(&*temp_path, e))?;
    drop(file);
    if written != expected {
        return Err(ClientError::Protocol(format!(
            "{}: received {written} of {expected} bytes",
            artifact.key
        )));
    }
    let sha256 = hex::encode(hasher.finalize());
    if !artifact.sha256.is_empty() && sha256 != artifact.sha256 {
        return Err(ClientError::Protocol(format!(
            "{}: SHA-256 {sha256} does not match the recorded {}",
            artifact.key, artifact.sha256
        )));
    }
    temp_path
        .persist(dest)
        .map_err(|e| ClientError::io(dest, e.error))?;
    Ok(DownloadedFile {
        key: artifact.key.clone(),
        path: dest.to_path_buf(),
        size: written,
        sha256,
        skipped: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_must_stay_inside_the_job() {
        assert_eq!(
            relative_key("j-1", "jobs/j-1/render_stylized/a.png").unwrap(),
            "render_stylized/a.png"
        );
        assert!(relative_key("j-1", "jobs/j-2/x").is_err());
        assert!(relative_key("j-1", "jobs/j-1/../j-2/x").is_err());
        assert!(relative_key("j-1", "jobs/j-1/").is_err());
    }

    #[test]
    fn inputs_and_checkpoints_are_opt_in() {
        let default = DownloadOptions::default();
        assert!(default.wants("nerf_pretrain/field.safetensors"));
        assert!(!default.wants("nerf_pretrain/ckpt/000100.safetensors"));
        assert!(!default.wants("inputs/scene.tar"));
        let all = DownloadOptions {
            include_inputs: true,
            include_checkpoints: true,
            ..Default::default()
        };
        assert!(all.wants("inputs/scene.tar") && all.wants("a/ckpt/b"));
    }
}
