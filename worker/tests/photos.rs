//! A job from plain photos through the service: photos of a generated turntable (no camera
//! poses) uploaded, the real worker (which finds COLMAP and advertises it) starts the `poses`
//! stage and is stopped after its first checkpoint (COLMAP's work folder), a second worker
//! resumes it at the next step and runs every other stage on the dataset it wrote, and the job
//! succeeds with the recovered poses stored. Needs `colmap` from the OS packages; without it the test says so
//! and passes, unless `STYLENERF_REQUIRE_TEST_TOOLS` is set, as `.ci/run` does.

mod support;

use std::time::Duration;

use stylenerf_engine::poses::Tool;
use stylenerf_engine::scene::generate::{generate, CameraRig, GenerateOptions, Surroundings};
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::{png, tar_dir, upload, uploaded, Source};
use stylenerf_worker::{TaskResult, WorkerEvent};
use support::*;

const VIEWS: usize = 30;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn photos_become_a_finished_job_through_the_poses_stage() {
    if Tool::colmap().is_err() {
        assert!(
            std::env::var_os("STYLENERF_REQUIRE_TEST_TOOLS").is_none(),
            "STYLENERF_REQUIRE_TEST_TOOLS is set but colmap is not installed"
        );
        eprintln!("skipped: colmap not installed (.ci/run installs it)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    generate(
        &GenerateOptions {
            rig: CameraRig::Turntable,
            size: 192,
            views: VIEWS,
            seed: 7,
            surroundings: Surroundings::Gallery,
        },
        &scene,
    )
    .unwrap();
    // Only the photos travel: no transforms.json, no depth.
    let photos = tar_dir("turntable", &scene.join("images"));

    let coordinator = coordinator(dir.path()).await;
    let mut client = jobs(&coordinator).await;
    let receipt = upload(
        &mut client,
        pb::UploadKind::Photos,
        "turntable.tar",
        &photos,
    )
    .await
    .expect("photos accepted");
    assert_eq!(receipt.summary, format!("{VIEWS} photos in turntable/"));
    let style = upload(
        &mut client,
        pb::UploadKind::StyleImage,
        "s.png",
        &png(48, 48),
    )
    .await
    .unwrap();
    let job = client
        .create_job(pb::CreateJobRequest {
            dataset: Some(uploaded(&receipt)),
            styles: vec![uploaded(&style)],
            preset: "tiny".into(),
            ..Default::default()
        })
        .await
        .expect("job created")
        .into_inner()
        .job
        .unwrap();

    // The first worker stops once a checkpoint of COLMAP's state is stored.
    let first = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let ckpt = format!("jobs/{}/poses/ckpt/", job.id);
    eventually(
        "a poses checkpoint stored",
        Duration::from_secs(60),
        || async {
            let keys = list(&coordinator, &ckpt).await;
            keys.iter().any(|k| k.ends_with(".json")).then_some(())
        },
    )
    .await;
    let summary = first.stop().await;
    assert_eq!(summary.released, 1, "{summary:?}");

    let mut worker = spawn_worker(worker_config(&coordinator, dir.path())).await;
    let resumed_from = worker
        .wait_for(Duration::from_secs(30), |e| match e {
            WorkerEvent::TaskStarted { resumed_from, .. } => Some(*resumed_from),
            _ => None,
        })
        .await;
    assert!(resumed_from >= 1, "resumed from step {resumed_from}");
    for expected in Source::Photos.stages().into_iter().map(pb::Stage::from) {
        let (stage, result) = worker
            .wait_for(Duration::from_secs(300), |event| match event {
                WorkerEvent::TaskFinished { stage, result, .. } => Some((*stage, result.clone())),
                _ => None,
            })
            .await;
        assert_eq!(stage, expected);
        let TaskResult::Completed { metrics, .. } = result else {
            panic!("{stage:?} did not complete: {result:?}");
        };
        if stage == pb::Stage::Poses {
            assert_eq!(metrics["resumed_from"], resumed_from as f64);
            // How many COLMAP places varies from run to run on this small turntable (the
            // engine's test grades the poses); the stage fails below half.
            assert_eq!(metrics["images"], VIEWS as f64, "{metrics:?}");
            assert!(metrics["registered"] >= 0.5 * VIEWS as f64, "{metrics:?}");
        }
    }
    worker.stop().await;

    let job = get_job(&coordinator, &job.id).await;
    assert_eq!(job.state, pb::JobState::Succeeded as i32, "{}", job.error);
    let keys = list(&coordinator, &format!("jobs/{}/", job.id)).await;
    for file in [
        "poses/transforms.json",
        "poses/poses_report.json",
        "poses/manifest.json",
        "nerf_pretrain/field.safetensors",
        "render_stylized/style-0/animation.gif",
    ] {
        let key = format!("jobs/{}/{file}", job.id);
        assert!(keys.contains(&key), "{key} missing from {keys:#?}");
    }
    let poses = job.tasks.iter().find(|t| t.stage() == pb::Stage::Poses);
    assert!(poses
        .unwrap()
        .outputs
        .iter()
        .all(|o| !o.key.contains("/ckpt/")));
    coordinator.shutdown().await.unwrap();
}
