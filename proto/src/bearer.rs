//! The bearer-token interceptor every caller of the coordinator uses (client library, worker,
//! benchmarks, tests): `authorization: Bearer <token>` on each call, nothing without a token.

use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Request, Status};

/// Adds `authorization: Bearer <token>` to every call (nothing when there is no token).
#[derive(Clone, Debug, Default)]
pub struct Bearer(Option<MetadataValue<Ascii>>);

/// A token holding characters that cannot be sent in an HTTP header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InvalidToken;

impl std::fmt::Display for InvalidToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("the token holds characters that cannot be sent in a header")
    }
}

impl std::error::Error for InvalidToken {}

impl Bearer {
    /// An interceptor for `token`, trimmed; `None` or a blank token sends nothing.
    pub fn new(token: Option<&str>) -> Result<Self, InvalidToken> {
        match token.map(str::trim).filter(|t| !t.is_empty()) {
            None => Ok(Bearer(None)),
            Some(token) => format!("Bearer {token}")
                .parse()
                .map(|value| Bearer(Some(value)))
                .map_err(|_| InvalidToken),
        }
    }
}

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// A channel whose calls carry the bearer token.
pub type Authed = InterceptedService<Channel, Bearer>;

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::service::Interceptor;

    fn header(token: Option<&str>) -> Option<String> {
        let request = Bearer::new(token).unwrap().call(Request::new(())).unwrap();
        request
            .metadata()
            .get("authorization")
            .map(|v| v.to_str().unwrap().to_string())
    }

    #[test]
    fn the_token_goes_in_the_authorization_header_trimmed() {
        assert_eq!(header(Some(" abc\n")).as_deref(), Some("Bearer abc"));
        assert_eq!(header(None), None);
        assert_eq!(header(Some("  ")), None);
        assert_eq!(Bearer::new(Some("a\u{7}b")).unwrap_err(), InvalidToken);
    }
}
