//! Bearer-token authentication and roles. Tokens are configured as `role:name:token` entries
//! and kept only as SHA-256 digests; an interceptor resolves the `authorization` header to a
//! `Principal` that the services check against the roles they accept.

use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::Arc;
use tonic::{Request, Status};

/// What a token may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Submit jobs and read its own jobs.
    Client,
    /// Lease, heartbeat, complete and fail tasks; read and write job objects.
    Worker,
    /// Everything, on every job.
    Admin,
}

impl Role {
    fn parse(s: &str) -> Option<Role> {
        match s {
            "client" => Some(Role::Client),
            "worker" => Some(Role::Worker),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }
}

/// The authenticated caller, stored in the request extensions.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Principal {
    pub name: String,
    pub role: Role,
}

impl Principal {
    /// Whether the caller may see jobs owned by `owner`.
    pub fn can_see(&self, owner: &str) -> bool {
        self.role == Role::Admin || self.name == owner
    }
}

/// One configured token.
#[derive(Clone, PartialEq, Eq)]
pub struct TokenEntry {
    pub role: Role,
    pub name: String,
    pub token: String,
}

impl std::fmt::Debug for TokenEntry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TokenEntry")
            .field("role", &self.role)
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}

impl TokenEntry {
    /// Parses `role:name:token` entries separated by newlines or commas; blank lines and lines
    /// starting with `#` are skipped (a `#` elsewhere belongs to the token). A token listed
    /// twice is an error: it would silently get one of the two roles.
    pub fn parse_list(text: &str) -> anyhow::Result<Vec<TokenEntry>> {
        let mut out: Vec<TokenEntry> = Vec::new();
        for (n, line) in text.lines().enumerate() {
            if line.trim_start().starts_with('#') {
                continue;
            }
            for entry in line.split(',').map(str::trim).filter(|e| !e.is_empty()) {
                let mut parts = entry.splitn(3, ':');
                let (role, name, token) = match (parts.next(), parts.next(), parts.next()) {
                    (Some(r), Some(n), Some(t)) => (r.trim(), n.trim(), t.trim()),
                    _ => anyhow::bail!("line {}: expected role:name:token", n + 1),
                };
                let role = Role::parse(role).ok_or_else(|| {
                    anyhow::anyhow!(
                        "line {}: unknown role {role:?} (client, worker or admin)",
                        n + 1
                    )
                })?;
                anyhow::ensure!(!name.is_empty(), "line {}: empty name", n + 1);
                anyhow::ensure!(
                    token.len() >= 16,
                    "line {}: token of {name:?} is shorter than 16 characters",
                    n + 1
                );
                if let Some(first) = out.iter().find(|e| e.token == token) {
                    anyhow::bail!(
                        "line {}: the token of {name:?} is already listed for {:?}; every \
                         principal needs its own token",
                        n + 1,
                        first.name
                    );
                }
                out.push(TokenEntry {
                    role,
                    name: name.to_string(),
                    token: token.to_string(),
                });
            }
        }
        Ok(out)
    }
}

/// How callers are authenticated.
#[derive(Debug, Clone)]
pub enum AuthConfig {
    /// Every caller is the admin `anonymous` (`--insecure-no-auth`).
    Disabled,
    Tokens(Vec<TokenEntry>),
}

/// Resolves bearer tokens to principals.
#[derive(Clone)]
pub struct Authenticator {
    /// SHA-256 of the token → principal; `None` when authentication is disabled.
    tokens: Option<Arc<HashMap<[u8; 32], Principal>>>,
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Authenticator {
    pub fn new(config: &AuthConfig) -> Self {
        let tokens = match config {
            AuthConfig::Disabled => None,
            AuthConfig::Tokens(entries) => Some(Arc::new(
                entries
                    .iter()
                    .map(|e| {
                        (
                            digest(&e.token),
                            Principal {
                                name: e.name.clone(),
                                role: e.role,
                            },
                        )
                    })
                    .collect(),
            )),
        };
        Authenticator { tokens }
    }

    /// The interceptor body: authenticates and stores the `Principal` in the extensions.
    #[allow(clippy::result_large_err)]
    pub fn intercept(&self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let principal = self.authenticate(request.metadata())?;
        request.extensions_mut().insert(principal);
        Ok(request)
    }

    /// The principal of a request's `authorization: Bearer <token>` (the gRPC services' and
    /// the web API's).
    #[allow(clippy::result_large_err)]
    pub fn authenticate(
        &self,
        metadata: &tonic::metadata::MetadataMap,
    ) -> Result<Principal, Status> {
        let Some(tokens) = &self.tokens else {
            return Ok(Principal {
                name: "anonymous".into(),
                role: Role::Admin,
            });
        };
        let header = metadata
            .get("authorization")
            .ok_or_else(|| Status::unauthenticated("missing `authorization: Bearer <token>`"))?;
        let token = header
            .to_str()
            .ok()
            .and_then(|h| {
                h.strip_prefix("Bearer ")
                    .or_else(|| h.strip_prefix("bearer "))
            })
            .ok_or_else(|| Status::unauthenticated("authorization must be `Bearer <token>`"))?;
        tokens
            .get(&digest(token.trim()))
            .cloned()
            .ok_or_else(|| Status::unauthenticated("unknown token"))
    }
}

/// The caller of a request, requiring one of `roles`.
#[allow(clippy::result_large_err)]
pub fn require<T>(request: &Request<T>, roles: &[Role]) -> Result<Principal, Status> {
    let principal = request
        .extensions()
        .get::<Principal>()
        .cloned()
        .ok_or_else(|| Status::unauthenticated("unauthenticated"))?;
    require_role(&principal, roles)?;
    Ok(principal)
}

/// PERMISSION_DENIED unless `principal` has one of `roles`.
#[allow(clippy::result_large_err)]
pub fn require_role(principal: &Principal, roles: &[Role]) -> Result<(), Status> {
    if roles.contains(&principal.role) {
        Ok(())
    } else {
        Err(Status::permission_denied(format!(
            "a {:?} token may not call this service",
            principal.role
        )))
    }
}

/// Roles accepted by the job API.
pub const CLIENT_ROLES: &[Role] = &[Role::Client, Role::Admin];
/// Roles accepted by the worker and artifact APIs.
pub const WORKER_ROLES: &[Role] = &[Role::Worker, Role::Admin];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_token_lists() {
        let list = TokenEntry::parse_list(
            "# comment\nclient:alice:aaaaaaaaaaaaaaaa\n\nworker:w1:bbbbbbbbbbbbbbbb, admin:root:cccccccccccccccc",
        )
        .unwrap();
        assert_eq!(list.len(), 3);
        assert_eq!(list[1].role, Role::Worker);
        assert_eq!(list[2].name, "root");
        assert!(TokenEntry::parse_list("boss:x:aaaaaaaaaaaaaaaa").is_err());
        let hashed = TokenEntry::parse_list("client:x:abc#defghijklmnopq").unwrap();
        assert_eq!(hashed[0].token, "abc#defghijklmnopq");
        let twice = TokenEntry::parse_list("client:x:aaaaaaaaaaaaaaaa\nadmin:y:aaaaaaaaaaaaaaaa")
            .unwrap_err()
            .to_string();
        assert!(twice.contains("already listed"), "{twice}");
        assert!(TokenEntry::parse_list("client:x:short").is_err());
    }
}
