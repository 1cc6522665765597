//! Smoke test: the generated WeightsService server and client speak to each other over a
//! real HTTP/2 connection on loopback, with the documented Subscribe semantics (newest
//! version at once, then strictly newer versions).

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use mapless_proto::v1::weights_service_client::WeightsServiceClient;
use mapless_proto::v1::weights_service_server::{WeightsService, WeightsServiceServer};
use mapless_proto::v1::{Algorithm, NamedTensor, ProtocolVersion, SubscribeRequest, WeightsSnapshot};
use mapless_proto::{MAX_MESSAGE_BYTES, check_protocol_version};
use tokio::sync::{oneshot, watch};
use tokio_stream::wrappers::{TcpListenerStream, WatchStream};
use tokio_stream::{Stream, StreamExt};
use tonic::transport::Server;
use tonic::{Code, Request, Response, Status};

/// Newest published snapshot; `None` before the first publication.
type Latest = Option<Arc<WeightsSnapshot>>;

/// Minimal WeightsService: a watch channel holds only the newest snapshot, which gives
/// "latest wins" with bounded memory per subscriber.
struct Weights {
    latest: watch::Receiver<Latest>,
}

#[tonic::async_trait]
impl WeightsService for Weights {
    type SubscribeStream = Pin<Box<dyn Stream<Item = Result<WeightsSnapshot, Status>> + Send>>;

    async fn subscribe(&self, request: Request<SubscribeRequest>) -> Result<Response<Self::SubscribeStream>, Status> {
        let request = request.into_inner();
        check_protocol_version(request.protocol_version)?;
        // Highest version this stream has sent (or the client already has).
        let mut sent = request.min_version.saturating_sub(1);
        let stream = WatchStream::new(self.latest.clone()).filter_map(move |latest: Latest| {
            let snapshot = latest?;
            if snapshot.version <= sent {
                return None;
            }
            sent = snapshot.version;
            Some(Ok(WeightsSnapshot::clone(&snapshot)))
        });
        Ok(Response::new(Box::pin(stream)))
    }
}

fn snapshot(version: u64) -> Arc<WeightsSnapshot> {
    let bias = NamedTensor::from_f32("actor.out.bias", vec![2], &[version as f32, -1.0]).expect("shape matches");
    Arc::new(WeightsSnapshot {
        protocol_version: ProtocolVersion::V1 as i32,
        version,
        algorithm: Algorithm::Sac as i32,
        created_unix_ms: 1_700_000_000_000 + version,
        obs_dim: 17,
        act_dim: 2,
        tensors: vec![bias],
        metadata: [("learner_step".to_owned(), (version * 100).to_string())].into(),
    })
}

/// The next snapshot on the stream, failing the test after 10 s instead of hanging.
async fn next(stream: &mut tonic::Streaming<WeightsSnapshot>) -> WeightsSnapshot {
    tokio::time::timeout(Duration::from_secs(10), stream.message()).await.expect("snapshot within 10 s").expect("stream healthy").expect("stream open")
}

#[tokio::test]
async fn subscriber_gets_newest_snapshot_at_once_then_each_newer_one() {
    let (publish, latest) = watch::channel::<Latest>(None);
    // Versions 1 and 2 were published before anyone subscribed; a late subscriber must get
    // only version 2.
    publish.send_replace(Some(snapshot(1)));
    publish.send_replace(Some(snapshot(2)));

    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
    let addr = listener.local_addr().expect("bound address");
    let (shutdown_tx, shutdown_rx) = oneshot::channel::<()>();
    let service = WeightsServiceServer::new(Weights { latest }).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES);
    let server = tokio::spawn(Server::builder().add_service(service).serve_with_incoming_shutdown(TcpListenerStream::new(listener), async {
        let _ = shutdown_rx.await;
    }));

    let mut client = WeightsServiceClient::connect(format!("http://{addr}")).await.expect("connect").max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES);

    // A request from an unknown contract version is refused before any stream starts.
    let refused = client.subscribe(SubscribeRequest { protocol_version: 7, ..SubscribeRequest::default() }).await.expect_err("unknown protocol version");
    assert_eq!(refused.code(), Code::FailedPrecondition);

    let mut stream = client.subscribe(SubscribeRequest { protocol_version: ProtocolVersion::V1 as i32, min_version: 1, subscriber_id: "actor-test".to_owned() }).await.expect("subscribe").into_inner();

    let first = next(&mut stream).await;
    assert_eq!(first.version, 2, "late subscriber starts at the newest version");
    assert_eq!(first.validate(), Ok(()));
    assert_eq!(first, *snapshot(2), "every field survives the wire");
    assert_eq!(first.tensor("actor.out.bias").expect("bias").to_f32_vec(), Ok(vec![2.0, -1.0]));

    publish.send_replace(Some(snapshot(3)));
    let second = next(&mut stream).await;
    assert_eq!(second.version, 3);
    assert!(second.version > first.version, "versions strictly increase");

    drop(stream);
    drop(client);
    shutdown_tx.send(()).expect("server still running");
    tokio::time::timeout(Duration::from_secs(10), server).await.expect("server stops within 10 s").expect("server task did not panic").expect("server exits cleanly");
}
