//! The coordinator's page in a real browser: headless Chromium, driven by Playwright
//! (`tests/web/drive.mjs`), signs in, submits a tiny job from the form with a generated scene
//! archive and two paintings, watches it finish on the job page, sees its animations and
//! training curves, and requests a style-blend render whose animation then appears — against
//! a coordinator and a worker running as processes of the built binary. Its screenshots are
//! kept in `target/web-screenshots/` for a person to open, and checked here for content.
//!
//! Needs Node.js, Chromium (`STYLENERF_CHROMIUM`, default `/usr/bin/chromium`) and the npm
//! package playwright-core (`STYLENERF_PLAYWRIGHT`: the `node_modules` folder holding it,
//! default `target/ci-tools/web/node_modules`); `.ci/run` installs them. Without them the test
//! says so and passes, unless `STYLENERF_REQUIRE_TEST_TOOLS` is set, as `.ci/run` does.

mod support;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;
use stylenerf_engine::image_io::{load_rgb, save_rgb_png};
use stylenerf_engine::style2d::painted;
use support::{log_tail, run, Service, CLIENT_TOKEN};

/// Chromium, Node.js and playwright-core, if all are there.
fn browser_tools() -> Option<(PathBuf, PathBuf)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let chromium = PathBuf::from(
        std::env::var_os("STYLENERF_CHROMIUM").unwrap_or_else(|| "/usr/bin/chromium".into()),
    );
    let playwright = std::env::var_os("STYLENERF_PLAYWRIGHT")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("target/ci-tools/web/node_modules"));
    let node = Command::new("node").arg("--version").output();
    let found = chromium.is_file()
        && playwright.join("playwright-core").is_dir()
        && node.is_ok_and(|o| o.status.success());
    found.then_some((chromium, playwright))
}

/// Distinct colours in a screenshot (a blank or error page has a handful).
fn colours(path: &Path) -> usize {
    let image = load_rgb(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut seen: Vec<[u8; 3]> = image
        .pixels()
        .map(|p| p.0.map(|c| (c * 255.0).round() as u8))
        .collect();
    seen.sort_unstable();
    seen.dedup();
    seen.len()
}

#[test]
fn a_person_submits_watches_and_blends_a_job_in_chromium() {
    let Some((chromium, playwright)) = browser_tools() else {
        assert!(
            std::env::var_os("STYLENERF_REQUIRE_TEST_TOOLS").is_none(),
            "STYLENERF_REQUIRE_TEST_TOOLS is set but Chromium, Node.js or playwright-core was \
             not found (STYLENERF_CHROMIUM, STYLENERF_PLAYWRIGHT)"
        );
        eprintln!("skipped: no Chromium, Node.js or playwright-core (.ci/run installs them)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene_dir = d.join("scene").display().to_string();
    run(&[
        "scene", "generate", "--out", &scene_dir, "--size", "24", "--views", "6",
    ]);
    let scene = stylenerf_client::pack_scene(&d.join("scene")).unwrap();
    let mut styles = Vec::new();
    for name in ["waves", "mosaic"] {
        let path = d.join(format!("{name}.png"));
        let image = painted::paint(name, 48).unwrap();
        save_rgb_png(&path, 48, 48, image.as_raw()).unwrap();
        styles.push(path.display().to_string());
    }
    let shots = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/web-screenshots");
    let _ = std::fs::remove_dir_all(&shots);
    std::fs::create_dir_all(&shots).unwrap();

    // Every heartbeat's progress stored, so that even short stages draw a curve.
    let extra = [
        "--progress-event-interval",
        "0",
        "--heartbeat-interval",
        "0.3",
    ];
    let service = Service::start(d, &extra);
    let started = Instant::now();
    let output = Command::new("node")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/web/drive.mjs"))
        .env("BASE", &service.http)
        .env("TOKEN", CLIENT_TOKEN)
        .env("SCENE", &scene.path)
        .env("STYLES", styles.join(":"))
        .env(
            "OVERRIDES",
            r#"{"nerf_pretrain.steps": 40, "decoder_pretrain.steps": 4, "mutual_learning.steps": 8}"#,
        )
        .env("SHOTS", &shots)
        .env("CHROMIUM", &chromium)
        .env("PLAYWRIGHT", &playwright)
        .env("TIMEOUT_MS", "400000")
        .output()
        .unwrap();
    // What the page did, seen through the API: the job succeeded and the blend was queued.
    let job = tokio::runtime::Runtime::new().unwrap().block_on(async {
        let client = stylenerf_client::Client::connect(&service.endpoint, Some(CLIENT_TOKEN))
            .await
            .unwrap();
        let listed = client.list(&Default::default()).await.unwrap().jobs;
        match listed.first() {
            Some(job) => Some(client.get(&job.id).await.unwrap()),
            None => None,
        }
    });
    drop(service);
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "drive.mjs failed after {:?}:\nstdout: {stdout}\nstderr: {}\ncoordinator log: {}\n\
         worker log: {}\nscreenshots: {}",
        started.elapsed(),
        String::from_utf8_lossy(&output.stderr),
        log_tail(d, "coordinator.log"),
        log_tail(d, "worker.log"),
        shots.display()
    );
    let summary: serde_json::Value =
        serde_json::from_str(stdout.trim().lines().last().unwrap()).expect("a JSON summary");
    // Every stage succeeded, as the timeline shows it.
    let stages: Vec<(String, String)> = serde_json::from_value(summary["stages"].clone()).unwrap();
    assert_eq!(
        stages.len(),
        stylenerf_plan::Source::Dataset.stages().len(),
        "{summary}"
    );
    assert!(stages.iter().all(|(_, s)| s == "succeeded"), "{summary}");
    // An animation and a contact sheet per painting loaded; the curves were drawn.
    let images: Vec<String> = serde_json::from_value(summary["images"].clone()).unwrap();
    let animations = images
        .iter()
        .filter(|i| i.ends_with("animation.gif"))
        .count();
    let sheets = images.iter().filter(|i| i.ends_with("sheet.png")).count();
    assert!(animations >= 2 && sheets >= 2, "{summary}");
    assert!(summary["plots"].as_u64().unwrap() >= 1, "{summary}");
    assert_eq!(summary["blendRequested"], true);
    let after: Vec<String> =
        serde_json::from_value(summary["animationsAfterBlend"].clone()).unwrap();
    assert_eq!(
        after.len(),
        3,
        "the blend's animation appeared on the page: {summary}"
    );
    let job = job.expect("the page's job is listed");
    assert_eq!(summary["jobId"], job.id.as_str());
    assert_eq!(job.name, "from the browser");
    let renders = job
        .tasks
        .iter()
        .filter(|t| t.stage() == stylenerf_client::pb::Stage::RenderStylized)
        .count();
    assert_eq!(renders, 2, "the final render and the blend: {job:?}");
    assert_eq!(
        summary["pageErrors"].as_array().unwrap().len(),
        0,
        "{summary}"
    );
    // Text pages have the shades of anti-aliased text; pages with the renders, many more.
    for (shot, least) in [
        ("1-jobs.png", 10),
        ("2-new-job.png", 10),
        ("3-job-finished.png", 500),
        ("4-blend-requested.png", 500),
    ] {
        let n = colours(&shots.join(shot));
        assert!(n >= least, "{shot} has {n} colours: is it blank?");
    }
}
