//! Bakes libtorch's library directory into this package's executables as an rpath, so tests
//! and binaries run without `LD_LIBRARY_PATH`.
//!
//! Why this file exists, and why it is per package:
//! - torch-sys (`links = "tch"`) finds libtorch (here `$LIBTORCH`, set by `.cargo/config.toml`)
//!   and reports its library directory as `cargo:libtorch_lib=<dir>`. Cargo passes that on as
//!   `DEP_TCH_LIBTORCH_LIB`, but only to build scripts of packages that list torch-sys as a
//!   *direct* `[dependencies]` entry; depending on tch alone is not enough.
//! - torch-sys's own `-Wl,-rpath` goes to its C++ shim's compile step, never to the final link.
//! - `cargo::rustc-link-arg` applies only to the targets of the package that emits it (a
//!   library's build script cannot give its dependents an rpath).
//!
//! So every package that links an executable against libtorch (`learner` for the
//! `mapless-learner` binary, its tests and benches; `tests` for the learner's integration tests)
//! needs `torch-sys.workspace = true` under
//! `[dependencies]` and a copy of this file. It is written to be copied verbatim.
//!
//! It also keeps libtorch's CUDA backend in the link. Nothing in tch refers to a symbol of
//! libtorch_cuda.so (the backend registers itself from static constructors), so the linker's
//! default `--as-needed` drops it, and then `tch::Cuda::is_available()` is false even on a GPU
//! box. When the libtorch has a libtorch_cuda.so we link it with `--no-as-needed`, as one
//! comma-joined `-Wl` argument so rustc cannot reorder the pieces. The price on CPU-only
//! machines: executables load the CUDA libraries at start-up (they are installed anyway).
//!
//! The rpath is libtorch's `lib/` only. libtorch's own libraries carry
//! `$ORIGIN/../../nvidia/*/lib` RPATHs that find the CUDA runtime wheels next to them in
//! site-packages (needed even on CPU-only machines: libtorch.so links libtorch_cuda.so).
//! The path is kept as given (`.torch/libtorch` is a symlink) rather than canonicalised, so
//! re-running `scripts/setup-torch.sh` with another Python minor version keeps binaries valid.

use std::env;
use std::path::Path;

fn main() {
    // Inputs: this file, torch-sys's output (cargo tracks that for `links` dependencies) and
    // the libtorch lib dir (below).
    println!("cargo::rerun-if-changed=build.rs");

    let target_os = env::var("CARGO_CFG_TARGET_OS").unwrap_or_default();
    if target_os != "linux" && target_os != "macos" {
        // No rpath on Windows: the DLLs must be on PATH.
        return;
    }
    match env::var("DEP_TCH_LIBTORCH_LIB") {
        Ok(dir) if !dir.is_empty() => {
            println!("cargo::rustc-link-arg=-Wl,-rpath,{dir}");
            // Relink when the libtorch variant under the same path changes (CPU <-> CUDA).
            println!("cargo::rerun-if-changed={dir}");
            if target_os == "linux" && Path::new(&dir).join("libtorch_cuda.so").exists() {
                println!("cargo::rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
            }
            // Lets tests check what was linked against.
            println!("cargo::rustc-env=MAPLESS_LIBTORCH_LIB={dir}");
        }
        _ => println!(
            "cargo::warning=DEP_TCH_LIBTORCH_LIB is not set (is torch-sys a direct [dependencies] \
             entry of this package?); executables will need LD_LIBRARY_PATH to find libtorch"
        ),
    }
}
