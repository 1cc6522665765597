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
/// the learner may restart at any time. Errors are never fatal; they are warnings, rate-limited
/// by [`Failures`] (a wrong token or a learner that is down would otherwise log every 5 s).
pub async fn follow(endpoint: GrpcEndpoint, subscriber_id: String, tx: watch::Sender<Option<std::sync::Arc<WeightsSnapshot>>>, mut stop: watch::Receiver<bool>) {
    let mut backoff = Duration::from_millis(100);
    let mut next_version = 1;
    let mut failures = Failures::default();
    while !*stop.borrow() {
        let attempt = async {
            let mut sub = subscribe(&endpoint, next_version, &subscriber_id).await?;
            if let Some(streak) = failures.recovered() {
                tracing::info!(endpoint = %endpoint.uri(), failed_attempts = streak, "weights stream open again");
            }
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
                    let retry_in_ms = backoff.as_millis() as u64;
                    match failures.failed(&e) {
                        Some(streak) => tracing::warn!(error = %e, failed_attempts = streak, retry_in_ms, "weights stream broken or refused; acting with the policy at hand and retrying"),
                        None => tracing::debug!(error = %e, failed_attempts = failures.streak, retry_in_ms, "weights stream broken; retrying"),
                    }
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

/// Consecutive failed attempts of a retrying client, and which of them are worth a warning:
/// the first of a streak, one whose kind (gRPC code, else message) differs from the last one
/// warned about (a learner that comes back with another token), and every
/// [`Failures::WARN_EVERY`]-th; the others are debug lines. Counts attempts, not seconds, so
/// it needs no clock.
#[derive(Debug, Default)]
pub struct Failures {
    streak: u64,
    warned_kind: Option<String>,
}

impl Failures {
    /// One warning per this many consecutive failures: about one a minute once the backoff
    /// reaches its 5 s cap.
    pub const WARN_EVERY: u64 = 12;

    /// Counts a failure; `Some(streak length)` when it should be a warning.
    pub fn failed(&mut self, error: &NetError) -> Option<u64> {
        self.streak += 1;
        let kind = error.code().map_or_else(|| error.to_string(), |c| format!("{c:?}"));
        let warn = self.streak == 1 || self.streak.is_multiple_of(Self::WARN_EVERY) || self.warned_kind.as_deref() != Some(kind.as_str());
        if warn {
            self.warned_kind = Some(kind);
            Some(self.streak)
        } else {
            None
        }
    }

    /// Ends a streak; `Some(its length)` when there was one.
    pub fn recovered(&mut self) -> Option<u64> {
        self.warned_kind = None;
        let streak = std::mem::take(&mut self.streak);
        (streak > 0).then_some(streak)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grpc(code: tonic::Code) -> NetError {
        NetError::Grpc { service: "weights", endpoint: "http://learner:50052".into(), code, message: "x".into() }
    }

    #[test]
    fn a_failure_streak_warns_first_on_a_new_kind_and_every_twelfth() {
        let mut f = Failures::default();
        let down = grpc(tonic::Code::Unavailable);
        let warned: Vec<u64> = (0..25).filter_map(|_| f.failed(&down)).collect();
        assert_eq!(warned, vec![1, 12, 24], "a learner that stays down warns about once a minute");
        assert_eq!(f.failed(&grpc(tonic::Code::Unauthenticated)), Some(26), "another kind of failure warns at once");
        assert_eq!(f.failed(&grpc(tonic::Code::Unauthenticated)), None);
        assert_eq!(f.recovered(), Some(27));
        assert_eq!(f.recovered(), None, "no streak, nothing to report");
        assert_eq!(f.failed(&grpc(tonic::Code::Unauthenticated)), Some(1), "a new streak warns again");
    }
}
