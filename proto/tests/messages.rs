//! Behaviour of the checks on SampledBatch, PriorityUpdate, weights and episode statistics.

use mapless_proto::v1::{Algorithm, Dtype, EpisodeStats, NamedTensor, PriorityUpdate, ProtocolVersion, SampleRequest, SampledBatch, WeightsSnapshot};
use mapless_proto::{ProtoError, Transition, TransitionBatchBuilder};
use prost::Message;
use tonic::Code;

const V1: i32 = ProtocolVersion::V1 as i32;

/// A valid 2-row minibatch with obs_dim 2, act_dim 1, as a replay server would send it.
fn sampled_batch() -> SampledBatch {
    let mut builder = TransitionBatchBuilder::new(2, 1);
    for i in 0..2u32 {
        let f = i as f32;
        builder
            .push(Transition { obs: &[f, -f], action: &[0.5], reward: f, next_obs: &[f + 1.0, -f - 1.0], terminal: i == 1, truncated: false, episode_id: 9, step: i, policy_version: 3 })
            .expect("valid row");
    }
    let t = builder.finish("unused", 1);
    SampledBatch {
        protocol_version: V1,
        table: "default".to_owned(),
        obs_dim: t.obs_dim,
        act_dim: t.act_dim,
        num_rows: t.num_rows,
        table_size: 1000,
        keys: vec![17, 4],
        probabilities: vec![0.001, 0.002],
        importance_weights: vec![1.0, 0.5],
        obs: t.obs,
        action: t.action,
        reward: t.reward,
        next_obs: t.next_obs,
        terminal: t.terminal,
        truncated: t.truncated,
        episode_id: t.episode_id,
        step: t.step,
        policy_version: t.policy_version,
        ..SampledBatch::default()
    }
}

#[test]
fn sampled_batch_validates_and_reads_rows_back_after_decoding() {
    let batch = sampled_batch();
    let decoded = SampledBatch::decode(batch.encode_to_vec().as_slice()).expect("decodes");

    assert_eq!(decoded.validate(2, 1, 256), Ok(2));
    let row = decoded.row(1).expect("row 1");
    assert_eq!(row.obs, &[1.0, -1.0]);
    assert_eq!(row.next_obs, &[2.0, -2.0]);
    assert!(row.terminal && !row.truncated);
    assert_eq!(decoded.iter_rows().count(), 2);
}

#[test]
fn sampled_batch_rejects_probability_outside_unit_interval() {
    for bad in [0.0, 1.5, f64::NAN] {
        let mut batch = sampled_batch();
        batch.probabilities[1] = bad;
        let err = batch.validate(2, 1, 256).unwrap_err();
        assert!(matches!(err, ProtoError::OutOfRange { column: "probabilities", row: 1, .. }), "{bad}: {err:?}");
    }
}

#[test]
fn sampled_batch_rejects_missing_keys() {
    let mut batch = sampled_batch();
    batch.keys.pop();
    assert_eq!(batch.validate(2, 1, 256), Err(ProtoError::ColumnLength { column: "keys", expected: 2, got: 1 }));
}

#[test]
fn sample_request_rejects_zero_or_oversized_batch_and_beta_outside_unit_interval() {
    let request = |batch_size, beta| SampleRequest { protocol_version: V1, batch_size, importance_beta: Some(beta), ..SampleRequest::default() };
    assert_eq!(request(256, 0.4).validate(1024), Ok(256));
    // Unset: the table's own beta.
    assert_eq!(SampleRequest { protocol_version: V1, batch_size: 256, ..SampleRequest::default() }.validate(1024), Ok(256));
    for (batch_size, beta, field) in [(0, 0.4, "batch_size"), (1025, 0.4, "batch_size"), (256, 1.5, "importance_beta"), (256, f32::NAN, "importance_beta")] {
        let err = request(batch_size, beta).validate(1024).unwrap_err();
        assert!(matches!(err, ProtoError::InvalidField { field: f, .. } if f == field), "{batch_size}, {beta}: {err:?}");
        assert_eq!(err.to_status().code(), Code::InvalidArgument);
    }
    let unversioned = SampleRequest { batch_size: 1, ..SampleRequest::default() };
    assert_eq!(unversioned.validate(1024).unwrap_err().to_status().code(), Code::FailedPrecondition);
}

