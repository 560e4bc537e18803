//! `stylenerf health`: the probe for container health checks and scripts. Asks a coordinator's
//! gRPC health service (exit 0 when it is SERVING, 1 when NOT_SERVING, e.g. draining) or, with
//! `--http`, a worker's `/healthz` (exit 0 on HTTP 200). The images need no other probe binary.

use std::io::{Read, Write};
use std::path::PathBuf;
use std::time::Duration;

use stylenerf_client::transport::{connect_channel, ConnectOptions};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

/// Options of `stylenerf health`.
#[derive(Debug, clap::Args)]
pub struct HealthArgs {
    /// Coordinator URL whose gRPC health to check
    #[arg(long, env = "STYLENERF_ENDPOINT", default_value = stylenerf_client::DEFAULT_ENDPOINT)]
    pub endpoint: String,
    /// PEM file of the CA that signed the coordinator's certificate (https endpoints)
    #[arg(long, env = "STYLENERF_CA_CERT")]
    pub ca_cert: Option<PathBuf>,
    /// Check an HTTP health URL instead, e.g. a worker's `http://127.0.0.1:9465/healthz`
    #[arg(long)]
    pub http: Option<String>,
    /// Give up after this many seconds
    #[arg(long, default_value_t = 5.0)]
    pub timeout_secs: f64,
}

pub fn run(args: HealthArgs) -> anyhow::Result<()> {
    let timeout = Duration::try_from_secs_f64(args.timeout_secs)
        .map_err(|e| anyhow::anyhow!("--timeout-secs {}: {e}", args.timeout_secs))?;
    if let Some(url) = &args.http {
        return check_http(url, timeout);
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let status = runtime.block_on(async {
        let mut options = ConnectOptions::new(&args.endpoint, None);
        options.ca_certificate = args.ca_cert.clone();
        options.connect_timeout = timeout;
        let (channel, endpoint) = connect_channel(&options).await?;
        let mut health = HealthClient::new(channel);
        let check = health.check(HealthCheckRequest {
            service: String::new(),
        });
        let reply = tokio::time::timeout(timeout, check)
            .await
            .map_err(|_| anyhow::anyhow!("{endpoint}: no health answer within {timeout:?}"))?
            .map_err(|s| anyhow::anyhow!("{endpoint}: health check failed: {}", s.message()))?;
        anyhow::Ok(reply.into_inner().status())
    })?;
    println!("{}", status.as_str_name());
    anyhow::ensure!(
        status == ServingStatus::Serving,
        "{}: {}",
        args.endpoint,
        status.as_str_name()
    );
    Ok(())
}

/// `GET url` over plain HTTP/1.1; succeeds on status 200.
fn check_http(url: &str, timeout: Duration) -> anyhow::Result<()> {
    let rest = url
        .strip_prefix("http://")
        .ok_or_else(|| anyhow::anyhow!("--http {url:?}: expected an http:// URL"))?;
    let (host, path) = rest.split_once('/').unwrap_or((rest, ""));
    let addr = std::net::ToSocketAddrs::to_socket_addrs(host)
        .map_err(|e| anyhow::anyhow!("--http {url:?}: {e}"))?
        .next()
        .ok_or_else(|| anyhow::anyhow!("--http {url:?}: the host has no address"))?;
    let mut stream = std::net::TcpStream::connect_timeout(&addr, timeout)
        .map_err(|e| anyhow::anyhow!("{url}: {e}"))?;
    stream.set_read_timeout(Some(timeout))?;
    write!(
        stream,
        "GET /{path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n"
    )?;
    let mut reply = String::new();
    stream
        .read_to_string(&mut reply)
        .map_err(|e| anyhow::anyhow!("{url}: {e}"))?;
    let status = reply.lines().next().unwrap_or_default();
    println!("{status}");
    anyhow::ensure!(
        status.split_whitespace().nth(1) == Some("200"),
        "{url}: {status}"
    );
    Ok(())
}
