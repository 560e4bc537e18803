//! `POST /upload?kind=…&filename=…`: one input as the raw request body, for browsers (a file
//! input's `File` is sent as it is). Checked like a gRPC `Upload` — kind, file name, the size
//! limit (from `content-length` and as the bytes arrive), the owner's storage quota, the
//! content — and the SHA-256 in `x-content-sha256` when the client sends one.

use super::{error, json, Web};
use crate::auth::CLIENT_ROLES;
use crate::errors::invalid;
use crate::inputs::{
    accept_spooled, check_declared_size, check_filename, size_limit, upload_kind, Spool,
};
use crate::storage::check_sha256;
use axum::body::Body;
use axum::http::{HeaderMap, StatusCode, Uri};
use axum::response::Response;
use futures::StreamExt;
use stylenerf_proto::v1 as pb;
use tonic::Status;

pub async fn receive(web: &Web, uri: &Uri, headers: &HeaderMap, body: Body) -> Response {
    match accept(web, uri, headers, body).await {
        Ok(receipt) => json(StatusCode::OK, &receipt),
        Err(status) => error(&status),
    }
}

async fn accept(
    web: &Web,
    uri: &Uri,
    headers: &HeaderMap,
    body: Body,
) -> Result<pb::UploadReceipt, Status> {
    let caller = web.caller(headers)?;
    crate::auth::require_role(&caller, CLIENT_ROLES)?;
    let shared = web.shared();
    let (mut kind, mut filename) = (None, String::new());
    for (name, value) in url::form_urlencoded::parse(uri.query().unwrap_or("").as_bytes()) {
        match name.as_ref() {
            "kind" => kind = pb::UploadKind::from_str_name(&format!("UPLOAD_KIND_{value}")),
            "filename" => filename = value.into_owned(),
            _ => {}
        }
    }
    let kind = upload_kind("kind", kind.map_or(0, |k| k as i32))?;
    let filename = check_filename("filename", &filename)?;
    let declared: Option<u64> = headers
        .get(axum::http::header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.parse().ok());
    if let Some(size) = declared {
        check_declared_size(shared, "content-length", kind, size, false)?;
    }
    let expected = match headers.get("x-content-sha256") {
        Some(value) => {
            let value = value.to_str().unwrap_or_default().to_string();
            check_sha256("x-content-sha256", &value)?;
            Some(value)
        }
        None => None,
    };
    let room = crate::quotas::storage_room(shared, &caller.name).await?;
    let what = "this upload";
    if let (Some(room), Some(size)) = (room, declared) {
        if size > room {
            return Err(crate::quotas::over_storage_quota(
                shared,
                &caller.name,
                what,
                room,
            ));
        }
    }
    let limit = size_limit(shared, kind).min(room.unwrap_or(u64::MAX));
    let mut spool = Spool::new(shared).await?;
    let mut stream = body.into_data_stream();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| invalid("body", format!("the upload broke off: {e}")))?;
        if spool.received + chunk.len() as u64 > limit {
            return Err(match room {
                Some(room) if room < size_limit(shared, kind) => {
                    crate::quotas::over_storage_quota(shared, &caller.name, what, room)
                }
                _ => invalid(
                    "body",
                    format!("more than the {} limit of {limit} bytes", kind.as_str()),
                ),
            });
        }
        spool.write(&chunk).await?;
    }
    let received = spool.received;
    if received == 0 {
        return Err(invalid("body", "empty"));
    }
    let (file, actual) = spool.finish().await?;
    if expected.as_ref().is_some_and(|e| *e != actual) {
        return Err(invalid(
            "x-content-sha256",
            format!("checksum mismatch: the uploaded data has SHA-256 {actual}"),
        ));
    }
    accept_spooled(shared, &caller, kind, filename, (file, actual, received)).await
}