#[test]
fn priority_update_rejects_negative_nan_and_mismatched_lengths() {
    let update = |priorities: Vec<f64>| PriorityUpdate { protocol_version: V1, table: String::new(), keys: vec![1, 2, 3], priorities };
    assert_eq!(update(vec![0.0, 1.0, 2.5]).validate(1024), Ok(3));
    assert!(matches!(update(vec![0.0, -1.0, 2.5]).validate(1024), Err(ProtoError::OutOfRange { column: "priorities", row: 1, .. })));
    assert!(matches!(update(vec![0.0, 1.0, f64::NAN]).validate(1024), Err(ProtoError::NonFinite { column: "priorities", row: 2, .. })));
    assert!(matches!(update(vec![0.0, 1.0]).validate(1024), Err(ProtoError::ColumnLength { column: "priorities", expected: 3, got: 2 })));
    let err = update(vec![0.0, 1.0, 2.0]).validate(2).unwrap_err();
    assert_eq!(err.to_status().code(), Code::ResourceExhausted);
}

#[test]
fn f32_tensor_round_trips_through_little_endian_bytes() {
    let values = [1.0f32, -2.5, 3.25, f32::MIN_POSITIVE, 0.0, 7.0];
    let tensor = NamedTensor::from_f32("actor.fc1.weight", vec![2, 3], &values).expect("shape fits");

    assert_eq!(tensor.dtype, Dtype::F32 as i32);
    assert_eq!(&tensor.data[..4], &1.0f32.to_le_bytes());
    let decoded = NamedTensor::decode(tensor.encode_to_vec().as_slice()).expect("decodes");
    assert_eq!(decoded.to_f32_vec(), Ok(values.to_vec()));
    assert_eq!(Dtype::F32.safetensors_name(), Some("F32"));
    assert_eq!(Dtype::from_safetensors_name("BF16"), Some(Dtype::Bf16));
    assert_eq!(Dtype::Bf16.size_bytes(), Some(2));
}

#[test]
fn scalar_tensor_has_empty_shape_and_one_value() {
    let tensor = NamedTensor::from_f32("log_alpha", vec![], &[0.5]).expect("scalar");
    assert_eq!(tensor.element_count(), Ok(1));
    assert_eq!(tensor.to_f32_vec(), Ok(vec![0.5]));
}

#[test]
fn tensor_with_data_not_matching_shape_is_rejected() {
    assert!(NamedTensor::from_f32("w", vec![2, 2], &[1.0; 3]).is_err());

    let mut tensor = NamedTensor::from_f32("w", vec![2, 2], &[1.0; 4]).expect("fits");
    tensor.data.pop();
    assert!(matches!(tensor.validate(), Err(ProtoError::InvalidTensor { ref name, .. }) if name == "w"));

    let overflowing = NamedTensor { name: "huge".to_owned(), shape: vec![u64::MAX, 2], dtype: Dtype::F32 as i32, data: Vec::new() };
    assert!(overflowing.validate().is_err());
}

#[test]
fn weights_snapshot_rejects_duplicate_tensor_names_and_version_zero() {
    let tensor = NamedTensor::from_f32("actor.out.bias", vec![2], &[0.0, 1.0]).expect("fits");
    let mut snapshot = WeightsSnapshot {
        protocol_version: V1,
        version: 1,
        algorithm: Algorithm::Td3 as i32,
        created_unix_ms: 1,
        obs_dim: 17,
        act_dim: 2,
        tensors: vec![tensor.clone()],
        metadata: Default::default(),
    };
    assert_eq!(snapshot.validate(), Ok(()));
    assert_eq!(snapshot.tensor("actor.out.bias"), Some(&tensor));

    snapshot.tensors.push(tensor);
    assert!(matches!(snapshot.validate(), Err(ProtoError::InvalidTensor { .. })));

    snapshot.tensors.pop();
    snapshot.version = 0;
    assert!(matches!(snapshot.validate(), Err(ProtoError::InvalidField { field: "version", .. })));
}

#[test]
fn episode_stats_must_end_for_exactly_one_reason() {
    let stats = |terminal, truncated| EpisodeStats {
        protocol_version: V1,
        actor_id: "actor-a".to_owned(),
        episode_id: 1,
        terminal,
        truncated,
        steps: 1000,
        distance_m: 12.5,
        map: "env1".to_owned(),
        ..EpisodeStats::default()
    };
    assert_eq!(stats(true, false).validate(), Ok(()));
    assert_eq!(stats(false, true).validate(), Ok(()));
    assert_eq!(stats(true, true).validate(), Err(ProtoError::TerminalAndTruncated { row: 0 }));
    assert_eq!(stats(false, false).validate(), Err(ProtoError::EpisodeNotEnded { episode_id: 1 }));

    let mut nan = stats(true, false);
    nan.ees = f64::NAN;
    assert!(matches!(nan.validate(), Err(ProtoError::NonFinite { column: "ees", .. })));
}
