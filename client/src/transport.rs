//! Connecting to a coordinator: endpoint normalisation (`host:port` means `http://host:port`),
//! TLS for `https://` endpoints (a given CA file, else the system's CA bundle), connect
//! timeouts, and the bearer-token interceptor added to every call. Workers and tools that talk
//! to other services of the coordinator can reuse `connect_channel` and [`Bearer`].

use crate::error::{error_chain, ClientError, Result};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};

/// The coordinator's default listen address (`stylenerf coordinator` without `--listen`).
pub const DEFAULT_ENDPOINT: &str = "http://127.0.0.1:50051";

/// Where the system keeps its CA bundle on common platforms (first readable one wins);
/// `SSL_CERT_FILE` takes precedence.
const SYSTEM_CA_BUNDLES: &[&str] = &[
    "/etc/ssl/certs/ca-certificates.crt",
    "/etc/pki/tls/certs/ca-bundle.crt",
    "/etc/ssl/ca-bundle.pem",
    "/etc/ssl/cert.pem",
];

/// How to connect.
#[derive(Debug, Clone)]
pub struct ConnectOptions {
    /// `http://host:port`, `https://host:port` or `host:port` (plain HTTP/2).
    pub endpoint: String,
    /// Bearer token; `None` for a coordinator running with `--insecure-no-auth`.
    pub token: Option<String>,
    /// PEM file of the CA (or self-signed certificate) that signed the coordinator's
    /// certificate, for `https://` endpoints. Without it the system CA bundle is used.
    pub ca_certificate: Option<PathBuf>,
    /// Server name to verify instead of the endpoint's host (e.g. when connecting by IP).
    pub tls_domain: Option<String>,
    /// Longest wait for the TCP (and TLS) connection.
    pub connect_timeout: Duration,
}

impl ConnectOptions {
    pub fn new(endpoint: impl Into<String>, token: Option<String>) -> Self {
        ConnectOptions {
            endpoint: endpoint.into(),
            token,
            ca_certificate: None,
            tls_domain: None,
            connect_timeout: Duration::from_secs(10),
        }
    }
}

/// `host:port` → `http://host:port`; trims whitespace and a trailing `/`.
pub fn normalize_endpoint(endpoint: &str) -> String {
    let trimmed = endpoint.trim().trim_end_matches('/');
    if trimmed.contains("://") {
        trimmed.to_string()
    } else {
        format!("http://{trimmed}")
    }
}

fn read_pem(path: &Path, endpoint: &str) -> Result<Certificate> {
    let pem = std::fs::read(path).map_err(|e| ClientError::Tls {
        endpoint: endpoint.to_string(),
        reason: format!("reading CA certificate {}: {e}", path.display()),
    })?;
    if !String::from_utf8_lossy(&pem).contains("-----BEGIN CERTIFICATE-----") {
        return Err(ClientError::Tls {
            endpoint: endpoint.to_string(),
            reason: format!("{} holds no PEM certificate", path.display()),
        });
    }
    Ok(Certificate::from_pem(pem))
}

/// The CA certificates to trust: the given file, else `SSL_CERT_FILE`, else the system bundle.
fn trust_roots(options: &ConnectOptions, endpoint: &str) -> Result<Certificate> {
    if let Some(path) = &options.ca_certificate {
        return read_pem(path, endpoint);
    }
    let from_env = std::env::var_os("SSL_CERT_FILE").map(PathBuf::from);
    let candidates = from_env
        .into_iter()
        .chain(SYSTEM_CA_BUNDLES.iter().map(PathBuf::from));
    for path in candidates {
        if path.is_file() {
            return read_pem(&path, endpoint);
        }
    }
    Err(ClientError::Tls {
        endpoint: endpoint.to_string(),
        reason: "no CA certificates: give the coordinator's CA with --ca-cert (or \
                 STYLENERF_CA_CERT / SSL_CERT_FILE)"
            .into(),
    })
}

/// The tonic endpoint for `options`, with TLS configured for `https://`.
pub fn endpoint(options: &ConnectOptions) -> Result<Endpoint> {
    let url = normalize_endpoint(&options.endpoint);
    let invalid = |reason: String| ClientError::InvalidEndpoint {
        endpoint: options.endpoint.clone(),
        reason,
    };
    let scheme = url.split("://").next().unwrap_or_default();
    if scheme != "http" && scheme != "https" {
        return Err(invalid(format!(
            "unsupported scheme {scheme:?} (use http:// or https://)"
        )));
    }
    let mut endpoint = Endpoint::from_shared(url.clone())
        .map_err(|e| invalid(error_chain(&e)))?
        .connect_timeout(options.connect_timeout)
        .tcp_nodelay(true)
        .http2_keep_alive_interval(Duration::from_secs(30))
        .keep_alive_while_idle(true);
    if scheme == "https" {
        let mut tls = ClientTlsConfig::new().ca_certificate(trust_roots(options, &url)?);
        if let Some(domain) = &options.tls_domain {
            tls = tls.domain_name(domain.clone());
        }
        endpoint = endpoint.tls_config(tls).map_err(|e| ClientError::Tls {
            endpoint: url.clone(),
            reason: error_chain(&e),
        })?;
    }
    Ok(endpoint)
}

/// Connects now (so an unreachable coordinator is reported at once). Returns the channel and
/// the normalised endpoint URL.
pub async fn connect_channel(options: &ConnectOptions) -> Result<(Channel, String)> {
    let endpoint = endpoint(options)?;
    let url = endpoint.uri().to_string().trim_end_matches('/').to_string();
    let channel = endpoint
        .connect()
        .await
        .map_err(|e| ClientError::Unreachable {
            endpoint: url.clone(),
            reason: error_chain(&e),
        })?;
    Ok((channel, url))
}

/// The bearer-token interceptor and the channel type whose calls carry it.
pub use stylenerf_proto::bearer::{Authed as AuthedChannel, Bearer};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_normalised() {
        assert_eq!(
            normalize_endpoint("localhost:50051"),
            "http://localhost:50051"
        );
        assert_eq!(
            normalize_endpoint(" https://coord.example:443/ "),
            "https://coord.example:443"
        );
        let err = endpoint(&ConnectOptions::new("ftp://x:1", None)).unwrap_err();
        assert!(err.to_string().contains("unsupported scheme"), "{err}");
    }
}
