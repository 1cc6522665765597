//! Reaching the cluster's gRPC services (replay, weights, stats): where they are, TLS and the
//! bearer token. Used by the actors, the learner and the supervisor.

use std::path::Path;
use std::time::Duration;

use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::{Code, Request, Status};

/// What reaching a service can fail with.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    /// A gRPC call failed: the peer could not be reached (`Unavailable`), or it answered with
    /// an error status.
    #[error("{service} at {endpoint}: {code:?}: {message}")]
    Grpc {
        /// `replay`, `weights` or `stats`.
        service: &'static str,
        /// The address dialled.
        endpoint: String,
        /// The gRPC status code (transport failures are `Unavailable`).
        code: Code,
        /// The peer's status message, or the transport error.
        message: String,
    },
    /// An endpoint that cannot work (not a URI, `https://` without a CA, a token that is not
    /// ASCII, an empty token file).
    #[error("invalid endpoint config: {reason}")]
    Config {
        /// What is wrong.
        reason: String,
    },
    /// Reading a CA or token file failed.
    #[error("{path}: {error}")]
    FileIo {
        /// The file.
        path: std::path::PathBuf,
        /// What the OS said.
        error: std::io::Error,
    },
    /// A peer sent a message that breaks the contract (an invalid or not-newer weights
    /// snapshot).
    #[error("invalid message from {origin}: {reason}")]
    Invalid {
        /// Where it came from.
        origin: String,
        /// What is wrong.
        reason: String,
    },
    /// A client configured with values that can never work (a batch size of 0, an empty
    /// queue, ...), or whose background thread could not be started.
    #[error("invalid {client} config: {reason}")]
    ClientConfig {
        /// Which client (`sample client`).
        client: &'static str,
        /// What is wrong, naming the field.
        reason: String,
    },
    /// A client stopped for good after an error that retrying cannot fix (wrong table, wrong
    /// token, incompatible dims, ...); every later call returns this again.
    #[error("{client} stopped: {reason}")]
    Stopped {
        /// Which client (`sample client`).
        client: &'static str,
        /// The error that stopped it.
        reason: String,
    },
}

impl NetError {
    /// The gRPC code, where there is one.
    pub fn code(&self) -> Option<Code> {
        match self {
            NetError::Grpc { code, .. } => Some(*code),
            _ => None,
        }
    }
}

/// Where a gRPC service is and how to reach it: the URI, optional TLS (a CA certificate to
/// trust, and the name to check it against) and an optional bearer token, sent as
/// `authorization: Bearer <token>` on every call (what the replay and weights services check).
///
/// `http://` URIs are plain HTTP/2 (the services allow that on loopback only); `https://`
/// needs [`GrpcEndpoint::with_tls`].
#[derive(Clone)]
pub struct GrpcEndpoint {
    uri: String,
    tls_ca_pem: Option<Vec<u8>>,
    tls_domain: Option<String>,
    token: Option<String>,
    connect_timeout: Duration,
    stream_window: Option<u32>,
}

impl std::fmt::Debug for GrpcEndpoint {
    // Never print the token.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GrpcEndpoint").field("uri", &self.uri).field("tls", &self.tls_ca_pem.is_some()).field("tls_domain", &self.tls_domain).field("token", &self.token.is_some()).finish()
    }
}

impl From<&str> for GrpcEndpoint {
    fn from(uri: &str) -> Self {
        Self::new(uri)
    }
}

impl From<String> for GrpcEndpoint {
    fn from(uri: String) -> Self {
        Self::new(uri)
    }
}

impl GrpcEndpoint {
    /// An endpoint at `uri`, e.g. `http://127.0.0.1:50051`; a bare `host:port` means
    /// `http://host:port`.
    pub fn new(uri: impl Into<String>) -> Self {
        let uri = uri.into();
        let uri = if uri.contains("://") { uri } else { format!("http://{uri}") };
        Self { uri, tls_ca_pem: None, tls_domain: None, token: None, connect_timeout: Duration::from_secs(5), stream_window: None }
    }

    /// Use TLS, trusting `ca_pem` (PEM certificate(s)); `domain` overrides the name the
    /// server's certificate is checked against (default: the URI's host). Switches an
    /// `http://` URI to `https://`.
    pub fn with_tls(mut self, ca_pem: impl Into<Vec<u8>>, domain: Option<String>) -> Self {
        if let Some(rest) = self.uri.strip_prefix("http://") {
            self.uri = format!("https://{rest}");
        }
        self.tls_ca_pem = Some(ca_pem.into());
        self.tls_domain = domain;
        self
    }

    /// [`GrpcEndpoint::with_tls`] with the CA read from a PEM file.
    pub fn with_tls_ca_file(self, path: &Path, domain: Option<String>) -> Result<Self, NetError> {
        let pem = std::fs::read(path).map_err(|error| NetError::FileIo { path: path.to_owned(), error })?;
        Ok(self.with_tls(pem, domain))
    }

    /// Send `authorization: Bearer <token>` on every call.
    pub fn with_token(mut self, token: impl Into<String>) -> Self {
        self.token = Some(token.into());
        self
    }

