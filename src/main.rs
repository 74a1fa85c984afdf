//! The `flowram` command line: thin subcommands over the library (see `flowram --help`).
mod cli;

fn main() -> std::process::ExitCode {
    // candle runs element-wise ops on its own spinning thread pool, which fights rayon's (the
    // scan kernels, convolutions, FPS) for the cores: one element-wise thread is faster here
    // (policy end to end 284 -> 242 ms on 2 cores). A value set by the user wins.
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        // SAFETY: first statement of main, before any thread exists.
        unsafe { std::env::set_var("CANDLE_NUM_THREADS", "1") };
    }
    cli::run()
}
