//! An actor process's slot from the replay (`RegisterActor`, replay.proto): the number it takes
//! its seeds and actor-id prefix from when it is started with `--index auto`, e.g. as one of
//! several identical container replicas.
//!
//! One unary call with the endpoint's TLS and bearer token, like the actor's other calls to
//! the replay; [`register_actor`] checks the name before dialling, so a bad name is a clear
//! local error rather than a round trip.

use std::time::Duration;

use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{ProtocolVersion, RegisterActorRequest, RegisterActorResponse};
use tonic::Code;

use crate::endpoint::{GrpcEndpoint, NetError};

/// Longest one registration may take, connection included; the replay answers from memory
/// and one small file write.
pub const REGISTER_TIMEOUT: Duration = Duration::from_secs(10);

/// Asks the replay at `endpoint` for `name`'s slot. Errors: [`NetError::ClientConfig`] for a name the
/// replay would refuse (empty, longer than [`mapless_proto::MAX_ACTOR_NAME_BYTES`], control
/// characters), else [`NetError::Grpc`] with the replay's status (UNAVAILABLE when it cannot
/// be reached; see [`is_retryable`]).
pub async fn register_actor(endpoint: &GrpcEndpoint, name: &str) -> Result<RegisterActorResponse, NetError> {
    let req = RegisterActorRequest { protocol_version: ProtocolVersion::V1 as i32, name: name.to_owned() };
    req.validate().map_err(|e| NetError::ClientConfig { client: "actor registration", reason: format!("actor name {name:?}: {e}") })?;
    let call = async {
        let channel = endpoint.connect("replay").await?;
        let mut client = ReplayServiceClient::new(channel).max_decoding_message_size(MAX_MESSAGE_BYTES);
        let mut request = endpoint.request("replay", req)?;
        request.set_timeout(REGISTER_TIMEOUT);
        client.register_actor(request).await.map(tonic::Response::into_inner).map_err(|s| endpoint.status_error("replay", &s))
    };
    match tokio::time::timeout(REGISTER_TIMEOUT, call).await {
        Ok(outcome) => outcome,
        Err(_) => {
            Err(NetError::Grpc { service: "replay", endpoint: endpoint.uri().to_owned(), code: Code::DeadlineExceeded, message: format!("no answer to RegisterActor within {REGISTER_TIMEOUT:?}") })
        }
    }
}

/// Whether trying again later can help: the replay is not (yet) reachable or did not answer
/// in time, or could not write its slot file. A bad name, a wrong token, a full slot table or
/// a replay without `RegisterActor` (UNIMPLEMENTED) stay as they are.
pub fn is_retryable(error: &NetError) -> bool {
    matches!(error.code(), Some(Code::Unavailable | Code::DeadlineExceeded | Code::Internal | Code::Unknown))
}
