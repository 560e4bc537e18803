//! The gRPC connection to the coordinator: one channel (plain or TLS) shared by the worker and
//! artifact clients, with the worker token sent as `authorization: Bearer <token>`.

use std::path::Path;

use anyhow::Context;
use stylenerf_proto::v1::artifact_service_client::ArtifactServiceClient;
use stylenerf_proto::v1::worker_service_client::WorkerServiceClient;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint};

/// Largest message accepted from the coordinator (download chunks are 1 MiB).
const MAX_MESSAGE_BYTES: usize = 16 << 20;

pub use stylenerf_proto::bearer::{Authed, Bearer};

/// The two services a worker calls.
#[derive(Clone)]
pub struct Clients {
    pub workers: WorkerServiceClient<Authed>,
    pub artifacts: ArtifactServiceClient<Authed>,
}

impl Clients {
    /// Connects to `endpoint` (`http://host:port` or `https://…`). `token` is the worker (or
    /// admin) token; `ca_cert` a PEM file of the CA that signed the coordinator's certificate.
    pub async fn connect(
        endpoint: &str,
        token: Option<&str>,
        ca_cert: Option<&Path>,
    ) -> anyhow::Result<Self> {
        let mut ep = Endpoint::from_shared(endpoint.to_string())
            .with_context(|| format!("--endpoint: `{endpoint}` is not a valid URL"))?
            .tcp_nodelay(true)
            .keep_alive_while_idle(true)
            .http2_keep_alive_interval(std::time::Duration::from_secs(30));
        if endpoint.starts_with("https://") {
            let mut tls = ClientTlsConfig::new();
            match ca_cert {
                Some(path) => {
                    let pem = std::fs::read(path)
                        .with_context(|| format!("--ca-cert: reading {}", path.display()))?;
                    tls = tls.ca_certificate(Certificate::from_pem(pem));
                }
                None => anyhow::bail!(
                    "--endpoint {endpoint}: a TLS endpoint needs --ca-cert (the PEM certificate \
                     of the CA that signed the coordinator's certificate)"
                ),
            }
            ep = ep.tls_config(tls).context("TLS configuration")?;
        }
        // Connected on first use and reconnected after a drop: a worker may start before its
        // coordinator (the calls then wait, see `retry::patient`).
        let channel = ep.connect_lazy();
        let bearer = Bearer::new(token).context("--token")?;
        Ok(Self {
            workers: WorkerServiceClient::with_interceptor(channel.clone(), bearer.clone())
                .max_decoding_message_size(MAX_MESSAGE_BYTES),
            artifacts: ArtifactServiceClient::with_interceptor(channel, bearer)
                .max_decoding_message_size(MAX_MESSAGE_BYTES),
        })
    }
}
