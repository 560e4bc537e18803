//! Job inputs: receiving chunked uploads into a spool file (size and SHA-256 checked as the
//! bytes arrive), validating datasets and style images off the async runtime, storing accepted
//! uploads under `uploads/<id>/` (also for the resumable sessions of `upload_sessions`), and
//! validating objects that operators staged in the store.

use crate::auth::{Principal, Role};
use crate::errors::{internal, invalid};
use crate::model::now_ms;
use crate::photos::validate_photos;
use crate::state::Shared;
use crate::storage::check_sha256;
use crate::validation::{validate_dataset_archive, validate_style_image};
use futures::{Stream, StreamExt};
use sha2::{Digest, Sha256};
use stylenerf_plan::DatasetFacts;
use stylenerf_proto::v1 as pb;
use tokio::io::AsyncWriteExt;
use tonic::Status;

/// The kinds of inputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputKind {
    Dataset,
    Style,
    /// Plain photos (a tar archive) or a video: a scene without camera poses.
    Photos,
}

impl InputKind {
    pub fn as_str(self) -> &'static str {
        match self {
            InputKind::Dataset => "dataset",
            InputKind::Style => "style",
            InputKind::Photos => "photos",
        }
    }

    /// The kind stored as [`InputKind::as_str`].
    pub fn parse(name: &str) -> Option<InputKind> {
        [InputKind::Dataset, InputKind::Style, InputKind::Photos]
            .into_iter()
            .find(|kind| kind.as_str() == name)
    }

    pub fn to_pb(self) -> pb::UploadKind {
        match self {
            InputKind::Dataset => pb::UploadKind::DatasetArchive,
            InputKind::Style => pb::UploadKind::StyleImage,
            InputKind::Photos => pb::UploadKind::Photos,
        }
    }
}

/// Most inputs validated at once: a style image is decoded whole (up to 8192² pixels of 16-bit
/// RGBA, 512 MiB), so this bounds the coordinator's memory under concurrent uploads.
pub const CONCURRENT_VALIDATIONS: usize = 2;

/// What validating an input file found.
struct Validated {
    /// One line for the receipt.
    summary: String,
    /// The extension to store it with.
    extension: &'static str,
    /// A dataset's facts, when the engine's checks are installed.
    facts: Option<DatasetFacts>,
}

/// Validates a complete input file.
async fn validate_file(
    shared: &Shared,
    kind: InputKind,
    path: std::path::PathBuf,
) -> Result<Result<Validated, String>, Status> {
    let limits = shared.config.limits.clone();
    let engine = shared.config.engine_checks.clone();
    let _slot = shared.validations.acquire().await.map_err(internal)?;
    let plain = |summary: String, extension| Validated {
        summary,
        extension,
        facts: None,
    };
    tokio::task::spawn_blocking(move || match kind {
        InputKind::Dataset => {
            let file = std::fs::File::open(&path).map_err(|e| e.to_string())?;
            let summary = validate_dataset_archive(file, &limits)?;
            let facts = engine.map(|engine| engine.dataset(&path)).transpose()?;
            Ok(Validated {
                facts,
                ..plain(summary.to_string(), "tar")
            })
        }
        InputKind::Style => {
            let bytes = std::fs::read(&path).map_err(|e| e.to_string())?;
            validate_style_image(&bytes, &limits)
                .map(|summary| plain(summary.to_string(), summary.extension()))
        }
        InputKind::Photos => validate_photos(&path, &limits)
            .map(|summary| plain(summary.to_string(), summary.extension)),
    })
    .await
    .map_err(internal)
}

/// The input kind an upload declares; `field` names it in errors.
pub fn upload_kind(field: &str, kind: i32) -> Result<InputKind, Status> {
    match pb::UploadKind::try_from(kind) {
        Ok(pb::UploadKind::DatasetArchive) => Ok(InputKind::Dataset),
        Ok(pb::UploadKind::StyleImage) => Ok(InputKind::Style),
        Ok(pb::UploadKind::Photos) => Ok(InputKind::Photos),
        _ => Err(invalid(
            field,
            "must be DATASET_ARCHIVE, STYLE_IMAGE or PHOTOS",
        )),
    }
}

/// The largest input of `kind` the coordinator accepts.
pub fn size_limit(shared: &Shared, kind: InputKind) -> u64 {
    match kind {
        InputKind::Dataset | InputKind::Photos => shared.config.limits.max_dataset_bytes,
        InputKind::Style => shared.config.limits.max_style_bytes,
    }
}

