//! The artifact store: an `object_store` opened from a directory or URL, object key rules
//! (everything a caller names must be a clean relative key), streamed reads and writes with
//! SHA-256 verification, and listings.

use crate::errors::{internal, invalid};
use bytes::Bytes;
use futures::{Stream, StreamExt, TryStreamExt};
use object_store::path::Path as ObjectPath;
use object_store::{
    GetOptions, GetRange, ObjectStore, ObjectStoreExt, ObjectStoreScheme, WriteMultipart,
};
use sha2::{Digest, Sha256};
use std::sync::Arc;
use stylenerf_proto::v1 as pb;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::Status;

/// Content of streamed reads is sent in chunks of this size.
pub const CHUNK_BYTES: usize = 1 << 20;

/// A store that signs URLs (only the cloud stores do).
#[cfg(feature = "cloud")]
type StoreSigner = Arc<dyn object_store::signer::Signer>;
#[cfg(not(feature = "cloud"))]
type StoreSigner = std::convert::Infallible;

/// The coordinator's object store.
#[derive(Clone, Debug)]
pub struct Storage {
    store: Arc<dyn ObjectStore>,
    /// The same store as a URL signer, when it can sign (the cloud stores).
    signer: Option<StoreSigner>,
    /// The store's own description (for logs).
    backend: String,
    /// The normalised URL workers with direct access can open.
    url: String,
}

/// A cloud store under `prefix`, configured from `options` (lower-case `aws_*`, `google_*`,
/// `azure_*` keys; others ignored) as object_store's `parse_url_opts` does, kept as both a
/// store and a URL signer, with the store's own description (for logs).
#[cfg(feature = "cloud")]
fn cloud_store(
    url: &url::Url,
    scheme: ObjectStoreScheme,
    prefix: ObjectPath,
    options: &[(String, String)],
) -> object_store::Result<(Arc<dyn ObjectStore>, StoreSigner, String)> {
    use object_store::prefix::PrefixStore;
    macro_rules! build {
        ($builder:ty) => {{
            let builder = options.iter().fold(
                <$builder>::new().with_url(url.to_string()),
                |builder, (key, value)| match key.parse() {
                    Ok(key) => builder.with_config(key, value.clone()),
                    Err(_) => builder,
                },
            );
            let inner = builder.build()?;
            let backend = inner.to_string();
            let store = Arc::new(PrefixStore::new(inner, prefix));
            Ok((
                store.clone() as Arc<dyn ObjectStore>,
                store as StoreSigner,
                backend,
            ))
        }};
    }
    match scheme {
        ObjectStoreScheme::AmazonS3 => build!(object_store::aws::AmazonS3Builder),
        ObjectStoreScheme::GoogleCloudStorage => {
            build!(object_store::gcp::GoogleCloudStorageBuilder)
        }
        ObjectStoreScheme::MicrosoftAzure => build!(object_store::azure::MicrosoftAzureBuilder),
        other => Err(object_store::Error::NotSupported {
            source: format!("{other:?} is not a cloud store").into(),
        }),
    }
}

impl Storage {
    /// Opens a local directory (a plain path or `file://` URL; created if missing) or, with the
    /// `cloud` feature, an `s3://`, `gs://` or `az://` URL configured from the environment.
    pub fn open(location: &str) -> anyhow::Result<Storage> {
        Storage::open_with_env(location, std::env::vars())
    }

