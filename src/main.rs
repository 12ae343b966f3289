//! The `glint` binary: everything is in [`cli`] (argument parsing and the commands) and in
//! the `glint` library.

mod cli;

fn main() -> std::process::ExitCode {
    cli::main()
}
