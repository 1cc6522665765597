//! Behaviour of TransitionBatch building, encoding and validation.

use mapless_proto::v1::{ProtocolVersion, SampledBatch, TransitionBatch};
use mapless_proto::{FloatColumn, FloatEncoding, ProtoError, Transition, TransitionBatchBuilder};
use prost::Message;
use prost::bytes::Bytes;
use tonic::Code;

const OBS_DIM: usize = 3;
const ACT_DIM: usize = 2;
const MAX_ROWS: usize = 64;

/// Owned row data, so test rows can be generated and compared.
#[derive(Debug, Clone, PartialEq)]
struct Row {
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: f32,
    next_obs: Vec<f32>,
    terminal: bool,
    truncated: bool,
    episode_id: u64,
    step: u32,
    policy_version: u64,
}

impl Row {
    /// A row whose every value depends on `i`, so a swapped or shifted column shows up.
    fn numbered(i: usize) -> Self {
        let f = i as f32;
        Self {
            obs: vec![f, f + 0.25, -f],
            action: vec![0.5 - f, f * 0.125],
            reward: -1.5 * f,
            next_obs: vec![f + 1.0, f + 1.25, -f - 1.0],
            terminal: i % 3 == 1,
            truncated: i % 3 == 2,
            episode_id: 100 + i as u64 / 2,
            step: i as u32 * 7,
            policy_version: 40 + i as u64,
        }
    }

    fn as_transition(&self) -> Transition<'_> {
        Transition {
            obs: &self.obs,
            action: &self.action,
            reward: self.reward,
            next_obs: &self.next_obs,
            terminal: self.terminal,
            truncated: self.truncated,
            episode_id: self.episode_id,
            step: self.step,
            policy_version: self.policy_version,
        }
    }
}

fn build(rows: &[Row]) -> TransitionBatch {
    let mut builder = TransitionBatchBuilder::with_capacity(OBS_DIM, ACT_DIM, rows.len());
    for row in rows {
        builder.push(row.as_transition()).expect("test rows are valid");
    }
    builder.finish("actor-test", 7)
}

fn valid_batch() -> TransitionBatch {
    build(&(0..5).map(Row::numbered).collect::<Vec<_>>())
}

fn validate(batch: &TransitionBatch) -> Result<usize, ProtoError> {
    batch.validate(OBS_DIM, ACT_DIM, MAX_ROWS)
}

#[test]
fn builder_encode_decode_round_trip_preserves_every_column() {
    let rows: Vec<Row> = (0..6).map(Row::numbered).collect();
    let batch = build(&rows);

    let bytes = batch.encode_to_vec();
    let decoded = TransitionBatch::decode(bytes.as_slice()).expect("decodes");

    assert_eq!(decoded, batch);
    assert_eq!(decoded.protocol_version, ProtocolVersion::V1 as i32);
    assert_eq!(decoded.actor_id, "actor-test");
    assert_eq!(decoded.sequence, 7);
    assert_eq!(decoded.obs_dim as usize, OBS_DIM);
    assert_eq!(decoded.act_dim as usize, ACT_DIM);
    assert_eq!(validate(&decoded), Ok(rows.len()));
    for (i, row) in rows.iter().enumerate() {
        assert_eq!(decoded.row(i), Some(row.as_transition()), "row {i}");
    }
    assert_eq!(decoded.row(rows.len()), None);
    let read_back: Vec<Transition<'_>> = decoded.iter_rows().collect();
    let expected: Vec<Transition<'_>> = rows.iter().map(Row::as_transition).collect();
    assert_eq!(read_back, expected);
}

#[test]
fn float_columns_are_packed_on_the_wire() {
    // Packed: one tag + length per column, 4 bytes per float. Unpacked would add a tag byte
    // per float, i.e. at least 25% more for the float columns.
    let batch = valid_batch();
    let float_bytes = 4 * (batch.obs.len() + batch.action.len() + batch.reward.len() + batch.next_obs.len());
    let encoded = batch.encoded_len();
    assert!(encoded < float_bytes + 200, "{encoded} bytes encoded for {float_bytes} bytes of floats");
}

