//! `stylenerf scene …`: generate procedural scenes and inspect datasets.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Subcommand, ValueEnum};
use stylenerf_engine::scene::generate::{self, CameraRig, GenerateOptions, Surroundings};
use stylenerf_engine::scene::{LoadOptions, Scene, SceneFormat};

#[derive(Debug, Subcommand)]
pub enum SceneCommand {
    /// Render a procedural scene (textured objects on a floor, with ground-truth depth) as a
    /// nerfstudio dataset; the forward kind also writes LLFF `poses_bounds.npy`.
    Generate {
        /// Output folder (must be missing or empty).
        #[arg(long)]
        out: PathBuf,
        /// Image width and height in pixels.
        #[arg(long, default_value_t = 128)]
        size: u32,
        /// Number of views (every 8th is a test view when loaded).
        #[arg(long, default_value_t = 48)]
        views: usize,
        /// Seed of the layout, colours, patterns and light.
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Camera layout: a 360° orbit or a forward-facing grid.
        #[arg(long, value_enum, default_value_t = Kind::Orbit)]
        kind: Kind,
        /// Around the table: a solid colour stated in the dataset (plain), a sky at infinity,
        /// or a room past the content box (the last two look like real captures).
        #[arg(long, value_enum, default_value_t = Around::Plain)]
        surroundings: Around,
    },
    /// Check that a dataset loads and print a summary.
    Info {
        /// Dataset folder (or its transforms.json / poses_bounds.npy).
        #[arg(long)]
        data: PathBuf,
        /// Read as this format instead of detecting it.
        #[arg(long, value_enum)]
        format: Option<Format>,
        /// Shrink images by this integer factor.
        #[arg(long, default_value_t = 1)]
        downscale: u32,
        /// Working resolution: shrink images so their longest side is at most this.
        #[arg(long)]
        max_side: Option<u32>,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Kind {
    Orbit,
    Forward,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Around {
    Plain,
    Sky,
    Room,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Format {
    Nerfstudio,
    Blender,
    Llff,
}

pub fn run(cmd: SceneCommand) -> anyhow::Result<()> {
    match cmd {
        SceneCommand::Generate {
            out,
            size,
            views,
            seed,
            kind,
            surroundings,
        } => {
            let rig = match kind {
                Kind::Orbit => CameraRig::Orbit,
                Kind::Forward => CameraRig::Forward,
            };
            let opts = GenerateOptions {
                rig,
                size,
                views,
                seed,
                surroundings: match surroundings {
                    Around::Plain => Surroundings::Plain,
                    Around::Sky => Surroundings::Sky,
                    Around::Room => Surroundings::Room,
                },
            };
            let start = Instant::now();
            generate::generate(&opts, &out)
                .with_context(|| format!("generating a scene into {}", out.display()))?;
            println!(
                "wrote {views} views of {size}×{size} ({kind:?}, seed {seed}) to {} in {:.1?}",
                out.display(),
                start.elapsed()
            );
            Ok(())
        }
        SceneCommand::Info {
            data,
            format,
            downscale,
            max_side,
        } => {
            let opts = LoadOptions {
                format: format.map(|f| match f {
                    Format::Nerfstudio => SceneFormat::Nerfstudio,
                    Format::Blender => SceneFormat::Blender,
                    Format::Llff => SceneFormat::Llff,
                }),
                downscale,
                max_side,
                ..LoadOptions::default()
            };
            let detected = match opts.format {
                Some(f) => f,
                None => SceneFormat::detect(&data)?.0,
            };
            let scene = Scene::load(&data, &opts)?;
            print_summary(detected, &scene);
            Ok(())
        }
    }
}

fn print_summary(format: SceneFormat, scene: &Scene) {
    let (w, h) = scene.resolution();
    let with_depth = scene.frames.iter().filter(|f| f.depth.is_some()).count();
    let k = scene.frames.first().map(|f| f.camera.intrinsics);
    println!("format      {format}");
    println!("root        {}", scene.root.display());
    println!(
        "frames      {} ({} train, {} test)",
        scene.frames.len(),
        scene.train.len(),
        scene.test.len()
    );
    println!("resolution  {w}×{h}");
    if let Some(k) = k {
        println!("focal       fx {:.2}, fy {:.2}", k.fx, k.fy);
    }
    println!(
        "aabb        [{:.3}, {:.3}, {:.3}] – [{:.3}, {:.3}, {:.3}]",
        scene.aabb.min.x,
        scene.aabb.min.y,
        scene.aabb.min.z,
        scene.aabb.max.x,
        scene.aabb.max.y,
        scene.aabb.max.z
    );
    println!("near, far   {:.3}, {:.3}", scene.near, scene.far);
    match scene.ndc {
        Some(ndc) => println!("rays        NDC (forward-facing, near plane {})", ndc.near),
        None if scene.unbounded => {
            println!("rays        world, unbounded (space beyond the box contracted)")
        }
        None => println!("rays        world"),
    }
    println!("background  {}", scene.background);
    println!("depth       {with_depth} of {} frames", scene.frames.len());
}
