//! The HTTP download endpoint (`--http-listen`): `GET /v1/artifacts/<key>?expires=<ms>&sig=<hex>`
//! streams one stored object to any HTTP client — a browser showing a job's animation, a web
//! backend copying results — with no token and no gRPC stream. The URL is what `GetArtifactUrl`
//! hands to a caller allowed to read the object: the coordinator signs the key and the expiry
//! with HMAC-SHA256 under its URL key, so a link cannot be altered to reach another object or
//! live longer, and it stops working at its expiry (or when the key changes).

use crate::model::now_ms;
use crate::state::Shared;
use axum::body::Body;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use futures::StreamExt;
use hmac::{KeyInit, Mac};
use std::sync::Arc;
use tokio::sync::watch;

type HmacSha256 = hmac::Hmac<sha2::Sha256>;

/// Signs and checks download URLs.
#[derive(Clone)]
pub struct UrlSigner {
    key: Arc<[u8]>,
}

impl std::fmt::Debug for UrlSigner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("UrlSigner(..)")
    }
}

impl UrlSigner {
    /// A signer with this secret key (at least 32 bytes).
    pub fn new(key: &[u8]) -> anyhow::Result<Self> {
        anyhow::ensure!(
            key.len() >= 32,
            "the URL signing key has {} bytes; it needs at least 32",
            key.len()
        );
        Ok(UrlSigner { key: key.into() })
    }

    /// A signer with a fresh random key: URLs stop working when the coordinator restarts.
    pub fn random() -> anyhow::Result<Self> {
        let mut key = [0u8; 32];
        getrandom::fill(&mut key).map_err(|e| anyhow::anyhow!("no random key: {e}"))?;
        Self::new(&key)
    }

    fn mac(&self, key: &str, expires_ms: i64) -> HmacSha256 {
        let mut mac = HmacSha256::new_from_slice(&self.key).expect("HMAC takes any key length");
        mac.update(key.as_bytes());
        mac.update(b"\n");
        mac.update(expires_ms.to_string().as_bytes());
        mac
    }

    /// The path and query of a signed URL for `key` (appended to the public base URL).
    pub fn path(&self, key: &str, expires_ms: i64) -> String {
        let sig = hex::encode(self.mac(key, expires_ms).finalize().into_bytes());
        let encoded: String = key
            .split('/')
            .map(|part| url::form_urlencoded::byte_serialize(part.as_bytes()).collect::<String>())
            .collect::<Vec<_>>()
            .join("/");
        format!("/v1/artifacts/{encoded}?expires={expires_ms}&sig={sig}")
    }

    /// Whether `sig` signs `key` until `expires_ms` (in constant time).
    fn verify(&self, key: &str, expires_ms: i64, sig: &str) -> bool {
        let Ok(sig) = hex::decode(sig) else {
            return false;
        };
        self.mac(key, expires_ms).verify_slice(&sig).is_ok()
    }
}

fn refuse(status: StatusCode, message: &str) -> Response {
    (status, format!("{message}\n")).into_response()
}

