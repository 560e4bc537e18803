//! TLS: a coordinator serving a self-signed `localhost` certificate generated at test time
//! (DER written here, signed with `ring`, which rustls already builds on) answers a client that
//! trusts the certificate; a client that does not trust it, or that speaks plaintext, gets no
//! answer.

use std::time::Duration;
use stylenerf_server::proto::v1 as pb;
use stylenerf_server::TlsConfig;
use stylenerf_testkit::*;
use tonic::transport::{Certificate, Channel, ClientTlsConfig};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

/// A DER element: tag, definite length, content.
fn der(tag: u8, content: &[u8]) -> Vec<u8> {
    let n = content.len();
    let mut out = vec![tag];
    match n {
        0..0x80 => out.push(n as u8),
        0x80..0x100 => out.extend([0x81, n as u8]),
        _ => out.extend([0x82, (n >> 8) as u8, n as u8]),
    }
    out.extend_from_slice(content);
    out
}

fn sequence(parts: &[&[u8]]) -> Vec<u8> {
    der(0x30, &parts.concat())
}

fn pem(label: &str, der: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut text = String::new();
    for chunk in der.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            text.push(if i <= chunk.len() {
                ALPHABET[(n >> (18 - 6 * i) & 63) as usize] as char
            } else {
                '='
            });
        }
    }
    let lines: Vec<&str> = text
        .as_bytes()
        .chunks(64)
        .map(|l| std::str::from_utf8(l).unwrap())
        .collect();
    format!(
        "-----BEGIN {label}-----\n{}\n-----END {label}-----\n",
        lines.join("\n")
    )
}

/// A fresh self-signed ECDSA P-256 certificate for `localhost` (X.509 v3 with a DNS
/// subjectAltName, valid 2025-2099) and its PKCS#8 key, as PEM, made with `ring` at test time.
fn self_signed_localhost() -> (String, String) {
    use ring::rand::SystemRandom;
    use ring::signature::{EcdsaKeyPair, KeyPair, ECDSA_P256_SHA256_ASN1_SIGNING as ALG};
    let rng = SystemRandom::new();
    let pkcs8 = EcdsaKeyPair::generate_pkcs8(&ALG, &rng).unwrap();
    let key = EcdsaKeyPair::from_pkcs8(&ALG, pkcs8.as_ref(), &rng).unwrap();
    let ecdsa_sha256 = sequence(&[&der(
        0x06,
        &[0x2a, 0x86, 0x48, 0xce, 0x3d, 0x04, 0x03, 0x02],
    )]);
    let name = sequence(&[&der(
        0x31,
        &sequence(&[
            &der(0x06, &[0x55, 0x04, 0x03]),
            &der(0x0c, b"stylenerf test"),
        ]),
    )]);
    let validity = sequence(&[&der(0x17, b"250101000000Z"), &der(0x18, b"20991231235959Z")]);
    let algorithm = sequence(&[
        &der(0x06, &[0x2a, 0x86, 0x48, 0xce, 0x3d, 0x02, 0x01]),
        &der(0x06, &[0x2a, 0x86, 0x48, 0xce, 0x3d, 0x03, 0x01, 0x07]),
    ]);
    let public_key = der(0x03, &[&[0u8][..], key.public_key().as_ref()].concat());
    let spki = sequence(&[&algorithm, &public_key]);
    let san = sequence(&[
        &der(0x06, &[0x55, 0x1d, 0x11]),
        &der(0x04, &sequence(&[&der(0x82, b"localhost")])),
    ]);
    let extensions = der(0xa3, &sequence(&[&san]));
    let tbs = sequence(&[
        &der(0xa0, &der(0x02, &[2])),
        &der(0x02, &[0x01]),
        &ecdsa_sha256,
        &name,
        &validity,
        &name,
        &spki,
        &extensions,
    ]);
    let signature = key.sign(&rng, &tbs).unwrap();
    let signature = der(0x03, &[&[0u8][..], signature.as_ref()].concat());
    let certificate = sequence(&[&tbs, &ecdsa_sha256, &signature]);
    (
        pem("CERTIFICATE", &certificate),
        pem("PRIVATE KEY", pkcs8.as_ref()),
    )
}

#[tokio::test]
async fn serves_grpc_over_tls_to_clients_that_trust_its_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let (cert, key) = self_signed_localhost();
    let (cert_path, key_path) = (dir.path().join("cert.pem"), dir.path().join("key.pem"));
    std::fs::write(&cert_path, &cert).unwrap();
    std::fs::write(&key_path, key).unwrap();
    let mut config = config(dir.path());
    config.tls = Some(TlsConfig {
        cert: cert_path,
        key: key_path,
    });
    let server = start(config).await;
    let endpoint = server.endpoint();
    assert!(endpoint.starts_with("https://127.0.0.1:"), "{endpoint}");

    // Trusting the certificate: health (no token) and an authenticated job call both work.
    let tls = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(&cert))
        .domain_name("localhost");
    let channel = Channel::from_shared(endpoint.clone())
        .unwrap()
        .tls_config(tls)
        .unwrap()
        .connect()
        .await
        .expect("TLS connection trusting the certificate");
    let health = HealthClient::new(channel.clone())
        .check(HealthCheckRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert_eq!(health.status(), ServingStatus::Serving);
    let mut jobs =
        pb::job_service_client::JobServiceClient::with_interceptor(channel, bearer(Some(ALICE)));
    let listed = jobs
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .expect("authenticated call over TLS")
        .into_inner();
    assert!(listed.jobs.is_empty());

    // Not trusting it: the handshake fails.
    let untrusted = Channel::from_shared(endpoint.clone())
        .unwrap()
        .tls_config(ClientTlsConfig::new().domain_name("localhost"))
        .unwrap()
        .connect_timeout(Duration::from_secs(5))
        .connect()
        .await;
    assert!(
        untrusted.is_err(),
        "a client that does not trust the certificate must not connect"
    );

    // Plaintext HTTP/2 to the TLS port: no answer.
    let plain = Channel::from_shared(format!("http://{}", server.local_addr()))
        .unwrap()
        .timeout(Duration::from_secs(5))
        .connect_lazy();
    let reply = HealthClient::new(plain)
        .check(HealthCheckRequest::default())
        .await;
    assert!(reply.is_err(), "plaintext must be refused: {reply:?}");
    server.shutdown().await.unwrap();
}
