//! `stylenerf demo`: the whole service in one process. Generates the default scene and paints
//! the bundled styles into a data folder, starts an embedded coordinator (SQLite and artifacts
//! under the same folder) and one in-process worker, submits the job through the client
//! library, shows the per-stage progress bars of `stylenerf watch`, downloads the outputs and
//! prints where the stylized frames, animations, contact sheets and `eval.md` are.
//!
//! Re-running with the same data folder reuses what is there: the scene and style images are
//! kept, and the job is found again by its idempotency key (derived from the preset, styles and
//! overrides), so a finished job is only downloaded again (unchanged files are skipped) and an
//! interrupted one resumes from its last checkpoint. A job that failed or was cancelled is
//! submitted anew under the next key. Ctrl-C stops the worker cleanly: the running stage
//! checkpoints, uploads the checkpoint and releases its lease.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use stylenerf_client::{names, pb, Client, Input, JobSpec};
use stylenerf_engine::image_io::save_rgb_png;
use stylenerf_engine::scene::generate::{generate, GenerateOptions};
use stylenerf_engine::scene::nerfstudio::TRANSFORMS;
use stylenerf_engine::style2d::images::StyleImage;
use stylenerf_server::{Coordinator, CoordinatorConfig};
use stylenerf_worker::{Worker, WorkerConfig};

use super::client::follow;
use super::client_args::parse_overrides;
use super::coordinator::shutdown_signal;

/// Options of `stylenerf demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Folder for the scene, styles, coordinator database and artifacts, and the outputs.
    #[arg(long, default_value = "stylenerf-demo")]
    pub data_dir: PathBuf,
    /// Training preset: tiny (seconds, for tests), quick (the CPU demo), standard or paper.
    #[arg(long, default_value = "quick")]
    pub preset: String,
    /// Bundled styles to use, comma-separated (mosaic, waves, dots).
    #[arg(long, value_delimiter = ',', default_value = "mosaic,waves")]
    pub styles: Vec<String>,
    /// Override a stage setting: `--set nerf_pretrain.steps=500`.
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Compute device of the in-process worker: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(demo(args))
}

async fn demo(args: DemoArgs) -> anyhow::Result<()> {
    let overrides = parse_overrides(&args.overrides)?;
    std::fs::create_dir_all(&args.data_dir)
        .with_context(|| format!("creating {}", args.data_dir.display()))?;
    let data_dir = args.data_dir.canonicalize()?;
    let scene = prepare_scene(&data_dir.join("scene"))?;
    let styles = paint_styles(&data_dir.join("styles"), &args.styles)?;

    let coordinator_config =
        super::common::with_engine_checks(CoordinatorConfig::local(&data_dir.join("coordinator")));
    let coordinator = Coordinator::start(coordinator_config)
        .await
        .context("starting the embedded coordinator")?;
    let endpoint = coordinator.endpoint();
    eprintln!("coordinator on {endpoint} (data in {})", data_dir.display());

    let mut config = WorkerConfig::new(endpoint.clone());
    config.name = "demo".into();
    config.device = args.device.clone();
    config.scratch_dir = Some(data_dir.join("worker"));
    let worker = Worker::register(config).await?;
    let handle = worker.handle();
    let mut worker_task = tokio::spawn(worker.run());

    let client = Client::connect(&endpoint, None).await?;
    let mut spec = JobSpec::new(Input::path(&scene), styles.iter().map(Input::path));
    spec.name = "demo".into();
    spec.preset = Some(args.preset.clone());
    spec.overrides = overrides;
    let job = submit_or_reuse(&client, spec).await?;

    let mut sink = std::io::sink();
    let outcome = tokio::select! {
        followed = follow(&client, &job.id, false, &mut sink) => Some(followed),
        _ = shutdown_signal() => None,
        joined = &mut worker_task => {
            let summary = joined.context("the worker panicked")??;
            anyhow::bail!("the worker stopped unexpectedly ({summary:?})");
        }
    };
    if outcome.is_none() {
        eprintln!("stopping: the running stage checkpoints and releases its task (Ctrl-C again exits now)");
        tokio::spawn(async {
            shutdown_signal().await;
            std::process::exit(130);
        });
    }
    handle.shutdown();
    let summary = worker_task.await.context("the worker panicked")??;
    let downloaded = match &outcome {
        Some(Ok(())) => {
            let out = data_dir.join("outputs");
            let files = client.download(&job.id, &out).await?;
            let fresh = files.iter().filter(|f| !f.skipped).count();
            eprintln!(
                "downloaded {} files ({fresh} new) to {}",
                files.len(),
                out.display()
            );
            Some(out)
        }
        _ => None,
    };
    coordinator.shutdown().await?;
    match outcome {
        None => {
            anyhow::bail!(
                "interrupted: the running stage was checkpointed ({} released); run the same \
                 command again to resume job {}",
                summary.released,
                job.id
            )
        }
        Some(Err(e)) => Err(e),
        Some(Ok(())) => {
            print_outputs(&downloaded.expect("downloaded on success"), &args.styles)?;
            Ok(())
        }
    }
}

