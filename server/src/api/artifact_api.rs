//! `ArtifactService`: object access under `jobs/` for workers without direct store access,
//! limited to the jobs the caller's workers hold leases on.

use crate::auth::{require, Principal, Role, WORKER_ROLES};
use crate::errors::invalid;
use crate::scheduler;
use crate::state::Shared;
use crate::storage::{check_key, check_prefix, check_sha256};
use futures::StreamExt;
use std::pin::Pin;
use std::sync::Arc;
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::artifact_service_server::ArtifactService;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

pub struct ArtifactApi {
    pub shared: Arc<Shared>,
}

/// Checks that a worker may reach `key` (an object key, or a listing prefix with `prefix`):
/// it must lie under `jobs/<job>/` of a job on which the caller holds a live lease, and a
/// write must fall in the leased task's output prefix. Admins may read any job's objects.
async fn check_worker_key(
    shared: &Shared,
    caller: &Principal,
    field: &str,
    key: &str,
    access: Access,
) -> Result<(), Status> {
    match access {
        Access::List => check_prefix(field, key)?,
        Access::Read | Access::Write => check_key(field, key)?,
    }
    let job_id = key
        .strip_prefix("jobs/")
        .and_then(|rest| rest.split_once('/'))
        .map(|(job, _)| job)
        .filter(|job| !job.is_empty())
        .ok_or_else(|| invalid(field, "workers may only access keys under jobs/<job>/"))?;
    let writing = access == Access::Write;
    if caller.role == Role::Admin && !writing {
        return Ok(());
    }
    if scheduler::worker_may_access(shared, caller, job_id, key, writing).await? {
        Ok(())
    } else {
        Err(Status::permission_denied(format!(
            "{field}: {key:?} is outside the tasks your workers hold leases on"
        )))
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Access {
    Read,
    List,
    Write,
}

#[tonic::async_trait]
impl ArtifactService for ArtifactApi {
    async fn put_object(
        &self,
        request: Request<Streaming<pb::PutObjectChunk>>,
    ) -> Result<Response<pb::Artifact>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let mut stream = request.into_inner();
        let header = match stream.next().await {
            Some(Ok(pb::PutObjectChunk {
                part: Some(pb::put_object_chunk::Part::Header(header)),
            })) => header,
            Some(Err(status)) => return Err(status),
            _ => return Err(invalid("header", "the first message must be the header")),
        };
        check_worker_key(
            &self.shared,
            &caller,
            "header.key",
            &header.key,
            Access::Write,
        )
        .await?;
        check_sha256("header.sha256", &header.sha256)?;
        let limit = self.shared.config.limits.max_object_bytes;
        if header.size > limit {
            return Err(invalid(
                "header.size",
                format!("more than the limit of {limit} bytes"),
            ));
        }
        let data = stream.map(|message| match message?.part {
            Some(pb::put_object_chunk::Part::Data(data)) => Ok(data),
            _ => Err(invalid("header", "only the first message may be a header")),
        });
        self.shared
            .storage
            .put_verified(&header.key, header.size, &header.sha256, Box::pin(data))
            .await?;
        Ok(Response::new(pb::Artifact {
            key: header.key,
            size: header.size,
            sha256: header.sha256,
        }))
    }

    type GetObjectStream = Pin<Box<dyn Stream<Item = Result<pb::ObjectChunk, Status>> + Send>>;

    async fn get_object(
        &self,
        request: Request<pb::GetObjectRequest>,
    ) -> Result<Response<Self::GetObjectStream>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        check_worker_key(&self.shared, &caller, "key", &req.key, Access::Read).await?;
        let stream = self.shared.storage.get_stream(&req.key, req.offset).await?;
        Ok(Response::new(Box::pin(stream)))
    }

    async fn list_objects(
        &self,
        request: Request<pb::ListObjectsRequest>,
    ) -> Result<Response<pb::ListObjectsResponse>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        check_worker_key(&self.shared, &caller, "prefix", &req.prefix, Access::List).await?;
        let objects = self
            .shared
            .storage
            .list(&req.prefix)
            .await?
            .into_iter()
            .map(|(key, size)| pb::Artifact {
                key,
                size,
                sha256: String::new(),
            })
            .collect();
        Ok(Response::new(pb::ListObjectsResponse { objects }))
    }
}
