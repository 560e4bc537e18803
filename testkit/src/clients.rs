//! gRPC clients of a test coordinator that carry a token (or none, to test refusals).

pub use stylenerf_proto::bearer::Authed;
use stylenerf_proto::bearer::Bearer;
use stylenerf_proto::v1::artifact_service_client::ArtifactServiceClient;
use stylenerf_proto::v1::job_service_client::JobServiceClient;
use stylenerf_proto::v1::worker_service_client::WorkerServiceClient;
use stylenerf_server::CoordinatorHandle;
use tonic::transport::Channel;

pub async fn channel(handle: &CoordinatorHandle) -> Channel {
    Channel::from_shared(handle.endpoint())
        .unwrap()
        .connect()
        .await
        .expect("connects")
}

/// The interceptor of `token` (`None`: no `authorization` header).
pub fn bearer(token: Option<&str>) -> Bearer {
    Bearer::new(token).expect("a test token fits a header")
}

pub async fn jobs_client(
    handle: &CoordinatorHandle,
    token: Option<&str>,
) -> JobServiceClient<Authed> {
    JobServiceClient::with_interceptor(channel(handle).await, bearer(token))
}

pub async fn worker_client(
    handle: &CoordinatorHandle,
    token: Option<&str>,
) -> WorkerServiceClient<Authed> {
    WorkerServiceClient::with_interceptor(channel(handle).await, bearer(token))
}

pub async fn artifact_client(
    handle: &CoordinatorHandle,
    token: Option<&str>,
) -> ArtifactServiceClient<Authed> {
    ArtifactServiceClient::with_interceptor(channel(handle).await, bearer(token))
}