/// Checks an upload's file name; returns it trimmed.
pub fn check_filename<'a>(field: &str, filename: &'a str) -> Result<&'a str, Status> {
    let filename = filename.trim();
    if filename.is_empty()
        || filename.len() > 255
        || filename.contains(['/', '\\'])
        || filename.chars().any(char::is_control)
        || filename.starts_with('.')
    {
        return Err(invalid(
            field,
            "must be a plain file name (no directories, 1-255 characters, not starting with `.`)",
        ));
    }
    Ok(filename)
}

/// Checks a declared size against the limit of `kind` (`allow_zero`: 0 means "not declared").
pub fn check_declared_size(
    shared: &Shared,
    field: &str,
    kind: InputKind,
    size: u64,
    allow_zero: bool,
) -> Result<(), Status> {
    let limit = size_limit(shared, kind);
    if size == 0 && !allow_zero {
        return Err(invalid(field, "must be greater than 0"));
    }
    if size > limit {
        return Err(invalid(
            field,
            format!(
                "{size} bytes is more than the {} limit of {limit} bytes",
                kind.as_str()
            ),
        ));
    }
    Ok(())
}

/// A complete input received into a local spool file, its size and SHA-256 already checked.
pub struct Received<'a> {
    pub kind: InputKind,
    pub filename: &'a str,
    pub path: &'a std::path::Path,
    pub size: u64,
    pub sha256: String,
    /// An object in the store with the same bytes, copied inside the store instead of
    /// uploading the spool file again (a resumable upload's only part).
    pub stored_as: Option<String>,
}

/// An input validated and stored under `uploads/<id>/`, whose row is not yet inserted.
pub struct StoredUpload {
    receipt: pb::UploadReceipt,
    key: String,
    filename: String,
    kind: InputKind,
    facts: Option<DatasetFacts>,
}

impl StoredUpload {
    /// Inserts the upload's row for `owner` (in the caller's transaction, if any).
    pub async fn insert<'e>(
        self,
        owner: &str,
        db: impl sqlx::SqliteExecutor<'e>,
    ) -> Result<pb::UploadReceipt, Status> {
        sqlx::query(
            "INSERT INTO uploads (id, owner, kind, key, filename, size, sha256, summary, \
             created_at, train_depth) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(&self.receipt.upload_id)
        .bind(owner)
        .bind(self.kind.as_str())
        .bind(&self.key)
        .bind(&self.filename)
        .bind(self.receipt.size as i64)
        .bind(&self.receipt.sha256)
        .bind(&self.receipt.summary)
        .bind(now_ms())
        .bind(self.facts.map(|f| f.train_depth))
        .execute(db)
        .await
        .map_err(internal)?;
        Ok(self.receipt)
    }
}

/// Validates a received input and stores its object (the row is the caller's to insert).
pub async fn store_upload(shared: &Shared, input: Received<'_>) -> Result<StoredUpload, Status> {
    let Validated {
        summary,
        extension,
        facts,
    } = validate_file(shared, input.kind, input.path.to_path_buf())
        .await?
        .map_err(|why| invalid("data", why))?;
    let id = format!("u-{}", uuid::Uuid::now_v7().simple());
    let key = format!("uploads/{id}/{}.{extension}", input.kind.as_str());
    match &input.stored_as {
        Some(source) => shared.storage.copy(source, &key).await,
        None => shared.storage.put_file(&key, input.path).await,
    }
    .map_err(internal)?;
    Ok(StoredUpload {
        receipt: pb::UploadReceipt {
            upload_id: id,
            kind: input.kind.to_pb() as i32,
            size: input.size,
            sha256: input.sha256,
            summary,
        },
        key,
        filename: input.filename.to_string(),
        kind: input.kind,
        facts,
    })
}

/// The receipt of a stored upload.
pub async fn upload_receipt(shared: &Shared, upload_id: &str) -> Result<pb::UploadReceipt, Status> {
    let (kind, size, sha256, summary): (String, i64, String, String) =
        sqlx::query_as("SELECT kind, size, sha256, summary FROM uploads WHERE id = ?")
            .bind(upload_id)
            .fetch_one(&shared.db.read)
            .await
            .map_err(internal)?;
    Ok(pb::UploadReceipt {
        upload_id: upload_id.to_string(),
        kind: InputKind::parse(&kind).map_or(pb::UploadKind::Unspecified, InputKind::to_pb) as i32,
        size: size as u64,
        sha256,
        summary,
    })
}