    /// [`Storage::open`] with the environment given: a cloud store takes its options
    /// (credentials, region, endpoint, …) from `AWS_*`, `GOOGLE_*` or `AZURE_*` variables, as
    /// object_store's builders do with `from_env` (names are case-insensitive; others ignored).
    pub fn open_with_env(
        location: &str,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> anyhow::Result<Storage> {
        let local_dir = match location.strip_prefix("file://") {
            Some(path) => Some(std::path::PathBuf::from(path)),
            None if !location.contains("://") => Some(std::path::PathBuf::from(location)),
            None => None,
        };
        if let Some(dir) = local_dir {
            std::fs::create_dir_all(&dir).map_err(|e| {
                anyhow::anyhow!("creating storage directory {}: {e}", dir.display())
            })?;
            let dir = dir.canonicalize()?;
            let store = object_store::local::LocalFileSystem::new_with_prefix(&dir)?
                .with_automatic_cleanup(true);
            return Ok(Storage {
                backend: store.to_string(),
                store: Arc::new(store),
                signer: None,
                url: format!("file://{}", dir.display()),
            });
        }
        let url = url::Url::parse(location)
            .map_err(|e| anyhow::anyhow!("storage URL {location:?}: {e}"))?;
        let (scheme, prefix) = ObjectStoreScheme::parse(&url)
            .map_err(|e| anyhow::anyhow!("storage URL {location:?}: {e}"))?;
        let cloud = matches!(
            scheme,
            ObjectStoreScheme::AmazonS3
                | ObjectStoreScheme::GoogleCloudStorage
                | ObjectStoreScheme::MicrosoftAzure
        );
        anyhow::ensure!(
            cloud,
            "storage URL {location:?}: expected a directory, file://, s3://, gs:// or az:// URL"
        );
        #[cfg(not(feature = "cloud"))]
        {
            let _ = (env, prefix);
            anyhow::bail!(
                "storage URL {location:?}: cloud stores need a coordinator built with the \
                 `cloud` feature of stylenerf-server"
            )
        }
        #[cfg(feature = "cloud")]
        {
            // HTTPS to the cloud APIs uses rustls with ring, as the gRPC server does (no
            // aws-lc C build); an embedding program may have installed a provider already.
            let _ = rustls::crypto::ring::default_provider().install_default();
            let prefix = ObjectPath::parse(prefix)
                .map_err(|e| anyhow::anyhow!("storage URL {location:?}: {e}"))?;
            let options: Vec<(String, String)> = env
                .into_iter()
                .map(|(k, v)| (k.to_ascii_lowercase(), v))
                .collect();
            let (store, signer, backend) = cloud_store(&url, scheme, prefix, &options)
                .map_err(|e| anyhow::anyhow!("storage URL {location:?}: {e}"))?;
            Ok(Storage {
                backend,
                store,
                signer: Some(signer),
                url: location.trim_end_matches('/').to_string(),
            })
        }
    }

    /// A presigned GET URL of `key` valid for `expires_in`, when the store signs URLs (S3,
    /// GCS, Azure); `None` for a local folder.
    pub async fn presigned_get(
        &self,
        key: &str,
        expires_in: std::time::Duration,
    ) -> Option<anyhow::Result<String>> {
        let signer = self.signer.as_ref()?;
        #[cfg(feature = "cloud")]
        {
            let url = signer
                .signed_url(
                    object_store::signer::Method::GET,
                    &ObjectPath::from(key),
                    expires_in,
                )
                .await;
            Some(url.map(|u| u.to_string()).map_err(anyhow::Error::from))
        }
        #[cfg(not(feature = "cloud"))]
        {
            let _ = (key, expires_in);
            match *signer {}
        }
    }

    /// Whether the store signs URLs itself.
    pub fn can_sign(&self) -> bool {
        self.signer.is_some()
    }

    /// Writes, reads back and deletes a small object, so that a missing bucket, wrong
    /// credentials or a read-only folder stop the coordinator at start with the store's own
    /// message instead of failing the first upload.
    pub async fn check_access(&self) -> anyhow::Result<()> {
        let path = ObjectPath::from(".stylenerf-access-check");
        let fail = |what: &str, e: object_store::Error| {
            anyhow::anyhow!(
                "storage {}: cannot {what} ({}): {e}",
                self.url,
                self.backend
            )
        };
        self.store
            .put(&path, Bytes::from_static(b"ok").into())
            .await
            .map_err(|e| fail("write an object", e))?;
        let read = async { self.store.get(&path).await?.bytes().await };
        read.await.map_err(|e| fail("read an object back", e))?;
        self.store
            .delete(&path)
            .await
            .map_err(|e| fail("delete an object", e))?;
        Ok(())
    }

    /// Which store this is, e.g. `AmazonS3(bucket)` or `LocalFileSystem(file:///dir)`.
    pub fn backend(&self) -> &str {
        &self.backend
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// Stores a local file under `key`, streaming it in parts.
    pub async fn put_file(&self, key: &str, file: &std::path::Path) -> anyhow::Result<()> {
        let mut source = tokio::fs::File::open(file).await?;
        let mut writer =
            WriteMultipart::new(self.store.put_multipart(&ObjectPath::from(key)).await?);
        let mut buf = vec![0u8; CHUNK_BYTES];
        loop {
            let n = source.read(&mut buf).await?;
            if n == 0 {
                break;
            }
            writer.wait_for_capacity(4).await?;
            writer.write(&buf[..n]);
        }
        writer.finish().await?;
        Ok(())
    }

    /// Copies an object (inputs of a job are copied from its uploads).
    pub async fn copy(&self, from: &str, to: &str) -> anyhow::Result<()> {
        self.store
            .copy(&ObjectPath::from(from), &ObjectPath::from(to))
            .await?;
        Ok(())
    }

    /// Deletes an object; one already gone is fine.
    pub async fn delete(&self, key: &str) -> anyhow::Result<()> {
        match self.store.delete(&ObjectPath::from(key)).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    /// Reads a whole object into a local file (for validating staged datasets).
    pub async fn get_to_file(&self, key: &str, file: &std::path::Path) -> Result<u64, Status> {
        let mut out = tokio::fs::File::create(file).await.map_err(internal)?;
        let size = self.append_to(key, &mut out, |_| {}).await?;
        // tokio hands writes to a blocking thread: without this the last one may still be in
        // flight when the caller reads the file.
        out.flush().await.map_err(internal)?;
        Ok(size)
    }

    /// Appends a whole object to `out`, handing each piece to `seen` as well (to hash it);
    /// returns the object's size. The caller flushes `out`.
    pub async fn append_to(
        &self,
        key: &str,
        out: &mut tokio::fs::File,
        mut seen: impl FnMut(&[u8]),
    ) -> Result<u64, Status> {
        /// Read in ranges this large: a store's own stream comes in small pieces (a local
        /// folder's in 8 KiB ones, each a trip to the blocking pool), which made joining
        /// uploaded parts several times slower than receiving them.
        const RANGE: u64 = 16 << 20;
        let path = ObjectPath::from(key);
        let size = self.size(key).await?;
        let mut offset = 0;
        while offset < size {
            let end = (offset + RANGE).min(size);
            let bytes = self
                .store
                .get_range(&path, offset..end)
                .await
                .map_err(|e| storage_status(key, e))?;
            seen(&bytes);
            out.write_all(&bytes).await.map_err(internal)?;
            offset = end;
        }
        Ok(size)
    }

    /// Size of an object.
    pub async fn size(&self, key: &str) -> Result<u64, Status> {
        let meta = self
            .store
            .head(&ObjectPath::from(key))
            .await
            .map_err(|e| storage_status(key, e))?;
        Ok(meta.size)
    }

    /// Streams an object from `offset` in chunks of at most `CHUNK_BYTES`.
    pub async fn get_stream(
        &self,
        key: &str,
        offset: u64,
    ) -> Result<impl Stream<Item = Result<pb::ObjectChunk, Status>> + Send + 'static, Status> {
        if offset > 0 {
            // A resumed download may start at the end (nothing left) but not beyond it.
            let size = self.size(key).await?;
            if offset > size {
                return Err(invalid(
                    "offset",
                    format!("{offset} is beyond the end of {key:?} ({size} bytes)"),
                ));
            }
            if offset == size {
                return Ok(futures::stream::empty().left_stream());
            }
        }
        let options = GetOptions {
            range: (offset > 0).then_some(GetRange::Offset(offset)),
            ..GetOptions::default()
        };
        let result = self
            .store
            .get_opts(&ObjectPath::from(key), options)
            .await
            .map_err(|e| storage_status(key, e))?;
        let total_size = result.meta.size;
        let key = key.to_string();
        let mut position = offset;
        let mut first = true;
        let stream = result
            .into_stream()
            .map_err({
                let key = key.clone();
                move |e| storage_status(&key, e)
            })
            .map_ok(move |bytes: Bytes| {
                let pieces: Vec<Bytes> = (0..bytes.len())
                    .step_by(CHUNK_BYTES)
                    .map(|start| bytes.slice(start..(start + CHUNK_BYTES).min(bytes.len())))
                    .collect();
                futures::stream::iter(pieces.into_iter().map(Ok::<_, Status>))
            })
            .try_flatten()
            .map_ok(move |data| {
                let chunk = pb::ObjectChunk {
                    key: if first { key.clone() } else { String::new() },
                    offset: position,
                    total_size: if first { total_size } else { 0 },
                    data: data.to_vec(),
                };
                first = false;
                position += data.len() as u64;
                chunk
            });
        Ok(stream.right_stream())
    }

    /// Objects under `prefix` (a key prefix ending in `/`, or empty), sorted by key.
    pub async fn list(&self, prefix: &str) -> Result<Vec<(String, u64)>, Status> {
        let dir = prefix.trim_end_matches('/');
        let path = (!dir.is_empty()).then(|| ObjectPath::from(dir));
        let mut out: Vec<(String, u64)> = self
            .store
            .list(path.as_ref())
            .map_ok(|meta| (meta.location.to_string(), meta.size))
            .try_collect()
            .await
            .map_err(internal)?;
        out.retain(|(key, _)| key.starts_with(prefix));
        out.sort();
        Ok(out)
    }

    /// Writes an object from a stream of chunks, verifying its declared size and SHA-256. The
    /// object only appears if everything matched.
    pub async fn put_verified<S>(
        &self,
        key: &str,
        size: u64,
        sha256: &str,
        mut chunks: S,
    ) -> Result<(), Status>
    where
        S: Stream<Item = Result<Vec<u8>, Status>> + Unpin,
    {
        let upload = self
            .store
            .put_multipart(&ObjectPath::from(key))
            .await
            .map_err(internal)?;
        let mut writer = WriteMultipart::new(upload);
        let mut hasher = Sha256::new();
        let mut received = 0u64;
        let outcome: Result<(), Status> = async {
            while let Some(chunk) = chunks.next().await {
                let chunk = chunk?;
                received += chunk.len() as u64;
                if received > size {
                    return Err(invalid(
                        "data",
                        format!("more data than the declared size of {size} bytes"),
                    ));
                }
                hasher.update(&chunk);
                writer.wait_for_capacity(4).await.map_err(internal)?;
                writer.write(&chunk);
            }
            if received != size {
                return Err(invalid(
                    "data",
                    format!("stream ended after {received} of {size} bytes"),
                ));
            }
            let actual = hex::encode(hasher.finalize());
            if actual != sha256 {
                return Err(invalid(
                    "header.sha256",
                    format!("checksum mismatch: the data has SHA-256 {actual}"),
                ));
            }
            Ok(())
        }
        .await;
        match outcome {
            Ok(()) => writer.finish().await.map(|_| ()).map_err(internal),
            Err(status) => {
                let _ = writer.abort().await;
                Err(status)
            }
        }
    }
}

fn storage_status(key: &str, err: object_store::Error) -> Status {
    match err {
        object_store::Error::NotFound { .. } => {
            Status::not_found(format!("object {key:?} not found"))
        }
        e => internal(e),
    }
}

/// Checks that a caller-supplied object key is clean: relative, `/`-separated, no empty, `.`
/// or `..` segments, no control characters, at most 1024 bytes, and naming an object (not
/// ending in `/`).
pub fn check_key(field: &str, key: &str) -> Result<(), Status> {
    check_prefix(field, key)?;
    if key.ends_with('/') {
        return Err(invalid(
            field,
            format!("object key {key:?}: names a folder, not an object (ends with `/`)"),
        ));
    }
    Ok(())
}

/// Checks a caller-supplied listing prefix: a clean key as for [`check_key`] that may end
/// with `/`.
pub fn check_prefix(field: &str, key: &str) -> Result<(), Status> {
    let why = if key.is_empty() {
        Some("must not be empty")
    } else if key.len() > 1024 {
        Some("longer than 1024 bytes")
    } else if key.starts_with('/') {
        Some("must be relative (no leading `/`)")
    } else if key.chars().any(|c| c.is_control() || c == '\\') {
        Some("control characters and backslashes are not allowed")
    } else if key
        .trim_end_matches('/')
        .split('/')
        .any(|seg| seg.is_empty() || seg == "." || seg == "..")
    {
        Some("empty, `.` and `..` segments are not allowed")
    } else {
        None
    };
    match why {
        Some(why) => Err(invalid(field, format!("object key {key:?}: {why}"))),
        None => Ok(()),
    }
}

/// Checks a lower-case hex SHA-256.
pub fn check_sha256(field: &str, sha: &str) -> Result<(), Status> {
    if sha.len() == 64 && sha.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
        Ok(())
    } else {
        Err(invalid(field, "must be 64 lower-case hex digits (SHA-256)"))
    }
}

#[cfg(test)]
mod tests {
    use super::Storage;

