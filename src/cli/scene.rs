//! `stylenerf scene …`: generate procedural scenes, recover camera poses for plain photos or a
//! video (COLMAP), compare poses, and inspect datasets.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Subcommand, ValueEnum};
use stylenerf_engine::poses::{
    self, align, CameraModel, Matcher, PosesOptions, PosesReport, VideoSampling,
};
use stylenerf_engine::scene::generate::{self, CameraRig, GenerateOptions, Surroundings};
use stylenerf_engine::scene::{LoadOptions, Scene, SceneFormat};
use stylenerf_engine::stages::{Outcome, StageControl};

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
        /// Camera layout: a 360° spiral orbit, a forward-facing grid, or one turn around the
        /// subject at a fixed height (as a phone video circles it).
        #[arg(long, value_enum, default_value_t = Kind::Orbit)]
        kind: Kind,
        /// Around the table: a solid colour stated in the dataset (plain), a sky at infinity,
        /// a room past the content box, or that room with marbled (never repeating) surfaces,
        /// which structure from motion needs (the last three look like real captures).
        #[arg(long, value_enum, default_value_t = Around::Plain)]
        surroundings: Around,
    },
    /// Camera poses for plain photos or a video, with COLMAP (from the OS packages): writes a
    /// nerfstudio dataset (transforms.json, images at the working resolution) and a report.
    /// Rerun with the same --out to resume after an interruption.
    FromPhotos {
        /// A folder of photos (PNG/JPEG) or a video file (frames sampled with ffmpeg).
        input: PathBuf,
        /// Output folder (COLMAP's work files go to its colmap/ folder).
        #[arg(long)]
        out: PathBuf,
        /// Longest side of the written images, in pixels.
        #[arg(long, default_value_t = 1024)]
        max_side: u32,
        /// Longest side COLMAP extracts features at (smaller is faster, larger finds more).
        #[arg(long, default_value_t = PosesOptions::default().feature_max_side)]
        feature_max_side: u32,
        /// Most SIFT features kept per image (CPU matching time grows with its square).
        #[arg(long, default_value_t = PosesOptions::default().max_features)]
        max_features: u32,
        /// Feature matching: auto picks sequential for a video, exhaustive for up to 300
        /// photos, a vocabulary tree (built from the photos' own features) above.
        #[arg(long, value_enum, default_value_t = MatcherArg::Auto)]
        matcher: MatcherArg,
        /// Camera model COLMAP estimates, shared by all images.
        #[arg(long, value_enum, default_value_t = CameraArg::Opencv)]
        camera_model: CameraArg,
        /// Video only: candidate frames per second.
        #[arg(long, default_value_t = 4.0)]
        fps: f32,
        /// Video only: frames kept at most (the sharpest of each stretch).
        #[arg(long, default_value_t = 150)]
        max_frames: usize,
        /// Fail when fewer than this fraction of the images are registered.
        #[arg(long, default_value_t = 0.5)]
        min_registered: f64,
    },
    /// Compare the camera poses of two datasets of the same photos (matched by file name)
    /// after the similarity transform that best aligns them.
    ComparePoses {
        /// transforms.json (or its folder) whose poses are measured.
        #[arg(long)]
        recovered: PathBuf,
        /// transforms.json (or its folder) taken as the truth.
        #[arg(long)]
        reference: PathBuf,
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
    Turntable,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Around {
    Plain,
    Sky,
    Room,
    Gallery,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum MatcherArg {
    Auto,
    Exhaustive,
    Sequential,
    VocabTree,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum CameraArg {
    Opencv,
    SimpleRadial,
    Pinhole,
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
                Kind::Turntable => CameraRig::Turntable,
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
                    Around::Gallery => Surroundings::Gallery,
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
        SceneCommand::FromPhotos {
            input,
            out,
            max_side,
            feature_max_side,
            max_features,
            matcher,
            camera_model,
            fps,
            max_frames,
            min_registered,
        } => {
            let opts = PosesOptions {
                max_side,
                feature_max_side,
                max_features,
                matcher: match matcher {
                    MatcherArg::Auto => Matcher::Auto,
                    MatcherArg::Exhaustive => Matcher::Exhaustive,
                    MatcherArg::Sequential => Matcher::Sequential,
                    MatcherArg::VocabTree => Matcher::VocabTree,
                },
                camera_model: match camera_model {
                    CameraArg::Opencv => CameraModel::Opencv,
                    CameraArg::SimpleRadial => CameraModel::SimpleRadial,
                    CameraArg::Pinhole => CameraModel::Pinhole,
                },
                video: VideoSampling {
                    fps,
                    max_frames,
                    ..PosesOptions::default().video
                },
                min_registered,
            };
            anyhow::ensure!(
                [max_side, feature_max_side]
                    .iter()
                    .all(|s| (8..=16384).contains(s)),
                "--max-side and --feature-max-side must be in 8..=16384"
            );
            anyhow::ensure!(
                (64..=65536).contains(&max_features),
                "--max-features must be in 64..=65536"
            );
            anyhow::ensure!(
                fps > 0.0 && max_frames >= 3,
                "--fps must be positive and --max-frames at least 3"
            );
            let start = Instant::now();
            let control = StageControl::default();
            let report = match poses::run(&input, &out.join("colmap"), &out, &opts, &control, None)?
            {
                Outcome::Done(report) => report,
                Outcome::Stopped { step } => anyhow::bail!("stopped after step {step}"),
            };
            print_poses(&report);
            println!(
                "wrote {} in {:.1?}; next: stylenerf run --data {}",
                out.join("transforms.json").display(),
                start.elapsed(),
                out.display()
            );
            Ok(())
        }
        SceneCommand::ComparePoses {
            recovered,
            reference,
        } => {
            let file = |p: PathBuf| {
                if p.is_dir() {
                    p.join("transforms.json")
                } else {
                    p
                }
            };
            let rec = align::read_transforms(&file(recovered))?;
            let truth = align::read_transforms(&file(reference))?;
            let names: Vec<&String> = rec.keys().filter(|n| truth.contains_key(*n)).collect();
            let a: Vec<_> = names.iter().map(|n| rec[*n]).collect();
            let b: Vec<_> = names.iter().map(|n| truth[*n]).collect();
            let e = align::pose_errors(&a, &b).with_context(|| {
                format!(
                    "{} cameras in common: need at least 3 not on one line",
                    names.len()
                )
            })?;
            println!(
                "cameras     {} in common ({} recovered, {} reference)",
                e.cameras,
                rec.len(),
                truth.len()
            );
            println!(
                "rotation    median {:.3}°, max {:.3}°",
                e.median_rotation_deg, e.max_rotation_deg
            );
            println!(
                "position    median {:.2}%, max {:.2}% of the camera spread",
                e.median_position * 100.0,
                e.max_position * 100.0
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
                None => stylenerf_engine::scene::detect(&data)?.0,
            };
            let scene = Scene::load(&data, &opts)?;
            print_summary(detected, &scene);
            Ok(())
        }
    }
}

fn print_poses(r: &PosesReport) {
    println!(
        "registered  {} of {} images ({:.0}%)",
        r.registered,
        r.images,
        100.0 * r.registered as f64 / r.images.max(1) as f64
    );
    if !r.unregistered.is_empty() {
        println!("not placed  {}", r.unregistered.join(", "));
    }
    println!(
        "sparse      {} points, mean reprojection error {:.3} px, {:.0} features per image",
        r.points, r.mean_reprojection_px, r.mean_features
    );
    println!("matcher     {:?}, camera {:?}", r.matcher, r.camera_model);
    println!("resolution  {}×{}", r.resolution.0, r.resolution.1);
    let steps: Vec<String> = r
        .seconds
        .iter()
        .map(|(k, v)| format!("{k} {v:.1}s"))
        .collect();
    println!("time        {}", steps.join(", "));
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