/// A new spool file for received bytes.
pub fn spool_file(shared: &Shared) -> Result<tempfile::NamedTempFile, Status> {
    match &shared.config.spool_dir {
        Some(dir) => tempfile::NamedTempFile::new_in(dir),
        None => tempfile::NamedTempFile::new(),
    }
    .map_err(internal)
}

/// An input arriving into a spool file, counted and hashed as the bytes come.
pub struct Spool {
    temp: tempfile::NamedTempFile,
    file: tokio::fs::File,
    hasher: Sha256,
    /// Bytes received so far.
    pub received: u64,
}

impl Spool {
    pub async fn new(shared: &Shared) -> Result<Spool, Status> {
        let temp = spool_file(shared)?;
        let file = tokio::fs::File::create(temp.path())
            .await
            .map_err(internal)?;
        Ok(Spool {
            temp,
            file,
            hasher: Sha256::new(),
            received: 0,
        })
    }

    pub async fn write(&mut self, data: &[u8]) -> Result<(), Status> {
        self.hasher.update(data);
        self.file.write_all(data).await.map_err(internal)?;
        self.received += data.len() as u64;
        Ok(())
    }

    /// The complete file and the lower-case hex SHA-256 of its content.
    pub async fn finish(mut self) -> Result<(tempfile::NamedTempFile, String), Status> {
        self.file.flush().await.map_err(internal)?;
        Ok((self.temp, hex::encode(self.hasher.finalize())))
    }
}

/// Validates and stores a complete spooled input as an upload of `caller`, its size and
/// checksum already checked.
pub async fn accept_spooled(
    shared: &Shared,
    caller: &Principal,
    kind: InputKind,
    filename: &str,
    (file, sha256, size): (tempfile::NamedTempFile, String, u64),
) -> Result<pb::UploadReceipt, Status> {
    let stored = store_upload(
        shared,
        Received {
            kind,
            filename,
            path: file.path(),
            size,
            sha256,
            stored_as: None,
        },
    )
    .await?;
    stored.insert(&caller.name, &shared.db.write).await
}

/// Receives an `Upload` stream, validates it and stores it as an upload of `caller`.
pub async fn receive_upload<S>(
    shared: &Shared,
    caller: &Principal,
    mut stream: S,
) -> Result<pb::UploadReceipt, Status>
where
    S: Stream<Item = Result<pb::UploadChunk, Status>> + Unpin,
{
    let header = match stream.next().await {
        Some(Ok(pb::UploadChunk {
            part: Some(pb::upload_chunk::Part::Header(header)),
        })) => header,
        Some(Err(status)) => return Err(status),
        _ => {
            return Err(invalid(
                "header",
                "the first message must be the upload header",
            ))
        }
    };
    let kind = upload_kind("header.kind", header.kind)?;
    let filename = check_filename("header.filename", &header.filename)?;
    check_declared_size(shared, "header.total_size", kind, header.total_size, false)?;
    check_sha256("header.sha256", &header.sha256)?;
    crate::quotas::check_storage(
        shared,
        &caller.name,
        header.total_size,
        &format!("this upload of {} bytes", header.total_size),
    )
    .await?;

    let mut spool = Spool::new(shared).await?;
    while let Some(message) = stream.next().await {
        let data = match message?.part {
            Some(pb::upload_chunk::Part::Data(data)) => data,
            _ => return Err(invalid("header", "only the first message may be a header")),
        };
        if spool.received + data.len() as u64 > header.total_size {
            return Err(invalid(
                "data",
                format!(
                    "more data than header.total_size ({} bytes)",
                    header.total_size
                ),
            ));
        }
        spool.write(&data).await?;
    }
    let received = spool.received;
    let (file, actual) = spool.finish().await?;
    if received != header.total_size {
        return Err(invalid(
            "data",
            format!(
                "the stream ended after {received} of {} bytes",
                header.total_size
            ),
        ));
    }
    if actual != header.sha256 {
        return Err(invalid(
            "header.sha256",
            format!("checksum mismatch: the uploaded data has SHA-256 {actual}"),
        ));
    }
    accept_spooled(shared, caller, kind, filename, (file, actual, received)).await
}

