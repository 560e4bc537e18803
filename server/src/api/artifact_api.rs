//! `ArtifactService`: object access under `jobs/` for workers without direct store access.

use crate::auth::{require, WORKER_ROLES};
use crate::errors::invalid;
use crate::state::Shared;
use crate::storage::{check_key, check_sha256};
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

#[allow(clippy::result_large_err)]
fn check_job_key(field: &str, key: &str) -> Result<(), Status> {
    check_key(field, key)?;
    if !key.starts_with("jobs/") {
        return Err(invalid(field, "workers may only access keys under jobs/"));
    }
    Ok(())
}

#[tonic::async_trait]
impl ArtifactService for ArtifactApi {
    async fn put_object(
        &self,
        request: Request<Streaming<pb::PutObjectChunk>>,
    ) -> Result<Response<pb::Artifact>, Status> {
        require(&request, WORKER_ROLES)?;
        let mut stream = request.into_inner();
        let header = match stream.next().await {
            Some(Ok(pb::PutObjectChunk {
                part: Some(pb::put_object_chunk::Part::Header(header)),
            })) => header,
            Some(Err(status)) => return Err(status),
            _ => return Err(invalid("header", "the first message must be the header")),
        };
        check_job_key("header.key", &header.key)?;
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
        require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        check_job_key("key", &req.key)?;
        let stream = self.shared.storage.get_stream(&req.key, req.offset).await?;
        Ok(Response::new(Box::pin(stream)))
    }

    async fn list_objects(
        &self,
        request: Request<pb::ListObjectsRequest>,
    ) -> Result<Response<pb::ListObjectsResponse>, Status> {
        require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        check_job_key("prefix", &req.prefix)?;
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