#[test]
fn terminal_and_truncated_are_preserved_independently() {
    let mut neither = Row::numbered(0);
    neither.terminal = false;
    neither.truncated = false;
    let mut terminal_only = Row::numbered(1);
    terminal_only.terminal = true;
    terminal_only.truncated = false;
    let mut truncated_only = Row::numbered(2);
    truncated_only.terminal = false;
    truncated_only.truncated = true;

    let batch = build(&[neither, terminal_only, truncated_only]);
    let decoded = TransitionBatch::decode(batch.encode_to_vec().as_slice()).expect("decodes");

    assert_eq!(validate(&decoded), Ok(3));
    assert_eq!(decoded.terminal, vec![false, true, false]);
    assert_eq!(decoded.truncated, vec![false, false, true]);
}

#[test]
fn validate_rejects_row_that_is_both_terminal_and_truncated() {
    let mut batch = valid_batch();
    batch.terminal[3] = true;
    batch.truncated[3] = true;

    let err = validate(&batch).unwrap_err();
    assert_eq!(err, ProtoError::TerminalAndTruncated { row: 3 });
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn builder_rejects_row_that_is_both_terminal_and_truncated() {
    let mut builder = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
    builder.push(Row::numbered(0).as_transition()).expect("valid row");
    let mut both = Row::numbered(1);
    both.terminal = true;
    both.truncated = true;

    assert_eq!(builder.push(both.as_transition()), Err(ProtoError::TerminalAndTruncated { row: 1 }));
    assert_eq!(builder.len(), 1, "a rejected row is not appended");
}

#[test]
fn validate_rejects_wrong_obs_dim() {
    let batch = valid_batch();

    let err = batch.validate(OBS_DIM + 1, ACT_DIM, MAX_ROWS).unwrap_err();
    assert_eq!(err, ProtoError::DimensionMismatch { field: "obs_dim", expected: OBS_DIM as u64 + 1, got: OBS_DIM as u64 });
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn validate_rejects_truncated_column_and_names_it() {
    let mut batch = valid_batch();
    batch.next_obs.pop();

    let err = validate(&batch).unwrap_err();
    assert_eq!(err, ProtoError::ColumnLength { column: "next_obs", expected: 5 * OBS_DIM as u64, got: 5 * OBS_DIM as u64 - 1 });
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
    assert!(err.to_status().message().contains("next_obs"));
}

#[test]
fn row_accessors_do_not_panic_on_malformed_batches() {
    let mut batch = valid_batch();
    batch.obs.truncate(OBS_DIM * 2 + 1); // rows 0 and 1 complete, row 2 cut short
    batch.num_rows = u32::MAX;

    assert!(batch.row(1).is_some());
    assert_eq!(batch.row(2), None);
    assert_eq!(batch.iter_rows().count(), 2);
}

#[test]
fn validate_rejects_nan_reward_naming_column_and_row() {
    let mut batch = valid_batch();
    batch.reward[2] = f32::NAN;

    let err = validate(&batch).unwrap_err();
    assert!(
        matches!(
            err,
            ProtoError::NonFinite { column: "reward", row: 2, element: 0, value } if value.is_nan()
        ),
        "{err:?}"
    );
    let status = err.to_status();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("`reward` row 2"), "{}", status.message());
}

#[test]
fn validate_rejects_infinite_obs_naming_row_and_element() {
    let mut batch = valid_batch();
    batch.obs[4 * OBS_DIM + 1] = f32::INFINITY;

    let err = validate(&batch).unwrap_err();
    assert_eq!(err, ProtoError::NonFinite { column: "obs", row: 4, element: 1, value: f64::INFINITY });
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn builder_rejects_non_finite_values_before_they_reach_the_wire() {
    let mut builder = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
    let mut row = Row::numbered(0);
    row.next_obs[2] = f32::NEG_INFINITY;

    let err = builder.push(row.as_transition()).unwrap_err();
    assert!(matches!(err, ProtoError::NonFinite { column: "next_obs", row: 0, element: 2, .. }));
    assert!(builder.is_empty());
}

#[test]
fn builder_rejects_vectors_of_the_wrong_length() {
    let mut builder = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
    let mut row = Row::numbered(0);
    row.action.push(0.0);

    assert_eq!(builder.push(row.as_transition()), Err(ProtoError::ColumnLength { column: "action", expected: ACT_DIM as u64, got: ACT_DIM as u64 + 1 }));
}

#[test]
fn validate_rejects_unknown_protocol_version_with_failed_precondition() {
    for version in [0, 2, -1] {
        let mut batch = valid_batch();
        batch.protocol_version = version;

        let err = validate(&batch).unwrap_err();
        assert_eq!(err, ProtoError::UnsupportedProtocolVersion { got: version });
        assert_eq!(err.to_status().code(), Code::FailedPrecondition);
    }
}

#[test]
fn validate_rejects_too_many_rows_with_resource_exhausted() {
    let rows: Vec<Row> = (0..MAX_ROWS + 1).map(Row::numbered).collect();
    let batch = build(&rows);

    let err = validate(&batch).unwrap_err();
    assert_eq!(err, ProtoError::TooManyRows { rows: MAX_ROWS as u64 + 1, max: MAX_ROWS as u64 });
    assert_eq!(err.to_status().code(), Code::ResourceExhausted);
    assert_eq!(batch.validate(OBS_DIM, ACT_DIM, MAX_ROWS + 1), Ok(MAX_ROWS + 1));
}

#[test]
fn validate_rejects_empty_batch() {
    let batch = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM).finish("actor-test", 1);

    let err = validate(&batch).unwrap_err();
    assert_eq!(err, ProtoError::Empty { message: "TransitionBatch" });
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn validate_rejects_missing_actor_id_and_zero_sequence() {
    let mut batch = valid_batch();
    batch.actor_id.clear();
    assert!(matches!(validate(&batch), Err(ProtoError::InvalidField { field: "actor_id", .. })));

    let mut batch = valid_batch();
    batch.actor_id = "x".repeat(mapless_proto::MAX_ACTOR_ID_BYTES + 1);
    assert!(matches!(validate(&batch), Err(ProtoError::InvalidField { field: "actor_id", .. })));

    let mut batch = valid_batch();
    batch.sequence = 0;
    assert!(matches!(validate(&batch), Err(ProtoError::InvalidField { field: "sequence", .. })));
}

#[test]
fn proto_error_converts_into_tonic_status() {
    let status: tonic::Status = ProtoError::TooManyRows { rows: 2, max: 1 }.into();
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert_eq!(mapless_proto::check_protocol_version(ProtocolVersion::V1 as i32), Ok(()));
    assert_eq!(mapless_proto::PROTOCOL_VERSION, ProtocolVersion::V1 as u32);
}

/// `valid_batch()` with every float column as `*_f32le` bytes.
fn bytes_batch() -> TransitionBatch {
    let mut batch = valid_batch();
    batch.convert_float_columns(FloatEncoding::F32Le);
    batch
}

#[test]
fn float_columns_as_bytes_round_trip_and_read_like_packed_ones() {
    let packed = valid_batch();
    let batch = bytes_batch();
    assert!(batch.obs.is_empty() && batch.action.is_empty() && batch.reward.is_empty() && batch.next_obs.is_empty());
    assert_eq!(batch.obs_f32le.len(), 4 * packed.obs.len());

    let decoded = TransitionBatch::decode(batch.encode_to_vec().as_slice()).expect("decodes");
    assert_eq!(decoded, batch);
    assert_eq!(validate(&decoded), Ok(5));
    assert_eq!(decoded.obs_column().encoding(), FloatEncoding::F32Le);
    assert_eq!(decoded.obs_values().as_ref(), &packed.obs[..]);
    assert_eq!(decoded.action_values().as_ref(), &packed.action[..]);
    assert_eq!(decoded.reward_values().as_ref(), &packed.reward[..]);
    assert_eq!(decoded.next_obs_values().as_ref(), &packed.next_obs[..]);
    assert_eq!(packed.obs_column(), FloatColumn::Packed(&packed.obs));

    // Rows borrow packed floats: none from bytes columns, all after converting back.
    assert_eq!(decoded.row(0), None);
    let mut back = decoded.clone();
    back.convert_float_columns(FloatEncoding::Packed);
    assert_eq!(back, packed);
    assert_eq!(back.iter_rows().count(), 5);
}

#[test]
fn encode_f32le_writes_what_converting_then_encoding_writes() {
    let packed = valid_batch();
    let converted = bytes_batch();
    let mut direct = Vec::new();
    packed.encode_f32le(&mut direct);
    assert_eq!(direct, converted.encode_to_vec(), "from packed columns");
    assert_eq!(direct.len(), packed.encoded_len_f32le());
    let mut again = Vec::new();
    converted.encode_f32le(&mut again);
    assert_eq!(again, direct, "from bytes columns");

    let mut sampled = SampledBatch {
        protocol_version: ProtocolVersion::V1 as i32,
        obs_dim: OBS_DIM as u32,
        act_dim: ACT_DIM as u32,
        num_rows: 5,
        table_size: 9,
        keys: (0..5).collect(),
        probabilities: vec![0.2; 5],
        importance_weights: vec![1.0; 5],
        obs: packed.obs.clone(),
        action: packed.action.clone(),
        reward: packed.reward.clone(),
        next_obs: packed.next_obs.clone(),
        terminal: packed.terminal.clone(),
        truncated: packed.truncated.clone(),
        episode_id: packed.episode_id.clone(),
        step: packed.step.clone(),
        policy_version: packed.policy_version.clone(),
        ..SampledBatch::default()
    };
    let mut direct = Vec::new();
    sampled.encode_f32le(&mut direct);
    sampled.convert_float_columns(FloatEncoding::F32Le);
    assert_eq!(direct, sampled.encode_to_vec());
    let decoded = SampledBatch::decode(direct.as_slice()).expect("decodes");
    assert_eq!(decoded.validate(OBS_DIM, ACT_DIM, MAX_ROWS), Ok(5));
    assert_eq!(decoded.next_obs_values().as_ref(), &packed.next_obs[..]);
}

#[test]
fn bytes_columns_decoded_from_a_buffer_borrow_it() {
    let batch = bytes_batch();
    let wire = Bytes::from(batch.encode_to_vec());
    let decoded = TransitionBatch::decode(wire.clone()).expect("decodes");
    let range = wire.as_ptr() as usize..wire.as_ptr() as usize + wire.len();
    for column in [&decoded.obs_f32le, &decoded.action_f32le, &decoded.reward_f32le, &decoded.next_obs_f32le] {
        assert!(range.contains(&(column.as_ptr() as usize)), "a column was copied out of the buffer");
    }
}

#[test]
fn validate_refuses_malformed_bytes_columns_naming_them() {
    fn invalid(field: &'static str) -> impl Fn(ProtoError) {
        move |err: ProtoError| {
            assert!(matches!(&err, ProtoError::InvalidField { field: f, .. } if *f == field), "{err:?}");
            assert_eq!(err.to_status().code(), Code::InvalidArgument);
            assert!(err.to_status().message().contains(field));
        }
    }

    let mut ragged = bytes_batch();
    ragged.obs_f32le = ragged.obs_f32le.slice(..ragged.obs_f32le.len() - 2);
    invalid("obs_f32le")(validate(&ragged).unwrap_err());

    let mut both = bytes_batch();
    both.action = vec![0.0; 5 * ACT_DIM];
    invalid("action_f32le")(validate(&both).unwrap_err());

    let mut short = bytes_batch();
    short.next_obs_f32le = short.next_obs_f32le.slice(4..);
    assert_eq!(validate(&short), Err(ProtoError::ColumnLength { column: "next_obs_f32le", expected: 5 * OBS_DIM as u64, got: 5 * OBS_DIM as u64 - 1 }));

    let mut missing = bytes_batch();
    missing.reward_f32le = Bytes::new();
    assert_eq!(validate(&missing), Err(ProtoError::ColumnLength { column: "reward", expected: 5, got: 0 }));

    let mut inf = bytes_batch();
    let mut obs = inf.obs_f32le.to_vec();
    let at = 2 * OBS_DIM + 1; // row 2, element 1
    obs[4 * at..4 * at + 4].copy_from_slice(&f32::NEG_INFINITY.to_le_bytes());
    inf.obs_f32le = obs.into();
    let err = validate(&inf).unwrap_err();
    assert!(matches!(err, ProtoError::NonFinite { column: "obs_f32le", row: 2, element: 1, value } if value == f64::NEG_INFINITY), "{err:?}");
}

#[test]
fn a_batch_may_mix_encodings_across_columns() {
    let packed = valid_batch();
    let mut mixed = packed.clone();
    mixed.obs_f32le = mapless_proto::f32le_bytes(&mixed.obs);
    mixed.obs = Vec::new();
    assert_eq!(validate(&mixed), Ok(5));
    assert_eq!(mixed.obs_values().as_ref(), &packed.obs[..]);
    assert_eq!(mixed.reward_column(), FloatColumn::Packed(&packed.reward));
}
