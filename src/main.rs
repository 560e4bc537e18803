//! `stylenerf`: the all-in-one binary. Every command group lives in its own module under
//! `cli/`; this file only parses the command line, sets up logging and dispatches.

mod cli;

use clap::Parser;

fn main() -> std::process::ExitCode {
    stylenerf_engine::keep_freed_memory();
    let mut args = cli::Cli::parse();
    // Still the only thread: the allocator's arenas are chosen per thread.
    if args.command.runs_stages() {
        stylenerf_engine::one_arena_for_all_threads();
    }
    cli::quiet_default_logs(&mut args);
    cli::init_tracing(&args.global);
    match cli::run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => cli::report(&err),
    }
}
