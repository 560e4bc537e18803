//! Per-RPC metrics of the gRPC server: a tower layer that records every call's latency (to its
//! response headers: the whole call for unary RPCs, the time to the first message for streams)
//! in `stylenerf_rpc_duration_seconds`, by method and status code. Only the methods the server
//! serves become label values; any other path a client sends is counted as `unknown`, so a
//! hostile client cannot grow the label set.

use std::collections::HashSet;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

use prost::Message;

/// The layer: wraps each service of the router.
#[derive(Clone)]
pub struct RpcMetricsLayer {
    methods: Arc<HashSet<String>>,
}

impl RpcMetricsLayer {
    /// Counts the methods of the services described by these encoded descriptor sets.
    pub fn new(descriptor_sets: &[&[u8]]) -> anyhow::Result<Self> {
        let mut methods = HashSet::new();
        for encoded in descriptor_sets {
            let set = prost_types::FileDescriptorSet::decode(*encoded)?;
            for file in set.file {
                for service in &file.service {
                    for method in &service.method {
                        methods.insert(format!(
                            "/{}.{}/{}",
                            file.package(),
                            service.name(),
                            method.name()
                        ));
                    }
                }
            }
        }
        Ok(RpcMetricsLayer {
            methods: Arc::new(methods),
        })
    }
}

impl<S> tower::Layer<S> for RpcMetricsLayer {
    type Service = RpcMetrics<S>;

    fn layer(&self, inner: S) -> Self::Service {
        RpcMetrics {
            inner,
            methods: self.methods.clone(),
        }
    }
}

/// A service wrapped by [`RpcMetricsLayer`].
#[derive(Clone)]
pub struct RpcMetrics<S> {
    inner: S,
    methods: Arc<HashSet<String>>,
}

impl<S, B, R> tower::Service<http::Request<B>> for RpcMetrics<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<S::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let path = request.uri().path();
        let method = if self.methods.contains(path) {
            path.to_string()
        } else {
            "unknown".to_string()
        };
        let started = Instant::now();
        let response = self.inner.call(request);
        Box::pin(async move {
            let response = response.await;
            // An error status before any message comes in the headers ("trailers-only");
            // otherwise it comes in the trailers, after what is measured here.
            let code = match &response {
                Ok(response) => response
                    .headers()
                    .get("grpc-status")
                    .and_then(|v| v.to_str().ok())
                    .and_then(|v| v.parse::<i32>().ok())
                    .map_or(tonic::Code::Ok, tonic::Code::from),
                Err(_) => tonic::Code::Unknown,
            };
            metrics::histogram!(
                "stylenerf_rpc_duration_seconds",
                "method" => method,
                "code" => format!("{code:?}"),
            )
            .record(started.elapsed().as_secs_f64());
            response
        })
    }
}
