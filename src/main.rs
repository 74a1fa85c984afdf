//! The `flowram` command line: thin subcommands over the library (see `flowram --help`).
mod cli;

fn main() -> std::process::ExitCode {
    cli::run()
}