    /// Fake credentials: building a store does not contact the cloud.
    fn fake_env() -> Vec<(String, String)> {
        [
            ("AWS_ACCESS_KEY_ID", "AKIDEXAMPLE"),
            ("AWS_SECRET_ACCESS_KEY", "not-a-secret"),
            ("AWS_REGION", "eu-west-1"),
            ("AZURE_STORAGE_ACCOUNT_NAME", "account"),
            ("AZURE_STORAGE_ACCOUNT_KEY", "bm90LWEta2V5"),
            ("UNRELATED", "ignored"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
    }

    #[test]
    fn cloud_urls_pick_their_store() {
        for (url, backend) in [
            ("s3://bucket/some/prefix", "AmazonS3(bucket)"),
            ("gs://bucket/some/prefix", "GoogleCloudStorage(bucket)"),
            ("az://container/some/prefix", "MicrosoftAzure"),
        ] {
            let opened = Storage::open_with_env(url, fake_env());
            if cfg!(feature = "cloud") {
                let storage = opened.unwrap_or_else(|e| panic!("{url}: {e}"));
                assert!(
                    storage.backend().starts_with(backend),
                    "{url}: {}",
                    storage.backend()
                );
                assert_eq!(storage.url(), url);
            } else {
                let error = opened.expect_err("needs the cloud feature").to_string();
                assert!(error.contains("`cloud` feature"), "{url}: {error}");
            }
        }
    }

    #[test]
    fn directories_and_unknown_schemes() {
        let dir = tempfile::tempdir().unwrap();
        let local = Storage::open_with_env(dir.path().to_str().unwrap(), fake_env()).unwrap();
        assert!(local.url().starts_with("file://"), "{}", local.url());
        assert!(
            local.backend().starts_with("LocalFileSystem"),
            "{}",
            local.backend()
        );
        let error = Storage::open_with_env("ftp://host/dir", fake_env()).unwrap_err();
        assert!(error.to_string().contains("storage URL"), "{error}");
    }
}
