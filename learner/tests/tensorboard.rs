//! TensorBoard event files: TFRecord framing with masked CRC-32C, a `brain.Event:2` header
//! record, scalar events read back exactly. No TensorFlow or TensorBoard needed.

use std::time::Duration;

use mapless_learner::LearnerError;
use mapless_learner::tensorboard::{Event, FILE_VERSION, Scalar, SummaryWriter, crc32c, frame_record, masked_crc32c, read_events, read_records, read_scalars};
use prost::Message as _;

#[test]
// The mask is written out as the TFRecord spec states it, to check `rotate_right` against it.
#[allow(clippy::manual_rotate)]
fn crc32c_matches_the_castagnoli_check_values() {
    // The standard check value of CRC-32C, and the iSCSI test vectors of RFC 3720 B.4.
    assert_eq!(crc32c(b"123456789"), 0xE306_9283);
    assert_eq!(crc32c(&[0u8; 32]), 0x8A91_36AA);
    assert_eq!(crc32c(&[0xFFu8; 32]), 0x62A8_AB43);
    let ascending: Vec<u8> = (0..32).collect();
    assert_eq!(crc32c(&ascending), 0x46DD_794E);
    assert_eq!(crc32c(b""), 0);
    // Not zlib's IEEE CRC-32.
    assert_ne!(crc32c(b"123456789"), crc32fast::hash(b"123456789"));
    // The TFRecord mask: rotate right by 15, add 0xa282ead8.
    let c = crc32c(b"abc");
    assert_eq!(masked_crc32c(b"abc"), ((c >> 15) | (c << 17)).wrapping_add(0xa282_ead8));
}

#[test]
fn frame_record_lays_out_length_crc_data_crc() {
    let mut out = Vec::new();
    frame_record(b"hello", &mut out);
    assert_eq!(out.len(), 8 + 4 + 5 + 4);
    assert_eq!(&out[..8], &5u64.to_le_bytes());
    assert_eq!(&out[8..12], &masked_crc32c(&5u64.to_le_bytes()).to_le_bytes());
    assert_eq!(&out[12..17], b"hello");
    assert_eq!(&out[17..], &masked_crc32c(b"hello").to_le_bytes());
}

#[test]
fn scalars_written_are_read_back_exactly_with_valid_crcs() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path;
    let written = [
        ("losses/critic", 1, 0.5f32),
        ("losses/actor", 1, -1.25),
        ("charts/updates_per_s", 2, 1234.5),
        ("losses/critic", 2, 0.0),
        ("losses/critic", 3, f32::MIN_POSITIVE),
        ("charts/episode_return", 1_000_000_000_000, 3642.0),
    ];
    {
        let mut writer = SummaryWriter::create(&dir.path().join("run1")).expect("create");
        path = writer.path().to_owned();
        for (tag, step, value) in written {
            writer.add_scalar_at(tag, step, value, 1_700_000_000.5 + step as f64).expect("add");
        }
        // Dropping the writer flushes what is buffered.
    }
    let name = path.file_name().expect("name").to_string_lossy().into_owned();
    assert!(name.starts_with("events.out.tfevents."), "{name}");
    let secs: &str = name.trim_start_matches("events.out.tfevents.").split('.').next().expect("secs");
    assert!(secs.len() >= 10 && secs.chars().all(|c| c.is_ascii_digit()), "{name}");

    let events = read_events(&path).expect("every CRC checks out");
    assert_eq!(events.len(), written.len() + 1);
    assert_eq!(events[0].file_version.as_deref(), Some(FILE_VERSION));
    assert!(events[0].summary.is_none());
    assert!(events[0].wall_time > 1.6e9, "wall time is now, in seconds");

    let scalars = read_scalars(&path).expect("scalars");
    let expected: Vec<Scalar> = written.iter().map(|&(tag, step, value)| Scalar { tag: tag.to_owned(), step, value, wall_time: 1_700_000_000.5 + step as f64 }).collect();
    assert_eq!(scalars, expected);
    // A zero is written explicitly (TensorBoard needs simple_value present to see a scalar).
    let zero = &events[4].summary.as_ref().expect("summary").value[0];
    assert_eq!(zero.simple_value, Some(0.0));

    // The records decode as Events field by field with the documented numbers: wall_time is
    // field 1 (fixed64 tag 0x09), step field 2 (varint tag 0x10), summary field 5 (0x2a).
    let records = read_records(&path).expect("records");
    assert_eq!(records[1][0], 0x09);
    assert_eq!(records[1][9], 0x10);
    assert!(records[1].contains(&0x2a));
    assert_eq!(Event::decode(records[1].as_slice()).expect("decode"), events[1]);
}

#[test]
fn explicit_flush_makes_scalars_visible_while_the_writer_lives() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut writer = SummaryWriter::create(dir.path()).expect("create").with_flush_interval(Duration::from_secs(3600));
    assert_eq!(read_events(writer.path()).expect("header record").len(), 1, "the header is written at once");
    writer.add_scalar("losses/critic", 10, 2.5).expect("add");
    writer.flush().expect("flush");
    let scalars = read_scalars(writer.path()).expect("read");
    assert_eq!(scalars.len(), 1);
    assert_eq!((scalars[0].tag.as_str(), scalars[0].step, scalars[0].value), ("losses/critic", 10, 2.5));

    // Many scalars trigger writes on their own (size threshold), none lost or reordered.
    for step in 0..5_000 {
        writer.add_scalar("charts/sps", step, step as f32).expect("add");
    }
    writer.flush().expect("flush");
    let scalars = read_scalars(writer.path()).expect("read");
    assert_eq!(scalars.len(), 5_001);
    assert!(scalars[1..].iter().enumerate().all(|(i, s)| s.step == i as i64 && s.value == i as f32));

    assert!(matches!(writer.add_scalar("", 0, 1.0), Err(LearnerError::EventFile { .. })), "empty tag refused");
}

#[test]
fn two_writers_in_one_directory_get_separate_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let a = SummaryWriter::create(dir.path()).expect("a");
    let b = SummaryWriter::create(dir.path()).expect("b");
    assert_ne!(a.path(), b.path());
}

#[test]
fn corrupt_event_files_are_clear_errors() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = {
        let mut writer = SummaryWriter::create(dir.path()).expect("create");
        writer.add_scalar("losses/critic", 1, 1.0).expect("add");
        writer.path().to_owned()
    };
    let good = std::fs::read(&path).expect("read");
    let check = |bytes: &[u8], needle: &str| {
        std::fs::write(&path, bytes).expect("write");
        match read_events(&path) {
            Err(e @ LearnerError::EventFile { .. }) => {
                assert!(e.to_string().contains(needle), "`{needle}` in {e}")
            }
            other => panic!("expected an EventFile error with `{needle}`, got {other:?}"),
        }
    };
    let mut data_flip = good.clone();
    let last = data_flip.len() - 6;
    data_flip[last] ^= 0x40;
    check(&data_flip, "data CRC mismatch");
    let mut length_flip = good.clone();
    length_flip[0] ^= 0x01;
    check(&length_flip, "length CRC mismatch");
    check(&good[..good.len() - 2], "runs past the end");
    check(&good[..good.len() - (good.len() - 5)], "truncated header");
}