    /// [`GrpcEndpoint::with_token`] with the token read from a file (trimmed), as the replay
    /// server reads its own: a file keeps the token out of `ps`.
    pub fn with_token_file(self, path: &Path) -> Result<Self, NetError> {
        let raw = std::fs::read(path).map_err(|error| NetError::FileIo { path: path.to_owned(), error })?;
        let token = String::from_utf8_lossy(&raw).trim().to_owned();
        if token.is_empty() {
            return Err(NetError::Config { reason: format!("token file {} is empty", path.display()) });
        }
        Ok(self.with_token(token))
    }

    /// Longest a connection attempt may take [default 5 s].
    pub fn with_connect_timeout(mut self, timeout: Duration) -> Self {
        self.connect_timeout = timeout;
        self
    }

    /// HTTP/2 flow-control window of each stream on connections this endpoint dials: how many
    /// bytes a server may send on one stream before this side has read them [default: the
    /// transport's, 2 MiB]. A small window bounds how much a server can push ahead of a slow
    /// reader (see `sample::SampleClient`, which sizes it to its prefetch).
    pub fn with_stream_window(mut self, bytes: u32) -> Self {
        self.stream_window = Some(bytes);
        self
    }

    /// The URI dialled.
    pub fn uri(&self) -> &str {
        &self.uri
    }

    /// Checks everything that can be checked without dialling: the URI, TLS settings, token.
    pub fn check(&self) -> Result<(), NetError> {
        self.endpoint()?;
        self.token_value()?;
        Ok(())
    }

    fn config_error(&self, reason: String) -> NetError {
        NetError::Config { reason: format!("endpoint `{}`: {reason}", self.uri) }
    }

    fn endpoint(&self) -> Result<Endpoint, NetError> {
        let mut endpoint = Endpoint::from_shared(self.uri.clone())
            .map_err(|e| self.config_error(format!("not a valid URI: {e}")))?
            .connect_timeout(self.connect_timeout)
            .tcp_nodelay(true)
            .http2_keep_alive_interval(Duration::from_secs(10))
            .keep_alive_timeout(Duration::from_secs(20))
            .keep_alive_while_idle(true)
            .initial_stream_window_size(self.stream_window);
        match &self.tls_ca_pem {
            Some(ca) => {
                let mut tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca));
                if let Some(domain) = &self.tls_domain {
                    tls = tls.domain_name(domain.clone());
                }
                endpoint = endpoint.tls_config(tls).map_err(|e| self.config_error(format!("TLS: {e}")))?;
            }
            None if self.uri.starts_with("https://") => {
                return Err(self.config_error("https:// needs a CA certificate to trust (GrpcEndpoint::with_tls)".into()));
            }
            None => {}
        }
        Ok(endpoint)
    }

    fn token_value(&self) -> Result<Option<MetadataValue<Ascii>>, NetError> {
        self.token.as_ref().map(|t| format!("Bearer {t}").parse::<MetadataValue<Ascii>>().map_err(|_| self.config_error("the bearer token is not printable ASCII".into()))).transpose()
    }

    /// Dials the service; failures are [`NetError::Grpc`] with code UNAVAILABLE.
    pub async fn connect(&self, service: &'static str) -> Result<Channel, NetError> {
        self.endpoint()?.connect().await.map_err(|e| NetError::Grpc { service, endpoint: self.uri.clone(), code: Code::Unavailable, message: format!("cannot connect: {}", error_chain(&e)) })
    }

    /// `message` as a request carrying the bearer token, if any.
    pub fn request<T>(&self, _service: &'static str, message: T) -> Result<Request<T>, NetError> {
        let mut request = Request::new(message);
        if let Some(value) = self.token_value()? {
            request.metadata_mut().insert("authorization", value);
        }
        Ok(request)
    }

    /// A status from the peer as a [`NetError::Grpc`].
    pub fn status_error(&self, service: &'static str, status: &Status) -> NetError {
        NetError::Grpc { service, endpoint: self.uri.clone(), code: status.code(), message: status.message().to_owned() }
    }
}

/// An error and its causes on one line (tonic's transport errors hide the useful part in
/// their sources).
pub fn error_chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}

/// Client-side TLS and token settings for services on other hosts (optional on loopback), as
/// they appear in a config file: the files are read when an endpoint is made from them.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ClientSecurity {
    /// PEM CA certificate to trust (switches `http://` to `https://`).
    pub tls_ca_file: Option<std::path::PathBuf>,
    /// Name to check the servers' certificates against (default: the URI's host).
    pub tls_domain: Option<String>,
    /// File holding the bearer token.
    pub token_file: Option<std::path::PathBuf>,
}

impl ClientSecurity {
    /// `uri` with this TLS and token, checked as far as it can be without dialling.
    pub fn endpoint(&self, uri: &str) -> Result<GrpcEndpoint, NetError> {
        let mut e = GrpcEndpoint::new(uri);
        if let Some(ca) = &self.tls_ca_file {
            e = e.with_tls_ca_file(ca, self.tls_domain.clone())?;
        }
        if let Some(t) = &self.token_file {
            e = e.with_token_file(t)?;
        }
        e.check()?;
        Ok(e)
    }
}
