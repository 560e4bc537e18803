//! `stylenerf worker`: leases stage tasks from a coordinator and runs them until Ctrl-C or
//! SIGTERM, then checkpoints the running tasks, uploads the checkpoints and releases their
//! leases (see `docs/OPERATIONS.md`).

use stylenerf_worker::WorkerArgs;

/// Options of `stylenerf worker`.
#[derive(Debug, clap::Args)]
pub struct WorkerCommand {
    #[command(flatten)]
    pub args: WorkerArgs,
}

pub fn run(command: WorkerCommand) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(stylenerf_worker::run_until_signal(
        command.args.into_config(),
    ))?;
    Ok(())
}
