//! Behaviour of TransitionBatch building, encoding and validation.

use mapless_proto::v1::{ProtocolVersion, TransitionBatch};
use mapless_proto::{ProtoError, Transition, TransitionBatchBuilder};
use prost::Message;
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
        builder
            .push(row.as_transition())
            .expect("test rows are valid");
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
    let float_bytes =
        4 * (batch.obs.len() + batch.action.len() + batch.reward.len() + batch.next_obs.len());
    let encoded = batch.encoded_len();
    assert!(
        encoded < float_bytes + 200,
        "{encoded} bytes encoded for {float_bytes} bytes of floats"
    );
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
    builder
        .push(Row::numbered(0).as_transition())
        .expect("valid row");
    let mut both = Row::numbered(1);
    both.terminal = true;
    both.truncated = true;

    assert_eq!(
        builder.push(both.as_transition()),
        Err(ProtoError::TerminalAndTruncated { row: 1 })
    );
    assert_eq!(builder.len(), 1, "a rejected row is not appended");
}

#[test]
fn validate_rejects_wrong_obs_dim() {
    let batch = valid_batch();

    let err = batch.validate(OBS_DIM + 1, ACT_DIM, MAX_ROWS).unwrap_err();
    assert_eq!(
        err,
        ProtoError::DimensionMismatch {
            field: "obs_dim",
            expected: OBS_DIM as u64 + 1,
            got: OBS_DIM as u64,
        }
    );
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn validate_rejects_truncated_column_and_names_it() {
    let mut batch = valid_batch();
    batch.next_obs.pop();

    let err = validate(&batch).unwrap_err();
    assert_eq!(
        err,
        ProtoError::ColumnLength {
            column: "next_obs",
            expected: 5 * OBS_DIM as u64,
            got: 5 * OBS_DIM as u64 - 1,
        }
    );
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
    assert!(
        status.message().contains("`reward` row 2"),
        "{}",
        status.message()
    );
}

#[test]
fn validate_rejects_infinite_obs_naming_row_and_element() {
    let mut batch = valid_batch();
    batch.obs[4 * OBS_DIM + 1] = f32::INFINITY;

    let err = validate(&batch).unwrap_err();
    assert_eq!(
        err,
        ProtoError::NonFinite {
            column: "obs",
            row: 4,
            element: 1,
            value: f64::INFINITY,
        }
    );
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn builder_rejects_non_finite_values_before_they_reach_the_wire() {
    let mut builder = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
    let mut row = Row::numbered(0);
    row.next_obs[2] = f32::NEG_INFINITY;

    let err = builder.push(row.as_transition()).unwrap_err();
    assert!(matches!(
        err,
        ProtoError::NonFinite {
            column: "next_obs",
            row: 0,
            element: 2,
            ..
        }
    ));
    assert!(builder.is_empty());
}

#[test]
fn builder_rejects_vectors_of_the_wrong_length() {
    let mut builder = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
    let mut row = Row::numbered(0);
    row.action.push(0.0);

    assert_eq!(
        builder.push(row.as_transition()),
        Err(ProtoError::ColumnLength {
            column: "action",
            expected: ACT_DIM as u64,
            got: ACT_DIM as u64 + 1,
        })
    );
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
    assert_eq!(
        err,
        ProtoError::TooManyRows {
            rows: MAX_ROWS as u64 + 1,
            max: MAX_ROWS as u64,
        }
    );
    assert_eq!(err.to_status().code(), Code::ResourceExhausted);
    assert_eq!(
        batch.validate(OBS_DIM, ACT_DIM, MAX_ROWS + 1),
        Ok(MAX_ROWS + 1)
    );
}

#[test]
fn validate_rejects_empty_batch() {
    let batch = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM).finish("actor-test", 1);

    let err = validate(&batch).unwrap_err();
    assert_eq!(
        err,
        ProtoError::Empty {
            message: "TransitionBatch"
        }
    );
    assert_eq!(err.to_status().code(), Code::InvalidArgument);
}

#[test]
fn validate_rejects_missing_actor_id_and_zero_sequence() {
    let mut batch = valid_batch();
    batch.actor_id.clear();
    assert!(matches!(
        validate(&batch),
        Err(ProtoError::InvalidField {
            field: "actor_id",
            ..
        })
    ));

    let mut batch = valid_batch();
    batch.actor_id = "x".repeat(mapless_proto::MAX_ACTOR_ID_BYTES + 1);
    assert!(matches!(
        validate(&batch),
        Err(ProtoError::InvalidField {
            field: "actor_id",
            ..
        })
    ));

    let mut batch = valid_batch();
    batch.sequence = 0;
    assert!(matches!(
        validate(&batch),
        Err(ProtoError::InvalidField {
            field: "sequence",
            ..
        })
    ));
}

#[test]
fn proto_error_converts_into_tonic_status() {
    let status: tonic::Status = ProtoError::TooManyRows { rows: 2, max: 1 }.into();
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert_eq!(
        mapless_proto::check_protocol_version(ProtocolVersion::V1 as i32),
        Ok(())
    );
    assert_eq!(mapless_proto::PROTOCOL_VERSION, ProtocolVersion::V1 as u32);
}
