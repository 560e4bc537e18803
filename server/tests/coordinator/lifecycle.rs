//! A job through every stage with a fake worker, watched with replay; artifacts listed and
//! downloaded; a further render; idempotent creation; capability matching; health.

use futures::StreamExt;
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;

const STAGES: [pb::Stage; 5] = [
    pb::Stage::NerfPretrain,
    pb::Stage::RenderViews,
    pb::Stage::DecoderPretrain,
    pb::Stage::MutualLearning,
    pb::Stage::RenderStylized,
];

/// The stages whose outputs a stage reads (the catalogue's DAG, written out).
fn reads(stage: pb::Stage) -> Vec<pb::Stage> {
    match stage {
        pb::Stage::NerfPretrain => vec![],
        pb::Stage::RenderViews => vec![pb::Stage::NerfPretrain],
        pb::Stage::DecoderPretrain => vec![pb::Stage::RenderViews],
        pb::Stage::MutualLearning => STAGES[..3].to_vec(),
        _ => STAGES[..4].to_vec(),
    }
}

#[tokio::test]
async fn job_runs_through_all_stages_and_renders_again() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut client).await;
    assert_eq!(job.state(), pb::JobState::Queued);
    assert_eq!(job.tasks.len(), STAGES.len());
    assert_eq!(job.style_keys.len(), 2);
    assert_eq!(job.dataset_key, format!("jobs/{}/inputs/scene.tar", job.id));

    let mut live = watch(&mut client, &job.id, 0, false).await;

    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let mut outputs = Vec::new();
    for (i, stage) in STAGES.iter().enumerate() {
        let task = worker.run_one().await;
        assert_eq!(task.stage(), *stage, "stage {i} in DAG order");
        assert_eq!(task.attempt, 1);
        let handed: Vec<pb::Stage> = task.inputs.iter().map(|i| i.stage()).collect();
        assert_eq!(
            handed,
            reads(*stage),
            "the outputs of the stages {stage:?} reads"
        );
        assert_eq!(task.style_keys.len(), 2);
        assert!(task.object_store_url.starts_with("file://"));
        let config: serde_json::Value = serde_json::from_str(&task.config_json).unwrap();
        assert_eq!(config["preset"], "tiny");
        outputs.push(task.output_prefix.clone());
    }

    let done = get_job(&mut client, &job.id).await;
    assert_eq!(done.state(), pb::JobState::Succeeded);
    // Each task depends on the tasks of the stages it reads.
    for task in &done.tasks {
        let deps: Vec<pb::Stage> = task
            .depends_on
            .iter()
            .map(|id| done.tasks.iter().find(|t| t.id == *id).unwrap().stage())
            .collect();
        assert_eq!(deps, reads(task.stage()), "{:?}", task.stage());
    }
    assert!(done
        .tasks
        .iter()
        .all(|t| t.state() == pb::TaskState::Succeeded));
    assert_eq!(
        done.tasks[0].progress.as_ref().unwrap().metrics["psnr"],
        31.0
    );

    // The watch stream saw the whole history and ended with the job's success.
    let events: Vec<pb::Event> = live.by_ref().map(|e| e.unwrap()).collect().await;
    assert_eq!(events[0].kind(), pb::EventKind::JobCreated);
    assert!(events.windows(2).all(|w| w[0].seq < w[1].seq));
    assert!(
        events
            .iter()
            .any(|e| e.kind() == pb::EventKind::TaskProgress
                && e.progress.as_ref().unwrap().step == 5)
    );
    let last = events.last().unwrap();
    assert_eq!(last.kind(), pb::EventKind::JobState);
    assert_eq!(last.job_state(), pb::JobState::Succeeded);

    // Replay from the middle returns exactly the later events.
    let middle = events[events.len() / 2].seq;
    let replayed: Vec<pb::Event> = watch(&mut client, &job.id, middle, true)
        .await
        .map(|e| e.unwrap())
        .collect()
        .await;
    let expected: Vec<u64> = events
        .iter()
        .filter(|e| e.seq > middle && e.kind() != pb::EventKind::TaskProgress)
        .map(|e| e.seq)
        .collect();
    assert_eq!(replayed.iter().map(|e| e.seq).collect::<Vec<_>>(), expected);

    // Artifacts: inputs and every stage's output, downloadable.
    let listed = client
        .list_artifacts(pb::ListArtifactsRequest {
            job_id: job.id.clone(),
            prefix: String::new(),
        })
        .await
        .unwrap()
        .into_inner()
        .artifacts;
    for prefix in &outputs {
        let key = format!("{prefix}result.bin");
        let artifact = listed.iter().find(|a| a.key == key).expect("output listed");
        assert_eq!(artifact.sha256.len(), 64);
    }
    assert!(listed.iter().any(|a| a.key == done.dataset_key));
    let key = format!("{}result.bin", outputs[4]);
    let chunks: Vec<pb::ObjectChunk> = client
        .download_artifact(pb::DownloadArtifactRequest {
            job_id: job.id.clone(),
            key: key.clone(),
            offset: 0,
        })
        .await
        .unwrap()
        .into_inner()
        .map(|c| c.unwrap())
        .collect()
        .await;
    let data: Vec<u8> = chunks.iter().flat_map(|c| c.data.clone()).collect();
    assert_eq!(chunks[0].total_size, data.len() as u64);
    assert!(String::from_utf8(data).unwrap().starts_with("output of"));
    let outside = client
        .download_artifact(pb::DownloadArtifactRequest {
            job_id: job.id.clone(),
            key: "uploads/x".into(),
            offset: 0,
        })
        .await
        .unwrap_err();
    assert_eq!(outside.code(), tonic::Code::InvalidArgument);

    // A further render with a style blend reopens the job until it is done.
    let render = client
        .render_job(pb::RenderJobRequest {
            job_id: job.id.clone(),
            camera_path: Some(pb::CameraPath {
                kind: "orbit".into(),
                num_frames: 12,
                fps: 24.0,
                params_json: r#"{"radius": 4}"#.into(),
            }),
            style_blend: vec![
                pb::StyleWeight {
                    style_index: 0,
                    weight: 1.0,
                },
                pb::StyleWeight {
                    style_index: 1,
                    weight: 3.0,
                },
            ],
            config_overrides_json: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(render.state(), pb::TaskState::Ready);
    assert_eq!(
        get_job(&mut client, &job.id).await.state(),
        pb::JobState::Running
    );
    let task = worker.run_one().await;
    assert_eq!(task.task_id, render.id);
    assert_eq!(task.inputs.len(), 4, "the four training stages");
    let config: serde_json::Value = serde_json::from_str(&task.config_json).unwrap();
    assert_eq!(config["style_blend"][1]["weight"], 0.75);
    assert_eq!(config["camera_path"]["num_frames"], 12);
    assert_eq!(
        get_job(&mut client, &job.id).await.state(),
        pb::JobState::Succeeded
    );

    let bad_blend = client
        .render_job(pb::RenderJobRequest {
            job_id: job.id.clone(),
            style_blend: vec![pb::StyleWeight {
                style_index: 7,
                weight: 1.0,
            }],
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&bad_blend), ["style_blend[0].style_index"]);
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn idempotency_key_returns_the_same_job() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let mut request = job_request(&mut client).await;
    request.idempotency_key = "submit-42".into();
    let first = client
        .create_job(request.clone())
        .await
        .unwrap()
        .into_inner();
    let second = client
        .create_job(request.clone())
        .await
        .unwrap()
        .into_inner();
    assert!(first.created);
    assert!(!second.created);
    assert_eq!(first.job.unwrap().id, second.job.unwrap().id);
    request.idempotency_key = "submit-43".into();
    assert!(
        client
            .create_job(request)
            .await
            .unwrap()
            .into_inner()
            .created
    );
    let listed = client
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert_eq!(listed.jobs.len(), 2);
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn tasks_go_only_to_capable_workers() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let mut request = job_request(&mut client).await;
    request.requirements = Some(pb::Requirements {
        require_cuda: true,
        labels: vec![],
        memory_bytes: 8 << 30,
    });
    let created = client.create_job(request).await.unwrap().into_inner();
    // Nobody can run it yet: the submitter is told so.
    let mut events = watch(&mut client, &created.job.unwrap().id, 0, true).await;
    let first = events.message().await.unwrap().unwrap();
    assert!(first.message.contains("no CUDA worker"), "{first:?}");
    let mut cpu = FakeWorker::register(&server, "cpu", 0).await;
    assert!(
        cpu.lease(100).await.is_none(),
        "cpu worker gets no CUDA task"
    );
    let mut small = FakeWorker::register(&server, "cuda:0", 4 << 30).await;
    assert!(small.lease(100).await.is_none(), "too little memory");
    let mut big = FakeWorker::register(&server, "cuda:1", 16 << 30).await;
    let task = big.lease(100).await.expect("capable worker gets it");
    assert_eq!(task.memory_bytes, 8 << 30);

    let mut health = tonic_health::pb::health_client::HealthClient::new(channel(&server).await);
    let status = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "stylenerf.v1.JobService".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        status.status(),
        tonic_health::pb::health_check_response::ServingStatus::Serving
    );
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn a_job_that_failed_in_its_final_render_renders_again() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let mut request = job_request(&mut client).await;
    request.camera_path = Some(pb::CameraPath {
        kind: "zoom".into(),
        ..Default::default()
    });
    let unknown = client.create_job(request.clone()).await.unwrap_err();
    assert_eq!(bad_fields(&unknown), ["camera_path.kind"]);
    request.camera_path = None;
    let job = create(&mut client, request).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    // Every stage before the last, render_stylized.
    for _ in 1..STAGES.len() {
        worker.run_one().await;
    }
    let render = worker.lease(5000).await.expect("render_stylized");
    worker
        .workers
        .fail_task(pb::FailTaskRequest {
            worker_id: worker.id.clone(),
            task_id: render.task_id,
            fencing_token: render.fencing_token,
            reason: "out of disk".into(),
            retryable: false,
        })
        .await
        .unwrap();
    assert_eq!(
        get_job(&mut client, &job.id).await.state(),
        pb::JobState::Failed
    );

    client
        .render_job(pb::RenderJobRequest {
            job_id: job.id.clone(),
            ..Default::default()
        })
        .await
        .expect("the trained job renders again");
    let again = get_job(&mut client, &job.id).await;
    assert_eq!(again.state(), pb::JobState::Running);
    assert!(again.error.is_empty(), "{}", again.error);
    worker.run_one().await;
    assert_eq!(
        get_job(&mut client, &job.id).await.state(),
        pb::JobState::Succeeded
    );
}

