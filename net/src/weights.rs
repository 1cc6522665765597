//! Following the learner's weights: the checked `WeightsService.Subscribe` client, and a
//! background follower that keeps the newest snapshot at hand and reconnects with backoff.

use std::time::Duration;

use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::weights_service_client::WeightsServiceClient;
use mapless_proto::v1::{ProtocolVersion, SubscribeRequest, WeightsSnapshot};
use tokio::sync::watch;

use crate::endpoint::{GrpcEndpoint, NetError};

fn invalid(origin: impl Into<String>, reason: impl Into<String>) -> NetError {
    NetError::Invalid { origin: origin.into(), reason: reason.into() }
}

/// An open Subscribe stream, checked: every snapshot passes [`WeightsSnapshot::validate`] and
/// versions strictly increase.
pub struct WeightsSubscription {
    stream: tonic::Streaming<WeightsSnapshot>,
    endpoint: String,
    last_version: u64,
}

impl std::fmt::Debug for WeightsSubscription {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WeightsSubscription").field("endpoint", &self.endpoint).field("last_version", &self.last_version).finish()
    }
}

/// Opens a Subscribe stream at `endpoint` for versions `>= min_version` (0 or 1: any).
/// `subscriber_id` (e.g. the actor id) appears in the server's logs; it may be empty.
///
/// Fails with [`NetError::Grpc`] when the server cannot be reached or refuses (e.g.
/// FAILED_PRECONDITION for a protocol mismatch, UNAUTHENTICATED for a wrong token).
pub async fn subscribe(endpoint: &GrpcEndpoint, min_version: u64, subscriber_id: &str) -> Result<WeightsSubscription, NetError> {
    let channel = endpoint.connect("weights").await?;
    let mut client = WeightsServiceClient::new(channel).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES);
    let request = endpoint.request("weights", SubscribeRequest { protocol_version: ProtocolVersion::V1 as i32, min_version, subscriber_id: subscriber_id.to_owned() })?;
    let stream = client.subscribe(request).await.map_err(|s| endpoint.status_error("weights", &s))?.into_inner();
    Ok(WeightsSubscription { stream, endpoint: endpoint.uri().to_owned(), last_version: min_version.saturating_sub(1) })
}

impl WeightsSubscription {
    /// The next snapshot: waits until the learner publishes a newer version. `Ok(None)` when
    /// the server ended the stream without an error status; an error when it ended with one
    /// (UNAVAILABLE on shutdown: reconnect with `min_version = last_version() + 1`), or when
    /// a snapshot is invalid or not newer than the previous one.
    pub async fn next(&mut self) -> Result<Option<WeightsSnapshot>, NetError> {
        let snapshot = match self.stream.message().await {
            Ok(Some(s)) => s,
            Ok(None) => return Ok(None),
            Err(status) => {
                return Err(NetError::Grpc { service: "weights", endpoint: self.endpoint.clone(), code: status.code(), message: status.message().to_owned() });
            }
        };
        let origin = || format!("{} version {}", self.endpoint, snapshot.version);
        snapshot.validate().map_err(|e| invalid(origin(), e.to_string()))?;
        if snapshot.version <= self.last_version {
            return Err(invalid(origin(), format!("not newer than the previous version {}; the server broke the strictly-increasing rule", self.last_version)));
        }
        self.last_version = snapshot.version;
        Ok(Some(snapshot))
    }

    /// Highest version received on this stream (`min_version - 1` before the first).
    pub fn last_version(&self) -> u64 {
        self.last_version
    }
}

/// Follows the weights stream at `endpoint` until `stop` turns true: every newer snapshot
/// replaces the value in `tx` (actors read it between steps). A broken or refused stream is
/// retried with exponential backoff (100 ms doubling to 5 s) from the next version on, so
/// the learner may restart at any time. Errors are logged, never fatal.
pub async fn follow(endpoint: GrpcEndpoint, subscriber_id: String, tx: watch::Sender<Option<std::sync::Arc<WeightsSnapshot>>>, mut stop: watch::Receiver<bool>) {
    let mut backoff = Duration::from_millis(100);
    let mut next_version = 1;
    while !*stop.borrow() {
        let attempt = async {
            let mut sub = subscribe(&endpoint, next_version, &subscriber_id).await?;
            loop {
                match sub.next().await? {
                    Some(s) => {
                        next_version = s.version + 1;
                        tracing::debug!(version = s.version, "new policy weights");
                        tx.send_replace(Some(std::sync::Arc::new(s)));
                        backoff = Duration::from_millis(100);
                    }
                    None => return Ok::<(), NetError>(()),
                }
            }
        };
        tokio::select! {
            r = attempt => {
                if let Err(e) = r {
                    tracing::debug!(error = %e, retry_in_ms = backoff.as_millis() as u64, "weights stream broken; retrying");
                }
            }
            _ = stop.changed() => return,
        }
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = stop.changed() => return,
        }
        backoff = (backoff * 2).min(Duration::from_secs(5));
    }
}
