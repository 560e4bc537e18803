//! `stylenerf scene …`: generate procedural scenes and inspect datasets.

use clap::Subcommand;

#[derive(Debug, Subcommand)]
pub enum SceneCommand {
    /// Check that a dataset loads and print a summary.
    Info {
        /// Dataset folder.
        #[arg(long)]
        data: std::path::PathBuf,
    },
}

pub fn run(cmd: SceneCommand) -> anyhow::Result<()> {
    match cmd {
        SceneCommand::Info { data } => {
            anyhow::bail!("{}: scene loading not built yet", data.display())
        }
    }
}
