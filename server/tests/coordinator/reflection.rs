//! Server reflection as grpcurl and generated-stub tools use it, in both protocol versions
//! (v1, and v1alpha that grpcurl 1.8 and Python's reflection client still ask for): the
//! services are listed, and the error-detail messages our statuses carry
//! (`google.rpc.BadRequest`) resolve to their file descriptor.

use stylenerf_testkit::*;

/// Asks one reflection version: (services listed, descriptors of `google.rpc.BadRequest`).
macro_rules! ask {
    ($version:ident, $channel:expr) => {{
        use tonic_reflection::pb::$version::server_reflection_client::ServerReflectionClient;
        use tonic_reflection::pb::$version::server_reflection_request::MessageRequest;
        use tonic_reflection::pb::$version::server_reflection_response::MessageResponse;
        use tonic_reflection::pb::$version::ServerReflectionRequest;
        let requests = [
            MessageRequest::ListServices(String::new()),
            MessageRequest::FileContainingSymbol("google.rpc.BadRequest".into()),
        ]
        .map(|request| ServerReflectionRequest {
            host: String::new(),
            message_request: Some(request),
        });
        let mut replies = ServerReflectionClient::new($channel)
            .server_reflection_info(tokio_stream::iter(requests))
            .await
            .expect("reflection answers")
            .into_inner();
        let mut services = Vec::new();
        let mut descriptors = 0;
        while let Some(reply) = replies.message().await.unwrap() {
            match reply.message_response.expect("a response") {
                MessageResponse::ListServicesResponse(list) => {
                    services.extend(list.service.into_iter().map(|s| s.name))
                }
                MessageResponse::FileDescriptorResponse(files) => {
                    descriptors += files.file_descriptor_proto.len()
                }
                other => panic!("unexpected reply {other:?}"),
            }
        }
        (services, descriptors)
    }};
}

#[tokio::test]
async fn reflection_answers_v1_and_v1alpha_with_the_error_details() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let (v1, v1_files) = ask!(v1, channel(&server).await);
    let (alpha, alpha_files) = ask!(v1alpha, channel(&server).await);
    for services in [&v1, &alpha] {
        for service in [
            "stylenerf.v1.JobService",
            "stylenerf.v1.WorkerService",
            "stylenerf.v1.ArtifactService",
            "grpc.health.v1.Health",
        ] {
            assert!(
                services.iter().any(|s| s == service),
                "{service}: {services:?}"
            );
        }
    }
    assert!(v1_files > 0 && alpha_files > 0, "{v1_files} {alpha_files}");
    server.shutdown().await.unwrap();
}