#[tokio::test]
async fn a_worker_advertising_an_unknown_device_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut workers = worker_client(&server, Some(WORKER)).await;
    let register = |device: &str| pb::RegisterWorkerRequest {
        name: "w".into(),
        capabilities: Some(pb::Capabilities {
            device: device.into(),
            memory_bytes: 0,
            labels: Vec::new(),
            max_tasks: 1,
            tools: Vec::new(),
        }),
        worker_id: String::new(),
    };
    for bad in ["gpu", "cuda:x", "cuda0"] {
        let err = workers.register_worker(register(bad)).await.unwrap_err();
        assert_eq!(err.code(), tonic::Code::InvalidArgument, "{bad}");
        let detail = format!("{err:?}");
        assert!(detail.contains("capabilities.device"), "{bad}: {detail}");
    }
    for good in ["cpu", "cuda", "cuda:1"] {
        workers.register_worker(register(good)).await.unwrap();
    }
}

/// Creates a job from an upload of plain photos or a video (`filename`, `data`).
async fn job_from_photos(
    client: &mut pb::job_service_client::JobServiceClient<Authed>,
    filename: &str,
    data: &[u8],
) -> pb::Job {
    let receipt = upload(client, pb::UploadKind::Photos, filename, data)
        .await
        .expect("photos accepted");
    let mut request = job_request(client).await;
    request.dataset = Some(uploaded(&receipt));
    create(client, request).await
}

