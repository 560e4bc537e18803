//! `POST /stylenerf.v1.JobService/<Method>`: a unary `JobService` call with proto JSON in and
//! out, run by the same code as the gRPC call (the caller's principal in the request
//! extensions), and `ListEvents`, the stored events of a job for the page's plots.

use super::{error, json, Web};
use crate::errors::{internal, invalid};
use axum::http::{HeaderMap, StatusCode};
use axum::response::Response;
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::job_service_server::JobService;
use tonic::Status;

/// Most events one `ListEvents` answer holds (page on with `afterSeq`).
const EVENTS_PER_PAGE: i64 = 5000;

/// The body of `ListEvents`.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ListEvents {
    #[serde(alias = "jobId")]
    job_id: String,
    #[serde(default, alias = "afterSeq")]
    after_seq: i64,
}

#[derive(serde::Serialize)]
struct EventPage {
    events: Vec<pb::Event>,
}

/// Runs one call; every failure is a Connect-style JSON error.
pub async fn call(web: &Web, method: &str, headers: &HeaderMap, body: &[u8]) -> Response {
    let result = async {
        let caller = web.caller(headers)?;
        dispatch(web, caller, method, body).await
    }
    .await;
    match result {
        Ok(response) => response,
        Err(status) => error(&status),
    }
}

/// Decodes the proto JSON body of `method`.
#[allow(clippy::result_large_err)]
fn decode<T: serde::de::DeserializeOwned + Default>(body: &[u8]) -> Result<T, Status> {
    if body.iter().all(u8::is_ascii_whitespace) {
        return Ok(T::default());
    }
    serde_json::from_slice(body)
        .map_err(|e| invalid("body", format!("not the request's JSON: {e}")))
}

async fn dispatch(
    web: &Web,
    caller: crate::auth::Principal,
    method: &str,
    body: &[u8],
) -> Result<Response, Status> {
    let api = web.api.as_ref();
    // Each arm: decode the request, call the service as gRPC would, encode the response.
    macro_rules! unary {
        ($method:ident) => {{
            let mut request = tonic::Request::new(decode(body)?);
            request.extensions_mut().insert(caller);
            let response = JobService::$method(api, request).await?.into_inner();
            Ok(json(StatusCode::OK, &response))
        }};
    }
    match method {
        "CreateJob" => unary!(create_job),
        "GetJob" => unary!(get_job),
        "ListJobs" => unary!(list_jobs),
        "CancelJob" => unary!(cancel_job),
        "ListArtifacts" => unary!(list_artifacts),
        "GetArtifactUrl" => unary!(get_artifact_url),
        "RenderJob" => unary!(render_job),
        "DeleteJob" => unary!(delete_job),
        "ListWebhookDeliveries" => unary!(list_webhook_deliveries),
        "StartUpload" => unary!(start_upload),
        "GetUploadSession" => unary!(get_upload_session),
        "FinishUpload" => unary!(finish_upload),
        "ListEvents" => {
            crate::auth::require_role(&caller, crate::auth::CLIENT_ROLES)?;
            let request: ListEvents = serde_json::from_slice(body)
                .map_err(|e| invalid("body", format!("expected {{job_id, after_seq}}: {e}")))?;
            let shared = web.shared();
            crate::jobs::visible_job(&shared.db.read, &caller, &request.job_id).await?;
            let events = crate::events::read_after(
                &shared.db.read,
                &crate::events::Scope::Job(request.job_id),
                request.after_seq,
                EVENTS_PER_PAGE,
            )
            .await
            .map_err(internal)?;
            Ok(json(StatusCode::OK, &EventPage { events }))
        }
        "Upload" | "WatchJob" | "WatchJobs" | "DownloadArtifact" | "AppendUpload" => {
            Err(Status::unimplemented(format!(
                "{method} streams: call it over gRPC (the page uploads with POST /upload and \
                 downloads through GetArtifactUrl)"
            )))
        }
        other => Err(Status::unimplemented(format!(
            "JobService has no method {other:?}"
        ))),
    }
}
