//! Command-line interface: the top-level command tree and the options every command shares.

use clap::{Args, Parser, Subcommand};
use stylenerf_worker::logging::LogFormat;

mod bench_chaos;
mod bench_coordinator;
mod bench_nerf;
mod bench_uploads;
mod bench_vgg;
mod client;
mod client_args;
mod client_format;
mod client_view;
mod common;
mod coordinator;
mod demo;
mod health;
mod nerf;
mod run;
mod scene;
mod stylize;
mod terminal_safe;
mod up;
mod weights;
mod worker;

/// StylizedNeRF: consistent 3D scene stylization as a distributed training service.
#[derive(Debug, Parser)]
#[command(name = "stylenerf", version, about)]
pub struct Cli {
    #[command(flatten)]
    pub global: GlobalArgs,
    #[command(subcommand)]
    pub command: Command,
}

/// Options shared by every command.
#[derive(Debug, Args)]
pub struct GlobalArgs {
    /// Log filter (tracing `EnvFilter` syntax), e.g. `info` or `stylenerf_engine=debug`.
    #[arg(long, global = true, env = "STYLENERF_LOG", default_value = "info")]
    pub log: String,
    /// Log format.
    #[arg(long, global = true, env = "STYLENERF_LOG_FORMAT", value_enum, default_value_t = LogFormat::Pretty)]
    pub log_format: LogFormat,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// The whole service in one process: generate the default scene, paint the bundled
    /// styles, start a coordinator and a worker, train, and print where the results are.
    Demo(demo::DemoArgs),
    /// A local cluster: a coordinator plus N worker processes, until Ctrl-C.
    Up(up::UpArgs),
    /// Generate or inspect scenes.
    #[command(subcommand)]
    Scene(scene::SceneCommand),
    /// Train a radiance field and render its views.
    #[command(subcommand)]
    Nerf(nerf::NerfCommand),
    /// 2D style transfer with AdaIN.
    #[command(subcommand)]
    Stylize(stylize::StylizeCommand),
    /// Import and inspect pretrained VGG encoder weights.
    #[command(subcommand)]
    Weights(weights::WeightsCommand),
    /// Run the coordinator: the gRPC job and worker APIs, SQLite, artifacts, metrics.
    Coordinator(Box<coordinator::CoordinatorCommand>),
    /// Run all five stages locally in one process (no server): NeRF pretraining, view
    /// rendering, decoder pretraining, mutual learning and stylized rendering.
    Run(Box<run::RunArgs>),
    /// Evaluate a finished `run`: consistency (warped error) and style fidelity of NeRF→AdaIN,
    /// the fine-tuned decoder and the stylized NeRF.
    Eval(run::EvalArgs),
    /// Run a worker: lease stage tasks from a coordinator and train them (CPU or CUDA).
    Worker(Box<worker::WorkerCommand>),
    #[command(flatten)]
    Client(client_args::ClientCommand),
    /// Print a shell completion script: `stylenerf completions bash > ~/.local/share/bash-completion/completions/stylenerf`.
    Completions {
        /// bash, zsh, fish, elvish or powershell
        shell: clap_complete::Shell,
    },
    /// Probe a coordinator's gRPC health (exit 0 when serving) or a worker's HTTP `/healthz`:
    /// the containers' health check.
    Health(health::HealthArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
}

/// `stylenerf bench ...`
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Radiance-field training: test PSNR against time, samples/s, depth error, peak RSS.
    Nerf(bench_nerf::BenchNerfArgs),
    /// Coordinator throughput and latency on loopback with a real SQLite file.
    Coordinator(stylenerf_server::bench::BenchOptions),
    /// VGG encoder forward and forward+backward time, frozen vs plain convolutions.
    Vgg(bench_vgg::BenchVggArgs),
    /// The service under SIGKILLs: jobs complete, stages complete once, kills cost at most a
    /// checkpoint interval.
    Chaos(bench_chaos::BenchChaosArgs),
    /// A resumable upload against a one-stream `Upload` of the same archive.
    Uploads(bench_uploads::BenchUploadsArgs),
}

