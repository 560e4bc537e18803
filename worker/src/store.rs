//! Object access through the coordinator's `ArtifactService`, which works for every deployment
//! (the worker needs no store credentials): list a prefix, download an object to a file (the
//! SHA-256 checked, written under a temporary name and renamed), upload a file or a whole
//! folder in 1 MiB chunks with its size and SHA-256 declared up front. Every transfer is
//! retried through a short coordinator outage.

use std::path::{Component, Path, PathBuf};
use std::sync::{Arc, Mutex};

use futures::StreamExt;
use sha2::{Digest, Sha256};
use stylenerf_engine::checkpoint::files_under;
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::artifact_service_client::ArtifactServiceClient;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::connection::Authed;
use crate::error::TaskError;
use crate::retry::with_retries;
use tonic::Status;

/// Bytes per upload message (the coordinator's limit).
const CHUNK: usize = 1 << 20;

/// The coordinator's object store, as seen by a worker.
#[derive(Clone)]
pub struct Store {
    client: ArtifactServiceClient<Authed>,
}

/// Store failures are retryable: the inputs were validated at submission, so a failing
/// transfer is a network, storage or local-disk problem.
fn transfer_error(what: String) -> impl FnOnce(Status) -> TaskError {
    move |s| TaskError::retryable(format!("{what}: {:?}: {}", s.code(), s.message()))
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> TaskError + '_ {
    move |e| TaskError::retryable(format!("{}: {e}", path.display()))
}

/// `rel` as a relative path with only normal components (no `..`, no root), if it is one.
pub fn safe_relative(rel: &str) -> Option<PathBuf> {
    let path = Path::new(rel);
    let ok = !rel.is_empty()
        && !rel.contains('\\')
        && path.components().all(|c| matches!(c, Component::Normal(_)));
    ok.then(|| path.to_path_buf())
}

impl Store {
    pub fn new(client: ArtifactServiceClient<Authed>) -> Self {
        Self { client }
    }

    /// Objects under `prefix`, sorted by key.
    pub async fn list(&self, prefix: &str) -> Result<Vec<pb::Artifact>, TaskError> {
        let request = pb::ListObjectsRequest {
            prefix: prefix.to_string(),
        };
        Ok(with_retries(&format!("listing {prefix}"), || {
            let mut client = self.client.clone();
            let request = request.clone();
            async move { client.list_objects(request).await }
        })
        .await
        .map_err(transfer_error(format!("listing {prefix}")))?
        .into_inner()
        .objects)
    }

    /// Downloads `key` to `dest`, checking the SHA-256 when `sha256` is not empty. A transfer
    /// cut by a coordinator outage starts again ([`with_retries`]).
    pub async fn download(&self, key: &str, sha256: &str, dest: &Path) -> Result<(), TaskError> {
        if let Some(dir) = dest.parent() {
            tokio::fs::create_dir_all(dir)
                .await
                .map_err(io_error(dir))?;
        }
        let tmp = dest.with_extension("part");
        let local = LocalError::default();
        let actual = with_retries(&format!("downloading {key}"), || {
            self.download_once(key, &tmp, &local)
        })
        .await;
        local.take(&tmp)?;
        let actual = actual.map_err(transfer_error(format!("downloading {key}")))?;
        if !sha256.is_empty() && actual != sha256 {
            let _ = tokio::fs::remove_file(&tmp).await;
            return Err(TaskError::retryable(format!(
                "downloading {key}: SHA-256 {actual} does not match the manifest's {sha256}"
            )));
        }
        tokio::fs::rename(&tmp, dest).await.map_err(io_error(dest))
    }

    /// One attempt at a download into `tmp`; returns the data's SHA-256.
    async fn download_once(
        &self,
        key: &str,
        tmp: &Path,
        local: &LocalError,
    ) -> Result<String, Status> {
        let mut stream = self
            .client
            .clone()
            .get_object(pb::GetObjectRequest {
                key: key.to_string(),
                offset: 0,
            })
            .await?
            .into_inner();
        let mut file = local.check(tokio::fs::File::create(tmp).await)?;
        let mut hasher = Sha256::new();
        while let Some(chunk) = stream.next().await {
            let chunk = chunk?;
            hasher.update(&chunk.data);
            local.check(file.write_all(&chunk.data).await)?;
        }
        local.check(file.flush().await)?;
        Ok(hex::encode(hasher.finalize()))
    }

