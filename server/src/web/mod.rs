//! The coordinator's web front, on the HTTP listener (`--http-listen`) beside the signed
//! downloads: a page for people (`/`: sign in with a client token, the job list with live
//! states, a job's stage timeline, progress, loss/PSNR plots, contact sheets and animations, a
//! style-blend render, and a form that submits a job), and the JSON API it runs on, which web
//! backends may use too:
//!
//! - `POST /stylenerf.v1.JobService/<Method>` with the request as proto JSON answers the
//!   response as proto JSON (the project's mapping: proto field names, enums by name), for every unary `JobService` method (Connect's unary JSON form:
//!   an error is `{"code": "not_found", "message": …, "violations": [{field, description}]}`
//!   with the matching HTTP status). `ListEvents` (`{job_id, after_seq}`) returns a job's stored
//!   events.
//! - `POST /upload?kind=DATASET_ARCHIVE|PHOTOS|STYLE_IMAGE&filename=F` with the file as the body (and
//!   optionally `x-content-sha256`, checked when given): the `UploadReceipt`.
//!
//! Every call needs `authorization: Bearer <token>` (no cookies: nothing a third-party page
//! could make a browser send). The page itself is static; it runs and fetches from this origin
//! only (its images may come from the object store's presigned URLs).

mod rpc;
mod upload;

use crate::api::job_api::JobApi;
use crate::auth::{Authenticator, Principal};
use crate::state::Shared;
use axum::body::Body;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use std::sync::Arc;
use tonic::Status;

const INDEX_HTML: &str = include_str!("page/index.html");
const APP_JS: &str = include_str!("page/app.js");
const APP_CSS: &str = include_str!("page/app.css");

/// What the handlers share.
#[derive(Clone)]
struct Web {
    api: Arc<JobApi>,
    auth: Authenticator,
}

impl Web {
    fn shared(&self) -> &Arc<Shared> {
        &self.api.shared
    }

    /// The caller, from the `authorization` header.
    #[allow(clippy::result_large_err)]
    fn caller(&self, headers: &HeaderMap) -> Result<Principal, Status> {
        let metadata = tonic::metadata::MetadataMap::from_headers(headers.clone());
        self.auth.authenticate(&metadata)
    }
}

/// The page's routes and the JSON API, merged into the HTTP listener's router.
pub fn router(shared: Arc<Shared>) -> axum::Router {
    let web = Web {
        auth: Authenticator::new(&shared.config.auth),
        api: Arc::new(JobApi { shared }),
    };
    let rpc_web = web.clone();
    let upload_web = web;
    axum::Router::new()
        .route(
            "/",
            axum::routing::get(|| async { page(INDEX_HTML, "text/html") }),
        )
        .route(
            "/app.js",
            axum::routing::get(|| async { page(APP_JS, "text/javascript") }),
        )
        .route(
            "/app.css",
            axum::routing::get(|| async { page(APP_CSS, "text/css") }),
        )
        .route(
            "/stylenerf.v1.JobService/{method}",
            axum::routing::post(
                move |axum::extract::Path(method): axum::extract::Path<String>,
                      headers: HeaderMap,
                      body: axum::body::Bytes| {
                    let web = rpc_web.clone();
                    async move { rpc::call(&web, &method, &headers, &body).await }
                },
            ),
        )
        .route(
            "/upload",
            axum::routing::post(
                move |uri: axum::http::Uri, headers: HeaderMap, body: Body| {
                    let web = upload_web.clone();
                    async move { upload::receive(&web, &uri, &headers, body).await }
                },
            ),
        )
}

/// A static part of the page, with a policy that lets it run and fetch only from this origin;
/// images and videos may also come from the object store (presigned artifact URLs).
fn page(text: &'static str, media_type: &str) -> Response {
    Response::builder()
        .header(header::CONTENT_TYPE, format!("{media_type}; charset=utf-8"))
        .header(
            header::CONTENT_SECURITY_POLICY,
            "default-src 'self'; img-src * data:; media-src *; frame-ancestors 'none'",
        )
        .header(header::X_CONTENT_TYPE_OPTIONS, "nosniff")
        .header(header::CACHE_CONTROL, "no-cache")
        .body(Body::from(text))
        .unwrap_or_else(|e| (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response())
}

/// A JSON answer.
fn json(status: StatusCode, value: &impl serde::Serialize) -> Response {
    match serde_json::to_vec(value) {
        Ok(body) => Response::builder()
            .status(status)
            .header(header::CONTENT_TYPE, "application/json")
            .header(header::CACHE_CONTROL, "no-store")
            .body(Body::from(body))
            .unwrap_or_else(|e| (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response()),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// A gRPC status as Connect's JSON error: its code name, message and field violations, with
/// the HTTP status Connect maps the code to.
fn error(status: &Status) -> Response {
    use tonic::Code;
    use tonic_types::StatusExt;
    let (http, code) = match status.code() {
        Code::InvalidArgument => (StatusCode::BAD_REQUEST, "invalid_argument"),
        Code::Unauthenticated => (StatusCode::UNAUTHORIZED, "unauthenticated"),
        Code::PermissionDenied => (StatusCode::FORBIDDEN, "permission_denied"),
        Code::NotFound => (StatusCode::NOT_FOUND, "not_found"),
        Code::AlreadyExists => (StatusCode::CONFLICT, "already_exists"),
        Code::Aborted => (StatusCode::CONFLICT, "aborted"),
        Code::FailedPrecondition => (StatusCode::BAD_REQUEST, "failed_precondition"),
        Code::ResourceExhausted => (StatusCode::TOO_MANY_REQUESTS, "resource_exhausted"),
        Code::Unimplemented => (StatusCode::NOT_FOUND, "unimplemented"),
        Code::Unavailable => (StatusCode::SERVICE_UNAVAILABLE, "unavailable"),
        Code::DeadlineExceeded => (StatusCode::GATEWAY_TIMEOUT, "deadline_exceeded"),
        _ => (StatusCode::INTERNAL_SERVER_ERROR, "internal"),
    };
    let violations: Vec<serde_json::Value> = status
        .get_details_bad_request()
        .map(|bad| {
            bad.field_violations
                .into_iter()
                .map(|v| serde_json::json!({"field": v.field, "description": v.description}))
                .collect()
        })
        .unwrap_or_default();
    json(
        http,
        &serde_json::json!({
            "code": code,
            "message": status.message(),
            "violations": violations,
        }),
    )
}