impl Command {
    /// Whether this command trains or renders in this process (and so wants every thread on
    /// one allocator arena; see `stylenerf_engine::one_arena_for_all_threads`). A coordinator
    /// on its own (`coordinator`, `up`, its benchmarks) and the client commands do not.
    pub fn runs_stages(&self) -> bool {
        match self {
            Command::Demo(_)
            | Command::Scene(_)
            | Command::Nerf(_)
            | Command::Stylize(_)
            | Command::Run(_)
            | Command::Eval(_)
            | Command::Worker(_) => true,
            Command::Bench(b) => matches!(b, BenchCommand::Nerf(_) | BenchCommand::Vgg(_)),
            Command::Up(_)
            | Command::Weights(_)
            | Command::Coordinator(_)
            | Command::Client(_)
            | Command::Completions { .. }
            | Command::Health(_) => false,
        }
    }
}

/// `demo` draws progress bars on stderr: unless a log level was asked for, keep the embedded
/// coordinator's and worker's info logs from interleaving with them.
pub fn quiet_default_logs(cli: &mut Cli) {
    if matches!(cli.command, Command::Demo(_))
        && cli.global.log == "info"
        && std::env::var_os("STYLENERF_LOG").is_none()
    {
        cli.global.log = "warn".into();
    }
}

/// Reports a command's error on stderr and picks the exit status. Output cut short by its
/// reader (`stylenerf events J | head`) is not an error. Each cause is printed once: a context
/// that already quotes its source's message does not get it repeated.
pub fn report(err: &anyhow::Error) -> std::process::ExitCode {
    let broken_pipe = err.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
    });
    if broken_pipe {
        return std::process::ExitCode::SUCCESS;
    }
    eprintln!("error: {}", describe(err));
    std::process::ExitCode::FAILURE
}

/// The error and its causes joined by `: `, leaving out a cause whose message the text so far
/// already ends with or contains.
fn describe(err: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in err.chain() {
        let message = cause.to_string();
        if text.contains(&message) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&message);
    }
    text
}

pub fn init_tracing(global: &GlobalArgs) {
    stylenerf_worker::logging::init(&global.log, global.log_format);
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Demo(args) => demo::run(args),
        Command::Up(args) => up::run(args),
        Command::Scene(cmd) => scene::run(cmd),
        Command::Nerf(cmd) => nerf::run(cmd),
        Command::Stylize(cmd) => stylize::run(cmd),
        Command::Weights(cmd) => weights::run(cmd),
        Command::Coordinator(cmd) => coordinator::run(*cmd),
        Command::Run(args) => run::run(*args),
        Command::Eval(args) => run::eval(args),
        Command::Worker(cmd) => worker::run(*cmd),
        Command::Client(cmd) => client::run(cmd),
        Command::Bench(BenchCommand::Coordinator(options)) => bench_coordinator::run(options),
        Command::Bench(BenchCommand::Nerf(args)) => bench_nerf::run(args),
        Command::Bench(BenchCommand::Vgg(args)) => bench_vgg::run(args),
        Command::Bench(BenchCommand::Chaos(args)) => bench_chaos::run(args),
        Command::Bench(BenchCommand::Uploads(args)) => bench_uploads::run(args),
        Command::Health(args) => health::run(args),
        Command::Completions { shell } => {
            let mut command = <Cli as clap::CommandFactory>::command();
            let mut script = Vec::new();
            clap_complete::generate(shell, &mut command, "stylenerf", &mut script);
            std::io::Write::write_all(&mut std::io::stdout(), &script)?;
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    #[test]
    fn each_cause_is_said_once_and_a_closed_pipe_is_not_an_error() {
        let missing = std::io::Error::new(
            std::io::ErrorKind::NotFound,
            "No such file or directory (os error 2)",
        );
        let err = Err::<(), _>(missing)
            .context("No such file or directory (os error 2)")
            .context("reading scene.tar")
            .unwrap_err();
        assert_eq!(
            describe(&err),
            "reading scene.tar: No such file or directory (os error 2)"
        );
        let pipe = std::io::Error::new(std::io::ErrorKind::BrokenPipe, "Broken pipe");
        let err = Err::<(), _>(pipe).context("printing events").unwrap_err();
        assert_eq!(report(&err), std::process::ExitCode::SUCCESS);
    }
}
