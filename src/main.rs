//! The `flowram` command line: thin subcommands over the library (see `flowram --help`).
mod cli;

/// Counts allocations inside control ticks (`bench realtime`); otherwise the system allocator.
#[global_allocator]
static ALLOCATOR: flowram::runtime::alloc_count::CountingAllocator = flowram::runtime::alloc_count::CountingAllocator;

fn main() -> std::process::ExitCode {
    // Thread pools and malloc thresholds for the policy's CPU speed; see policy::runtime.
    flowram::policy::runtime::configure_process();
    // MuJoCo's warnings go to stderr (stdout carries --json output).
    flowram::sim::logging::set_warning_handler(|message| eprintln!("{message}"));
    cli::run()
}