/// Generates the default scene into `dir` unless a previous run did.
fn prepare_scene(dir: &Path) -> anyhow::Result<PathBuf> {
    if dir.join(TRANSFORMS).is_file() {
        eprintln!("scene: {} (already generated)", dir.display());
        return Ok(dir.to_path_buf());
    }
    let options = GenerateOptions::default();
    eprintln!(
        "generating the default scene ({} views of {}x{} px) into {}",
        options.views,
        options.size,
        options.size,
        dir.display()
    );
    let staging = dir.with_extension("partial");
    if staging.exists() {
        std::fs::remove_dir_all(&staging)?;
    }
    generate(&options, &staging)?;
    if dir.exists() {
        std::fs::remove_dir_all(dir)?;
    }
    std::fs::rename(&staging, dir)?;
    Ok(dir.to_path_buf())
}

/// Paints the named bundled styles into `dir` as PNG files (kept across runs).
fn paint_styles(dir: &Path, names: &[String]) -> anyhow::Result<Vec<PathBuf>> {
    anyhow::ensure!(!names.is_empty(), "--styles: name at least one style");
    std::fs::create_dir_all(dir)?;
    names
        .iter()
        .map(|name| {
            let image = StyleImage::load(&format!("{}{name}", StyleImage::BUILTIN))
                .with_context(|| format!("--styles {name}"))?
                .image;
            let path = dir.join(format!("{name}.png"));
            if !path.is_file() {
                save_rgb_png(&path, image.width(), image.height(), image.as_raw())?;
            }
            Ok(path)
        })
        .collect()
}

/// The idempotency key of a demo job: the same settings find the same job again.
fn idempotency_key(spec: &JobSpec, generation: u32) -> String {
    let styles: Vec<String> = spec
        .styles
        .iter()
        .map(|s| match s {
            Input::Path(p) => p.file_stem().unwrap_or_default().to_string_lossy().into(),
            other => format!("{other:?}"),
        })
        .collect();
    let overrides = serde_json::Value::Object(spec.overrides.clone()).to_string();
    let mut key = format!(
        "demo/{}/{}/{overrides}",
        spec.preset.as_deref().unwrap_or_default(),
        styles.join("+")
    );
    if key.len() > 180 {
        // Keep the key within the coordinator's limit; the overrides hash keeps it unique.
        key = format!("demo/{}/{:x}", styles.join("+"), fnv1a(key.as_bytes()));
    }
    if generation > 0 {
        key.push_str(&format!("#{generation}"));
    }
    key
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Submits the demo job, or returns the job an earlier run created with the same settings.
/// Jobs that failed or were cancelled are skipped by moving to the next key generation.
async fn submit_or_reuse(client: &Client, mut spec: JobSpec) -> anyhow::Result<pb::Job> {
    for generation in 0..1000 {
        spec.idempotency_key = Some(idempotency_key(&spec, generation));
        let submission = client.submit(&spec).await?;
        let job = submission.job;
        let state = pb::JobState::try_from(job.state).unwrap_or_default();
        if submission.created {
            eprintln!("submitted job {}", job.id);
            return Ok(job);
        }
        match state {
            pb::JobState::Failed | pb::JobState::Cancelled => continue,
            pb::JobState::Succeeded => {
                eprintln!("job {} finished in an earlier run; reusing it", job.id)
            }
            _ => eprintln!(
                "resuming job {} of an earlier run ({})",
                job.id,
                names::job_state(job.state)
            ),
        }
        return Ok(job);
    }
    anyhow::bail!("too many failed demo jobs in this data folder; use a new --data-dir")
}

/// Prints where the interesting outputs are.
fn print_outputs(out: &Path, styles: &[String]) -> anyhow::Result<()> {
    println!("\nOutputs in {}:", out.display());
    let stylized = out.join("render_stylized");
    let mut specs: Vec<PathBuf> = std::fs::read_dir(&stylized)
        .with_context(|| format!("reading {}", stylized.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    specs.sort();
    for spec in specs {
        let name = spec.file_name().unwrap_or_default().to_string_lossy();
        // `style-<i>` is the i-th style of the job, in the order given.
        let style = name
            .strip_prefix("style-")
            .and_then(|i| i.parse::<usize>().ok())
            .and_then(|i| styles.get(i))
            .map_or(String::new(), |s| format!(" ({s})"));
        println!("  {name}{style}:");
        for (what, path) in [
            ("frames", spec.join("frames")),
            ("animation", spec.join("animation.gif")),
            ("animation (mp4)", spec.join("animation.mp4")),
            ("contact sheet", spec.join("sheet.png")),
        ] {
            if path.exists() {
                println!("    {what:<16} {}", path.display());
            }
        }
    }
    let sheets = out.join("decoder_pretrain").join("sheets");
    if sheets.is_dir() {
        println!("  2D decoder contact sheets: {}", sheets.display());
    }
    let eval = stylized.join("eval.md");
    if eval.is_file() {
        println!(
            "  evaluation (consistency, style fidelity): {}",
            eval.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_the_settings_and_stay_short() {
        let mut spec = JobSpec::new(
            Input::path("s"),
            [Input::path("a/mosaic.png"), Input::path("b/waves.png")],
        );
        spec.preset = Some("quick".into());
        assert_eq!(idempotency_key(&spec, 0), "demo/quick/mosaic+waves/{}");
        assert_eq!(idempotency_key(&spec, 2), "demo/quick/mosaic+waves/{}#2");
        spec.overrides
            .insert("nerf_pretrain.steps".into(), "x".repeat(300).into());
        let long = idempotency_key(&spec, 1);
        assert!(long.len() < 200 && long.ends_with("#1"), "{long}");
    }
}