/// A job input found and validated.
pub struct ResolvedInput {
    /// Its object in the store.
    pub key: String,
    /// The extension to copy it with.
    pub extension: String,
    pub kind: InputKind,
    /// A dataset's facts, when known (not for uploads from before they were recorded).
    pub facts: Option<DatasetFacts>,
}

/// Resolves an `InputRef` to a validated input: an upload of one of the `accepted` kinds, or
/// an object validated as the first of them. `field` names the reference in errors.
pub async fn resolve_input(
    shared: &Shared,
    caller: &Principal,
    field: &str,
    accepted: &[InputKind],
    input: Option<&pb::InputRef>,
) -> Result<ResolvedInput, Status> {
    let kind = accepted[0];
    use pb::input_ref::Source;
    match input.and_then(|i| i.source.as_ref()) {
        None => Err(invalid(
            field,
            "missing: give an upload_id or an object_key",
        )),
        Some(Source::UploadId(id)) => {
            let row: Option<(String, String, String, Option<bool>)> =
                sqlx::query_as("SELECT owner, kind, key, train_depth FROM uploads WHERE id = ?")
                    .bind(id)
                    .fetch_optional(&shared.db.read)
                    .await
                    .map_err(internal)?;
            match row {
                Some((owner, stored_kind, key, train_depth)) if caller.can_see(&owner) => {
                    let Some(kind) =
                        InputKind::parse(&stored_kind).filter(|k| accepted.contains(k))
                    else {
                        let names: Vec<&str> = accepted.iter().map(|k| k.as_str()).collect();
                        return Err(invalid(
                            format!("{field}.upload_id"),
                            format!(
                                "upload {id:?} is a {stored_kind}, not a {}",
                                names.join(" or ")
                            ),
                        ));
                    };
                    let extension = key.rsplit('.').next().unwrap_or("bin").to_string();
                    Ok(ResolvedInput {
                        key,
                        extension,
                        kind,
                        facts: train_depth.map(|train_depth| DatasetFacts { train_depth }),
                    })
                }
                _ => Err(invalid(
                    format!("{field}.upload_id"),
                    format!("no upload {id:?}"),
                )),
            }
        }
        Some(Source::ObjectKey(key)) => {
            let key_field = format!("{field}.object_key");
            crate::storage::check_key(&key_field, key)?;
            // Someone else's key and a missing key get the same answer: a caller cannot probe
            // which objects exist.
            let unreadable = || invalid(&key_field, format!("no object {key:?} that you can read"));
            if !may_read_object(shared, caller, key).await? {
                return Err(unreadable());
            }
            let limit = size_limit(shared, kind);
            let size = match shared.storage.size(key).await {
                Err(status) if status.code() == tonic::Code::NotFound => return Err(unreadable()),
                other => other?,
            };
            if size > limit {
                return Err(invalid(
                    &key_field,
                    format!("{size} bytes is more than the limit of {limit} bytes"),
                ));
            }
            let spool = spool_file(shared)?;
            shared.storage.get_to_file(key, spool.path()).await?;
            let validated = validate_file(shared, kind, spool.path().to_path_buf())
                .await?
                .map_err(|why| invalid(&key_field, why))?;
            Ok(ResolvedInput {
                key: key.clone(),
                extension: validated.extension.to_string(),
                kind,
                facts: validated.facts,
            })
        }
    }
}

/// Whether `caller` may use the object `key` as a job input: admins any key; others the
/// objects of their own uploads (`uploads/<id>/…`) and jobs (`jobs/<id>/…`) and what an
/// operator staged for them (`staged/<name>/…`).
async fn may_read_object(shared: &Shared, caller: &Principal, key: &str) -> Result<bool, Status> {
    if caller.role == Role::Admin {
        return Ok(true);
    }
    let mut segments = key.splitn(3, '/');
    let (Some(area), Some(id), Some(_)) = (segments.next(), segments.next(), segments.next())
    else {
        return Ok(false);
    };
    let owner_query = match area {
        "uploads" => "SELECT owner FROM uploads WHERE id = ?",
        "jobs" => "SELECT owner FROM jobs WHERE id = ?",
        "staged" => return Ok(id == caller.name),
        _ => return Ok(false),
    };
    let owner: Option<String> = sqlx::query_scalar(owner_query)
        .bind(id)
        .fetch_optional(&shared.db.read)
        .await
        .map_err(internal)?;
    Ok(owner.is_some_and(|owner| caller.can_see(&owner)))
}
