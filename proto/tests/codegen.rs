//! The Rust under `src/gen/` is generated from `proto/mapless/v1/*.proto` and checked in, so
//! that no crate depending on `mapless-proto` needs `protoc` at build time. This test
//! regenerates it into a temporary directory and fails on any difference, so the checked-in
//! code can never drift from the `.proto` files.
//!
//! To update the checked-in code after editing a `.proto` file:
//!
//! ```text
//! MAPLESS_REGEN_PROTO=1 cargo test -p mapless-proto --test codegen
//! ```

use std::fs;
use std::path::{Path, PathBuf};

/// Environment variable that turns the check into an overwrite.
const REGEN_ENV: &str = "MAPLESS_REGEN_PROTO";

fn crate_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Every `.proto` file of the contract, sorted so that generation is independent of directory
/// order. New files under `proto/mapless/v1/` are picked up without editing this test.
fn proto_files(include_dir: &Path) -> Vec<PathBuf> {
    let dir = include_dir.join("mapless").join("v1");
    let mut files: Vec<PathBuf> = fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
        .map(|entry| entry.expect("readable directory entry").path())
        .filter(|path| path.extension().is_some_and(|ext| ext == "proto"))
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no .proto files in {}", dir.display());
    files
}

/// Generates messages, servers and clients into `out_dir` with the vendored `protoc`.
fn generate(out_dir: &Path) {
    let include_dir = crate_dir().join("proto");
    let protos = proto_files(&include_dir);
    let protoc = protoc_bin_vendored::protoc_bin_path().expect("vendored protoc for this platform");

    let mut config = tonic_prost_build::Config::new();
    config.protoc_executable(protoc);
    // The `bytes *_f32le` float columns decode as `bytes::Bytes`, which borrows from tonic's
    // receive buffer instead of copying (transition.proto, "Two encodings"). Other `bytes`
    // fields (NamedTensor.data) stay `Vec<u8>`.
    config.bytes([".mapless.v1.TransitionBatch", ".mapless.v1.SampledBatch"]);

    tonic_prost_build::configure()
        .build_server(true)
        .build_client(true)
        .build_transport(true)
        .out_dir(out_dir)
        .compile_with_config(config, &protos, &[include_dir])
        .expect("protoc and code generation succeed");
}

/// Names of the `.rs` files directly inside `dir`, sorted.
fn rust_files(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
        .map(|entry| entry.expect("readable directory entry").file_name())
        .filter_map(|name| name.into_string().ok())
        .filter(|name| name.ends_with(".rs"))
        .collect();
    names.sort();
    names
}

/// A fresh, empty directory under the system temp dir, unique to this process.
fn scratch_dir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mapless-proto-codegen-{}", std::process::id()));
    if dir.exists() {
        fs::remove_dir_all(&dir).expect("remove stale scratch dir");
    }
    fs::create_dir_all(&dir).expect("create scratch dir");
    dir
}

/// First line on which two texts differ, for a readable failure message.
fn first_difference(checked_in: &str, generated: &str) -> String {
    let mut checked_lines = checked_in.lines();
    let mut generated_lines = generated.lines();
    for line_no in 1.. {
        match (checked_lines.next(), generated_lines.next()) {
            (Some(a), Some(b)) if a == b => continue,
            (None, None) => return "only line endings differ".to_owned(),
            (a, b) => {
                return format!("line {line_no}:\n  checked in: {}\n  generated:  {}", a.unwrap_or("<end of file>"), b.unwrap_or("<end of file>"));
            }
        }
    }
    unreachable!("the loop returns")
}

#[test]
fn checked_in_generated_code_matches_proto_files() {
    let checked_in_dir = crate_dir().join("src").join("gen");
    let generated_dir = scratch_dir();
    generate(&generated_dir);

    let regenerate = std::env::var_os(REGEN_ENV).is_some_and(|v| v == "1");
    let generated_names = rust_files(&generated_dir);
    assert!(!generated_names.is_empty(), "code generation produced no files");

    let mut problems = Vec::new();
    for name in &generated_names {
        let generated = fs::read_to_string(generated_dir.join(name)).expect("read generated file");
        let target = checked_in_dir.join(name);
        if regenerate {
            fs::create_dir_all(&checked_in_dir).expect("create src/gen");
            fs::write(&target, &generated).expect("write src/gen file");
            continue;
        }
        match fs::read_to_string(&target) {
            Ok(checked_in) if checked_in == generated => {}
            Ok(checked_in) => problems.push(format!("src/gen/{name} is out of date; first difference at {}", first_difference(&checked_in, &generated))),
            Err(e) => problems.push(format!("src/gen/{name} is missing ({e})")),
        }
    }
    // A file that generation no longer produces (a renamed package) must not linger.
    for name in rust_files(&checked_in_dir) {
        if !generated_names.contains(&name) {
            if regenerate {
                fs::remove_file(checked_in_dir.join(&name)).expect("remove stale src/gen file");
            } else {
                problems.push(format!("src/gen/{name} is not produced by the .proto files any more"));
            }
        }
    }
    fs::remove_dir_all(&generated_dir).expect("remove scratch dir");

    assert!(
        problems.is_empty(),
        "checked-in generated code differs from what the .proto files generate:\n- {}\n\n\
         Regenerate it with:\n  {REGEN_ENV}=1 cargo test -p mapless-proto --test codegen\n\
         and commit the .proto change together with src/gen/.",
        problems.join("\n- ")
    );
}