#[tokio::test]
async fn a_job_from_photos_starts_with_poses_on_a_worker_that_has_colmap() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let photo = png(32, 24);
    let photos = tar_of(&[
        ("trip/a.png", &photo),
        ("trip/b.png", &photo),
        ("trip/c.png", &photo),
    ]);
    let job = job_from_photos(&mut client, "trip.tar", &photos).await;
    assert_eq!(
        job.dataset_key,
        format!("jobs/{}/inputs/photos.tar", job.id)
    );
    assert_eq!(job.tasks.len(), Source::Photos.stages().len());
    let first = watch(&mut client, &job.id, 0, true)
        .await
        .next()
        .await
        .unwrap()
        .unwrap();
    assert!(
        first.message.contains("needs a worker with colmap"),
        "{}",
        first.message
    );

    // Only a worker that advertises COLMAP is handed the poses task.
    let mut plain = FakeWorker::register(&server, "cpu", 0).await;
    assert!(plain.lease(300).await.is_none());
    let mut equipped = FakeWorker::register_with(&server, WORKER, "cpu", 0, &["colmap"]).await;
    let poses = equipped.run_one().await;
    assert_eq!(poses.stage(), pb::Stage::Poses);
    assert!(poses.inputs.is_empty());
    assert_eq!(poses.dataset_key, job.dataset_key);
    // Then nerf_pretrain, on the poses stage's output, on any worker.
    let nerf = plain.lease(2000).await.expect("nerf_pretrain is ready");
    assert_eq!(nerf.stage(), pb::Stage::NerfPretrain);
    let handed: Vec<pb::Stage> = nerf.inputs.iter().map(|i| i.stage()).collect();
    assert_eq!(handed, [pb::Stage::Poses]);
    assert_eq!(
        get_job(&mut client, &job.id).await.state(),
        pb::JobState::Running
    );

    // A video also needs ffmpeg.
    let mp4 = [&[0, 0, 0, 0x20][..], b"ftypisom", &[0; 200]].concat();
    let video = job_from_photos(&mut client, "walk.mp4", &mp4).await;
    assert_eq!(
        video.dataset_key,
        format!("jobs/{}/inputs/video.mp4", video.id)
    );
    assert!(equipped.lease(300).await.is_none());
    let mut both =
        FakeWorker::register_with(&server, WORKER, "cpu", 0, &["colmap", "ffmpeg"]).await;
    let task = both.lease(2000).await.expect("the video's poses task");
    assert_eq!(
        (task.stage(), task.job_id.as_str()),
        (pb::Stage::Poses, video.id.as_str())
    );

    // Photos are refused at upload, naming why, when a worker would refuse them.
    let err = upload(
        &mut client,
        pb::UploadKind::Photos,
        "two.tar",
        &tar_of(&[("a.png", &photo), ("b.png", &photo)]),
    )
    .await
    .unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().contains("at least 3"), "{}", err.message());
}
