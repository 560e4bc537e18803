//! Camera poses from plain images with COLMAP (`engine/src/poses`), checked against the
//! generator's ground truth: a turntable of the gallery scene as photos and as a video, a
//! stopped run resumed at its next step, a set COLMAP cannot solve refused with its cause, and
//! an output folder that would overwrite the photos and a file that is no video refused.
//! Needs `colmap` and `ffmpeg` from the OS packages; without them the tests say so and pass,
//! unless `STYLENERF_REQUIRE_TEST_TOOLS` is set, as `.ci/run` does.

use std::path::Path;
use std::process::Command;

use stylenerf_engine::checkpoint::CheckpointDir;
use stylenerf_engine::poses::{self, align, PosesOptions, PosesReport, Tool};
use stylenerf_engine::scene::generate::{generate, CameraRig, GenerateOptions, Surroundings};
use stylenerf_engine::scene::{LoadOptions, Scene};
use stylenerf_engine::stages::{Outcome, StageControl};

const VIEWS: usize = 30;
// Every view registers here; the assertions leave room for three not to (COLMAP's threads
// may order work differently on another machine).

fn tools_present() -> bool {
    let present = Tool::colmap().is_ok() && Tool::ffmpeg().is_ok();
    if !present {
        assert!(
            std::env::var_os("STYLENERF_REQUIRE_TEST_TOOLS").is_none(),
            "STYLENERF_REQUIRE_TEST_TOOLS is set but colmap or ffmpeg is not installed"
        );
        eprintln!("skipped: colmap or ffmpeg not installed (.ci/run installs them)");
    }
    present
}

fn turntable(dir: &Path) {
    let opts = GenerateOptions {
        rig: CameraRig::Turntable,
        size: 192,
        views: VIEWS,
        seed: 7,
        surroundings: Surroundings::Gallery,
    };
    generate(&opts, dir).unwrap();
}

fn done(outcome: Outcome<PosesReport>) -> PosesReport {
    match outcome {
        Outcome::Done(r) => r,
        Outcome::Stopped { step } => panic!("stopped at {step}"),
    }
}

/// Median rotation (degrees) and position (fraction of the spread) errors of `recovered`'s
/// cameras against `truth`'s, paired by `pair(recovered name) -> truth name`.
fn errors(recovered: &Path, truth: &Path, pair: impl Fn(&str) -> String) -> (usize, f64, f64) {
    let rec = align::read_transforms(&recovered.join("transforms.json")).unwrap();
    let gt = align::read_transforms(&truth.join("transforms.json")).unwrap();
    let (a, b): (Vec<_>, Vec<_>) = rec.iter().map(|(n, p)| (*p, gt[&pair(n)])).unzip();
    let e = align::pose_errors(&a, &b).unwrap();
    (e.cameras, e.median_rotation_deg, e.median_position)
}

#[test]
fn photos_of_a_generated_turntable_get_the_generators_poses_and_a_stopped_run_resumes() {
    if !tools_present() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    turntable(&scene);
    let (work, out) = (tmp.path().join("work"), tmp.path().join("out"));
    let opts = PosesOptions {
        max_side: 128,
        ..PosesOptions::default()
    };
    // Stopped after two steps (frames, features), then resumed on "another machine" (the work
    // folder gone, its checkpoint kept, as a worker's task is): features are not extracted
    // again.
    let mut stop = StageControl::default();
    stop.stop_after_step = Some(2);
    let snapshots = CheckpointDir::new(tmp.path().join("ckpt"), 1);
    let first = poses::run(
        &scene.join("images"),
        &work,
        &out,
        &opts,
        &stop,
        Some(&snapshots),
    )
    .unwrap();
    assert!(matches!(first, Outcome::Stopped { step: 2 }));
    assert!(!out.join("transforms.json").exists());
    assert_eq!(snapshots.steps().unwrap(), [2]);
    std::fs::remove_dir_all(&work).unwrap();
    let report = done(
        poses::run(
            &scene.join("images"),
            &work,
            &out,
            &opts,
            &StageControl::default(),
            Some(&snapshots),
        )
        .unwrap(),
    );
    let log = std::fs::read_to_string(work.join("colmap.log")).unwrap();
    assert_eq!(
        log.matches("feature_extractor").count(),
        1,
        "features extracted twice"
    );

    assert_eq!(report.images, VIEWS);
    assert!(report.registered as f64 >= 0.9 * VIEWS as f64, "{report:?}");
    assert!(report.mean_reprojection_px < 1.5, "{report:?}");
    assert_eq!(report.resolution, (128, 128));
    let (cameras, rot, pos) = errors(&out, &scene, |n| n.to_string());
    assert_eq!(cameras, report.registered);
    assert!(rot <= 2.0 && pos <= 0.05, "rotation {rot}°, position {pos}");

    // The output is a dataset the loader reads at the written resolution.
    let loaded = Scene::load(&out, &LoadOptions::default()).unwrap();
    assert_eq!(loaded.frames.len(), report.registered);
    assert_eq!(loaded.resolution(), (128, 128));
    assert!(loaded.unbounded, "a capture with a room is unbounded");

    // Each frame has a sparse depth map from the points it observes, in the model's units:
    // scaled by the similarity that maps the recovered cameras onto the generator's, it is the
    // generator's depth at those pixels.
    let truth = Scene::load(
        &scene,
        &LoadOptions {
            max_side: Some(128),
            ..LoadOptions::default()
        },
    )
    .unwrap();
    let truth_of = |name: &str| truth.frames.iter().find(|f| f.name == name).unwrap();
    let (from, to): (Vec<_>, Vec<_>) = loaded
        .frames
        .iter()
        .map(|f| (f.camera.position, truth_of(&f.name).camera.position))
        .map(|(a, b)| (a.as_dvec3(), b.as_dvec3()))
        .unzip();
    let scale = align::similarity(&from, &to).unwrap().scale as f32;
    let mut relative = Vec::new();
    for frame in &loaded.frames {
        let (sparse, dense) = (
            frame.depth.as_ref().unwrap(),
            truth_of(&frame.name).depth.as_ref().unwrap(),
        );
        relative.extend(
            sparse
                .iter()
                .zip(dense)
                .filter(|(s, t)| **s > 0.0 && **t > 0.0)
                .map(|(s, t)| (s * scale - t).abs() / t),
        );
    }
    relative.sort_by(f32::total_cmp);
    let per_frame = relative.len() / loaded.frames.len();
    let median = relative[relative.len() / 2];
    eprintln!("sparse depth: {per_frame} points per frame, median relative error {median}");
    assert!(
        per_frame > 50 && median < 0.02,
        "{per_frame} points per frame, median {median}"
    );
}

