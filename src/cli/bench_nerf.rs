//! `stylenerf bench nerf`: trains the field on a dataset (by default the generated 360° scene)
//! at the preset's working resolution and prints test PSNR against training time, samples per
//! second, depth error and peak memory.

use std::path::PathBuf;

use clap::Args;
use stylenerf_engine::scene::generate::{generate, CameraRig, GenerateOptions};
use stylenerf_engine::scene::Scene;
use stylenerf_engine::stages::nerf_pretrain::{self, NerfConfig};
use stylenerf_engine::stages::Outcome;
use stylenerf_plan::Stage;

use super::common::{stage_progress, TrainingArgs};

#[derive(Debug, Args)]
pub struct BenchNerfArgs {
    /// A dataset to train on instead of the generated scene (e.g. a real capture).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Image size of the generated scene.
    #[arg(long, default_value_t = 128)]
    pub size: u32,
    /// Number of generated views (every 8th is a test view).
    #[arg(long, default_value_t = 48)]
    pub views: usize,
    /// Test-PSNR measurements during training.
    #[arg(long, default_value_t = 8)]
    pub evals: u64,
    /// Working folder (default: a temporary folder, removed afterwards).
    #[arg(long)]
    pub work: Option<PathBuf>,
    #[command(flatten)]
    pub training: TrainingArgs,
}

/// Peak resident memory of this process (Linux), in MiB.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

pub fn run(args: BenchNerfArgs) -> anyhow::Result<()> {
    let tmp = tempfile::tempdir()?;
    let work = args
        .work
        .clone()
        .unwrap_or_else(|| tmp.path().to_path_buf());
    let data = args.data.clone().unwrap_or_else(|| work.join("scene"));
    if args.data.is_none() && !data.join("transforms.json").exists() {
        let opts = GenerateOptions {
            rig: CameraRig::Orbit,
            size: args.size,
            views: args.views,
            seed: 7,
            ..GenerateOptions::default()
        };
        generate(&opts, &data)?;
    }
    let mut cfg: NerfConfig = args
        .training
        .config(Stage::NerfPretrain, NerfConfig::preset)?;
    let scene = Scene::load(&data, &cfg.load_options())?;
    cfg.eval_every = (cfg.steps / args.evals.max(1)).max(1);
    let out = work.join(format!("nerf-{}", args.training.preset));
    if out.exists() {
        std::fs::remove_dir_all(&out)?;
    }
    let (bar, control) = stage_progress("nerf_pretrain");
    let outcome = nerf_pretrain::run(&scene, &cfg, &out, &control, &args.training.device()?)?;
    bar.finish_and_clear();
    let Outcome::Done(report) = outcome else {
        anyhow::bail!("training stopped early")
    };
    let (w, h) = scene.resolution();
    let name = match &args.data {
        Some(d) => d.display().to_string(),
        None => "generated orbit".to_string(),
    };
    println!(
        "scene: {name}, {w}x{h}, {} train / {} test views, background {}{}; preset {} ({} steps)",
        scene.train.len(),
        scene.test.len(),
        scene.background,
        if scene.unbounded { ", unbounded" } else { "" },
        args.training.preset,
        cfg.steps
    );
    println!("| step | train seconds | test PSNR (dB) |");
    println!("|---:|---:|---:|");
    for (step, seconds, psnr) in &report.psnr_curve {
        println!("| {step} | {seconds:.1} | {psnr:.2} |");
    }
    println!(
        "samples/s (with gradients): {:.0}",
        report.samples_per_second
    );
    if let (Some(mae), Some(rel)) = (report.depth_mae, report.depth_mae_relative) {
        println!("depth MAE on test pixels with opacity > 0.5: {mae:.4} world units = {:.2}% of the scene extent", rel * 100.0);
    }
    if let Some(m) = report.depth_median_relative_error {
        println!("median relative depth error: {:.2}%", m * 100.0);
    }
    if let Some(o) = report.empty_opacity {
        println!("mean opacity where the truth sees nothing (background at infinity): {o:.3}");
    }
    if let Some(o) = report.test_opacity {
        println!("mean opacity of the test pixels: {o:.3}");
    }
    println!(
        "samples per ray (training): {:.1}; occupied cells: {:.1}%",
        report.samples_per_ray,
        report.occupied_fraction * 100.0
    );
    if let Some(rss) = peak_rss_mib() {
        println!("peak RSS: {rss:.0} MiB");
    }
    Ok(())
}