    /// Downloads every object under `prefix` into `dir`, at its path relative to the prefix.
    pub async fn download_all(
        &self,
        objects: &[pb::Artifact],
        prefix: &str,
        dir: &Path,
    ) -> Result<(), TaskError> {
        for object in objects {
            let rel = object
                .key
                .strip_prefix(prefix)
                .and_then(safe_relative)
                .ok_or_else(|| {
                    TaskError::permanent(format!(
                        "object {} is not a plain path under {prefix}",
                        object.key
                    ))
                })?;
            self.download(&object.key, &object.sha256, &dir.join(rel))
                .await?;
        }
        Ok(())
    }

    /// Uploads the file at `path` as `key`, starting again through a coordinator outage
    /// ([`with_retries`]).
    pub async fn upload(&self, key: &str, path: &Path) -> Result<pb::Artifact, TaskError> {
        let (size, sha256) = hash_file(path).await?;
        let local = LocalError::default();
        let result = with_retries(&format!("uploading {key}"), || {
            self.upload_once(key, path, size, &sha256, &local)
        })
        .await;
        local.take(path)?;
        result.map_err(transfer_error(format!("uploading {key}")))
    }

    async fn upload_once(
        &self,
        key: &str,
        path: &Path,
        size: u64,
        sha256: &str,
        local: &LocalError,
    ) -> Result<pb::Artifact, Status> {
        let header = pb::PutObjectChunk {
            part: Some(pb::put_object_chunk::Part::Header(pb::PutObjectHeader {
                key: key.to_string(),
                size,
                sha256: sha256.to_string(),
            })),
        };
        let file = local.check(tokio::fs::File::open(path).await)?;
        // A read error ends the stream early; it is reported instead of the coordinator's
        // "stream ended" complaint.
        let read_error: Arc<Mutex<Option<std::io::Error>>> = Arc::default();
        let data = futures::StreamExt::map(
            stylenerf_proto::chunks::file_chunks(file, CHUNK, read_error.clone()),
            |buf| pb::PutObjectChunk {
                part: Some(pb::put_object_chunk::Part::Data(buf)),
            },
        );
        let result = self
            .client
            .clone()
            .put_object(futures::stream::iter([header]).chain(data))
            .await;
        if let Some(e) = read_error.lock().expect("read-error slot").take() {
            return local.check(Err(e));
        }
        Ok(result?.into_inner())
    }

    /// Uploads every file under `dir` (except hidden ones and those `skip` rejects, given their
    /// `/`-separated relative path) to `prefix` + relative path, in sorted order.
    pub async fn upload_dir(
        &self,
        dir: &Path,
        prefix: &str,
        skip: impl Fn(&str) -> bool,
    ) -> Result<Vec<pb::Artifact>, TaskError> {
        let mut artifacts = Vec::new();
        for rel in files_under(dir)? {
            if skip(&rel) {
                continue;
            }
            artifacts.push(
                self.upload(&format!("{prefix}{rel}"), &dir.join(&rel))
                    .await?,
            );
        }
        Ok(artifacts)
    }
}

/// A local file error met during a transfer attempt: it ends the attempt (as a status that is
/// not retried) and is reported as itself afterwards.
#[derive(Default)]
struct LocalError(Mutex<Option<std::io::Error>>);

impl LocalError {
    fn check<T>(&self, result: std::io::Result<T>) -> Result<T, Status> {
        result.map_err(|e| {
            let status = Status::cancelled(format!("local file error: {e}"));
            *self.0.lock().expect("local-error slot") = Some(e);
            status
        })
    }

    /// The local error, if one ended the transfer, as a task error naming `path`.
    fn take(&self, path: &Path) -> Result<(), TaskError> {
        match self.0.lock().expect("local-error slot").take() {
            Some(e) => Err(io_error(path)(e)),
            None => Ok(()),
        }
    }
}

/// Size and lower-case hex SHA-256 of a file.
async fn hash_file(path: &Path) -> Result<(u64, String), TaskError> {
    let mut file = tokio::fs::File::open(path).await.map_err(io_error(path))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; CHUNK];
    let mut size = 0u64;
    loop {
        let n = file.read(&mut buf).await.map_err(io_error(path))?;
        if n == 0 {
            break;
        }
        size += n as u64;
        hasher.update(&buf[..n]);
    }
    Ok((size, hex::encode(hasher.finalize())))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_stay_inside() {
        assert_eq!(safe_relative("a/b.png"), Some(PathBuf::from("a/b.png")));
        assert_eq!(safe_relative("../x"), None);
        assert_eq!(safe_relative("/etc/passwd"), None);
        assert_eq!(safe_relative("a\\b"), None);
        assert_eq!(safe_relative(""), None);
    }
}