#[test]
#[ignore = "flaky: COLMAP on this 192² video leaves the turn's last 7-8 frames out, or places \
            them 4° off, in about 2 runs of 5 (not so through `scene from-photos` on the same \
            video); run with --ignored"]
fn a_turntable_video_gets_the_generators_poses() {
    if !tools_present() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene");
    turntable(&scene);
    let video = tmp.path().join("turntable.mp4");
    let status = Command::new("ffmpeg")
        .args(["-nostdin", "-loglevel", "error", "-framerate", "6", "-i"])
        .arg(scene.join("images/frame_%05d.png"))
        .args(["-c:v", "libx264", "-crf", "12", "-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(status.success());
    // One candidate per video frame, all kept: frame k of the output is view k.
    let mut opts = PosesOptions::default();
    opts.video.fps = 6.0;
    let out = tmp.path().join("out");
    let report = done(
        poses::run(
            &video,
            &tmp.path().join("work"),
            &out,
            &opts,
            &StageControl::default(),
            None,
        )
        .unwrap(),
    );
    assert_eq!(report.images, VIEWS);
    assert!(report.registered as f64 >= 0.9 * VIEWS as f64, "{report:?}");
    let transforms = std::fs::read_to_string(out.join("transforms.json")).unwrap();
    assert!(transforms.contains("\"sharpness\""));
    let (_, rot, pos) = errors(&out, &scene, |n| n.to_string());
    assert!(rot <= 2.0 && pos <= 0.05, "rotation {rot}°, position {pos}");
}

#[test]
fn unsolvable_images_get_their_likely_cause_and_an_output_over_the_input_is_refused() {
    if !tools_present() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let photos = tmp.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for i in 0..4u8 {
        let img = image::RgbImage::from_pixel(64, 64, image::Rgb([40 * i, 90, 200]));
        img.save(photos.join(format!("plain_{i}.png"))).unwrap();
    }
    let err = poses::run(
        &photos,
        &tmp.path().join("work"),
        &tmp.path().join("out"),
        &PosesOptions::default(),
        &StageControl::default(),
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("registered 0 of 4 images"), "{err}");
    assert!(err.contains("textureless"), "{err}");
    assert!(!tmp.path().join("out/transforms.json").exists());

    // An output folder whose images/ is the input is refused before anything runs.
    let photos_in_place = tmp.path().join("capture/images");
    std::fs::create_dir_all(&photos_in_place).unwrap();
    let err = poses::run(
        &photos_in_place,
        &tmp.path().join("work2"),
        &tmp.path().join("capture"),
        &PosesOptions::default(),
        &StageControl::default(),
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("would replace the photos"), "{err}");

    // A "video" ffmpeg cannot decode is named as the input at fault.
    let video = tmp.path().join("holiday.mp4");
    std::fs::write(&video, b"not a video at all").unwrap();
    let err = poses::run(
        &video,
        &tmp.path().join("work3"),
        &tmp.path().join("out3"),
        &PosesOptions::default(),
        &StageControl::default(),
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("holiday.mp4") && err.contains("cannot read it as a video"),
        "{err}"
    );
}
