//! `mapless` — the command-line entry point; the commands live in the library (`src/lib.rs`).

fn main() -> std::process::ExitCode {
    mapless_cli::main()
}