/// The media type browsers need to show an artifact.
fn content_type(key: &str) -> &'static str {
    match key.rsplit('.').next().unwrap_or("") {
        "png" => "image/png",
        "gif" => "image/gif",
        "jpg" | "jpeg" => "image/jpeg",
        "webp" => "image/webp",
        "mp4" => "video/mp4",
        "webm" => "video/webm",
        "json" => "application/json",
        "md" => "text/markdown; charset=utf-8",
        "txt" => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

async fn download(shared: Arc<Shared>, signer: UrlSigner, uri: axum::http::Uri) -> Response {
    let Some(encoded) = uri.path().strip_prefix("/v1/artifacts/") else {
        return refuse(StatusCode::NOT_FOUND, "not found");
    };
    let key: String = encoded
        .split('/')
        .map(|part| {
            url::form_urlencoded::parse(format!("k={part}").as_bytes())
                .next()
                .map(|(_, v)| v.into_owned())
                .unwrap_or_default()
        })
        .collect::<Vec<_>>()
        .join("/");
    let (mut expires, mut sig) = (None, None);
    for (name, value) in url::form_urlencoded::parse(uri.query().unwrap_or("").as_bytes()) {
        match name.as_ref() {
            "expires" => expires = value.parse::<i64>().ok(),
            "sig" => sig = Some(value.into_owned()),
            _ => {}
        }
    }
    let (Some(expires), Some(sig)) = (expires, sig) else {
        return refuse(
            StatusCode::FORBIDDEN,
            "this link is not signed (expires, sig)",
        );
    };
    if !signer.verify(&key, expires, &sig) {
        return refuse(
            StatusCode::FORBIDDEN,
            "this link's signature does not match",
        );
    }
    if expires < now_ms() {
        return refuse(StatusCode::FORBIDDEN, "this link has expired");
    }
    let size = match shared.storage.size(&key).await {
        Ok(size) => size,
        Err(s) if s.code() == tonic::Code::NotFound => {
            return refuse(StatusCode::NOT_FOUND, "the object no longer exists")
        }
        Err(s) => return refuse(StatusCode::INTERNAL_SERVER_ERROR, s.message()),
    };
    let stream = match shared.storage.get_stream(&key, 0).await {
        Ok(stream) => stream.map(|chunk| chunk.map(|c| bytes::Bytes::from(c.data))),
        Err(s) => return refuse(StatusCode::INTERNAL_SERVER_ERROR, s.message()),
    };
    let name = key
        .rsplit('/')
        .next()
        .unwrap_or("artifact")
        .replace('"', "");
    Response::builder()
        .header(header::CONTENT_TYPE, content_type(&key))
        .header(header::CONTENT_LENGTH, size)
        .header(
            header::CONTENT_DISPOSITION,
            format!("inline; filename=\"{name}\""),
        )
        .header(header::CACHE_CONTROL, "private, max-age=300")
        .body(Body::from_stream(stream))
        .unwrap_or_else(|e| refuse(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()))
}

/// Where signed URLs point and how they are signed.
#[derive(Debug, Clone)]
pub struct Downloads {
    pub signer: UrlSigner,
    /// Base URL clients reach the endpoint at, without a trailing `/`.
    pub public_url: String,
}

/// Serves the download endpoint, with the web page and its JSON API (`web`), on `listener`
/// until `shutdown` turns true.
pub fn serve(
    listener: tokio::net::TcpListener,
    shared: Arc<Shared>,
    signer: UrlSigner,
    shutdown: watch::Receiver<bool>,
) -> tokio::task::JoinHandle<()> {
    let web = crate::web::router(shared.clone());
    let app = axum::Router::new()
        .route(
            "/v1/artifacts/{*key}",
            axum::routing::get(move |uri: axum::http::Uri| {
                download(shared.clone(), signer.clone(), uri)
            }),
        )
        .merge(web);
    crate::metrics_http::spawn_router(listener, app, shutdown, "HTTP endpoint")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signatures_bind_the_key_and_the_expiry() {
        let signer = UrlSigner::new(&[7u8; 32]).unwrap();
        let path = signer.path("jobs/j-1/render_stylized/a b.gif", 1000);
        assert!(
            path.starts_with("/v1/artifacts/jobs/j-1/render_stylized/a+b.gif?expires=1000&sig=")
        );
        let sig = path.rsplit("sig=").next().unwrap();
        assert!(signer.verify("jobs/j-1/render_stylized/a b.gif", 1000, sig));
        assert!(!signer.verify("jobs/j-2/render_stylized/a b.gif", 1000, sig));
        assert!(!signer.verify("jobs/j-1/render_stylized/a b.gif", 1001, sig));
        let other = UrlSigner::new(&[8u8; 32]).unwrap();
        assert!(!other.verify("jobs/j-1/render_stylized/a b.gif", 1000, sig));
        assert!(UrlSigner::new(&[1u8; 16]).is_err());
    }
}
