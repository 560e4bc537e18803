//! The client against an embedded coordinator on 127.0.0.1 with a real SQLite file: uploads of
//! a scene folder and style images, submit (with idempotency), get, list with paging, watch,
//! wait, cancel, artifacts and atomic downloads of objects a fake worker stored, renders, and
//! the error messages (unreachable, bad token, wrong role, unknown job, invalid fields).

use futures::StreamExt;
use std::path::Path;
use std::time::Duration;
use stylenerf_client::{
    pb, Client, ClientError, Input, JobSpec, ListFilter, RenderSpec, WatchOptions,
};
use stylenerf_server::CoordinatorHandle;
use stylenerf_testkit::{
    config, fake_output, png, FakeWorker, Source, ALICE, BOB, SCENE_TRANSFORMS, WORKER,
};

async fn start(dir: &Path) -> CoordinatorHandle {
    stylenerf_testkit::start(config(dir)).await
}

fn write_png(path: &Path, size: u32) {
    std::fs::write(path, png(size, size)).unwrap();
}

/// A NeRF-synthetic scene folder: `transforms_train.json` and two images.
fn write_scene(dir: &Path) {
    std::fs::create_dir_all(dir.join("train")).unwrap();
    std::fs::write(dir.join("transforms_train.json"), SCENE_TRANSFORMS).unwrap();
    write_png(&dir.join("train/r_0.png"), 4);
    write_png(&dir.join("train/r_1.png"), 4);
}

/// A scene folder and two style images under `root`, and a spec using them.
fn job_spec(root: &Path) -> JobSpec {
    let scene = root.join("lego");
    write_scene(&scene);
    write_png(&root.join("starry.png"), 8);
    write_png(&root.join("wave.png"), 12);
    let mut spec = JobSpec::new(
        Input::path(&scene),
        [
            Input::path(root.join("starry.png")),
            Input::path(root.join("wave.png")),
        ],
    );
    spec.name = "lego".into();
    spec.preset = Some("tiny".into());
    spec.overrides
        .insert("nerf_pretrain.steps".into(), 25.into());
    spec
}

#[tokio::test]
async fn submit_get_list_watch_and_cancel() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = start(&dir.path().join("coord")).await;
    let client = Client::connect(&coordinator.endpoint(), Some(ALICE))
        .await
        .unwrap();

    let receipt = client.upload_dataset(dir.path().join("missing")).await;
    assert!(
        matches!(receipt, Err(ClientError::Io { .. })),
        "{receipt:?}"
    );

    let spec = job_spec(dir.path());
    let mut keyed = spec.clone();
    keyed.idempotency_key = Some("order-1".into());
    let first = client.submit(&keyed).await.unwrap();
    assert!(first.created);
    assert_eq!(first.uploads.len(), 3);
    assert!(
        first.uploads[0].summary.contains("blender")
            && first.uploads[0].summary.contains("2 frames"),
        "{}",
        first.uploads[0].summary
    );
    let job = first.job;
    assert_eq!(job.preset, "tiny");
    assert_eq!(job.tasks.len(), Source::Dataset.stages().len());
    assert_eq!(job.style_keys.len(), 2);
    let overrides: serde_json::Value = serde_json::from_str(&job.config_overrides_json).unwrap();
    assert_eq!(overrides, serde_json::json!({"nerf_pretrain.steps": 25}));
    let again = client.submit(&keyed).await.unwrap();
    assert!(!again.created);
    assert_eq!(again.job.id, job.id);

    // A second job reusing the uploaded inputs by id.
    let mut reuse = spec.clone();
    reuse.dataset = Some(Input::UploadId(first.uploads[0].upload_id.clone()));
    reuse.styles = vec![Input::UploadId(first.uploads[1].upload_id.clone())];
    let second = client.submit(&reuse).await.unwrap();
    assert!(second.uploads.is_empty());

    assert_eq!(client.get(&job.id).await.unwrap().id, job.id);
    let page = client
        .list(&ListFilter {
            page_size: 1,
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(page.jobs.len(), 1);
    assert_eq!(page.jobs[0].id, second.job.id, "newest first");
    let token = page.next_page_token.expect("a second page");
    let rest = client
        .list(&ListFilter {
            page_token: Some(token),
            include_tasks: true,
            ..Default::default()
        })
        .await
        .unwrap();
    assert_eq!(rest.jobs.len(), 1);
    assert_eq!(rest.jobs[0].tasks.len(), Source::Dataset.stages().len());
    assert!(rest.next_page_token.is_none());
    let queued = client
        .list_all(
            &ListFilter {
                states: vec![pb::JobState::Queued],
                ..Default::default()
            },
            10,
        )
        .await
        .unwrap();
    assert_eq!(queued.len(), 2);
    let bob = Client::connect(&coordinator.endpoint(), Some(BOB))
        .await
        .unwrap();
    assert!(bob
        .list(&ListFilter::default())
        .await
        .unwrap()
        .jobs
        .is_empty());

    // Watch replays the history, then follows live events until the job is cancelled.
    let mut events = client
        .watch(&job.id, WatchOptions::default())
        .await
        .unwrap();
    let created = events.next().await.unwrap().unwrap();
    assert_eq!(created.kind, pb::EventKind::JobCreated as i32);
    let cancelled = client.cancel(&job.id, "changed my mind").await.unwrap();
    assert_eq!(cancelled.state, pb::JobState::Cancelled as i32);
    let mut rest = Vec::new();
    while let Some(event) = tokio::time::timeout(Duration::from_secs(10), events.next())
        .await
        .expect("the stream ends")
    {
        rest.push(event.unwrap());
    }
    let last = rest.last().expect("events after the cancel");
    assert_eq!(last.kind, pb::EventKind::JobState as i32);
    assert_eq!(last.job_state, pb::JobState::Cancelled as i32);
    assert!(rest.windows(2).all(|w| w[0].seq < w[1].seq));
    assert!(rest
        .iter()
        .any(|e| e.task_state == pb::TaskState::Cancelled as i32));
    let done = client.wait(&job.id).await.unwrap();
    assert_eq!(done.state, pb::JobState::Cancelled as i32);
    assert_eq!(done.error, "cancelled by alice: changed my mind");
    // Resuming after the last event of a terminal job ends at once.
    let mut resumed = client
        .watch(
            &job.id,
            WatchOptions {
                after_seq: last.seq,
                skip_progress: false,
            },
        )
        .await
        .unwrap();
    assert!(resumed.next().await.is_none());

    coordinator.shutdown().await.unwrap();
}

#[tokio::test]
async fn artifacts_download_and_render() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = start(&dir.path().join("coord")).await;
    let client = Client::connect(&coordinator.endpoint(), Some(ALICE))
        .await
        .unwrap();
    let job = client.submit(&job_spec(dir.path())).await.unwrap().job;
    let mut events = client
        .watch(&job.id, WatchOptions::default())
        .await
        .unwrap();

    let mut worker = FakeWorker::register(&coordinator, "cpu", 0).await;
    let task = worker.run_one().await;
    let data = fake_output(&task);
    assert_eq!(
        task.output_prefix,
        format!("jobs/{}/nerf_pretrain/", job.id)
    );

    // The watch saw the lease, the progress report and the completion.
    let mut seen = Vec::new();
    while !seen.iter().any(|e: &pb::Event| {
        e.kind == pb::EventKind::TaskState as i32 && e.task_state == pb::TaskState::Succeeded as i32
    }) {
        seen.push(events.next().await.unwrap().unwrap());
    }
    let progress = seen
        .iter()
        .find(|e| e.kind == pb::EventKind::TaskProgress as i32)
        .and_then(|e| e.progress.clone())
        .expect("a progress event");
    assert_eq!((progress.step, progress.total), (5, 10));
    assert_eq!(progress.metrics["psnr"], 25.0);

    let artifacts = client.artifacts(&job.id, "nerf_pretrain/").await.unwrap();
    assert_eq!(artifacts.len(), 1);
    assert_eq!(artifacts[0].size, data.len() as u64);
    assert_eq!(artifacts[0].sha256.len(), 64);
    let all = client.artifacts(&job.id, "").await.unwrap();
    assert!(all.iter().any(|a| a.key.ends_with("inputs/scene.tar")));

    let out = dir.path().join("out");
    let files = client.download(&job.id, &out).await.unwrap();
    assert_eq!(files.len(), 1, "inputs are left out by default: {files:?}");
    assert!(!files[0].skipped);
    let path = out.join("nerf_pretrain/result.bin");
    assert_eq!(files[0].path, path);
    assert_eq!(std::fs::read(&path).unwrap(), data);
    let again = client.download(&job.id, &out).await.unwrap();
    assert!(
        again[0].skipped,
        "an up-to-date file is not downloaded again"
    );
    let leftovers: Vec<_> = std::fs::read_dir(out.join("nerf_pretrain"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(leftovers.len(), 1, "no temporary files left: {leftovers:?}");
    let with_inputs = client
        .download_with(
            &job.id,
            &out,
            &stylenerf_client::DownloadOptions {
                include_inputs: true,
                ..Default::default()
            },
        )
        .await
        .unwrap();
    assert_eq!(with_inputs.len(), 4);
    assert!(out.join("inputs/styles/1.png").is_file());

    // Render before training finished is refused with a clear reason.
    let early = client.render(&job.id, &RenderSpec::default()).await;
    assert!(
        matches!(early, Err(ClientError::FailedPrecondition { .. })),
        "{early:?}"
    );
    // The stages after the first, which ran above.
    for _ in 1..Source::Dataset.stages().len() {
        worker.run_one().await;
    }
    let finished = client.wait(&job.id).await.unwrap();
    assert_eq!(finished.state, pb::JobState::Succeeded as i32);

    let spec = RenderSpec {
        camera_path: Some(pb::CameraPath {
            kind: "orbit".into(),
            num_frames: 12,
            fps: 24.0,
            params_json: String::new(),
        }),
        style_blend: vec![
            pb::StyleWeight {
                style_index: 0,
                weight: 0.3,
            },
            pb::StyleWeight {
                style_index: 1,
                weight: 0.7,
            },
        ],
        overrides: Default::default(),
    };
    let render = client.render(&job.id, &spec).await.unwrap();
    assert_eq!(render.stage, pb::Stage::RenderStylized as i32);
    let config: serde_json::Value = serde_json::from_str(&render.config_json).unwrap();
    assert_eq!(config["camera_path"]["num_frames"], 12);
    // A reopened job: the watch goes past the earlier terminal event until the render ends.
    let waiter = tokio::spawn({
        let client = client.clone();
        let id = job.id.clone();
        async move { client.wait(&id).await }
    });
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(!waiter.is_finished(), "the job is running again");
    let task = worker.run_one().await;
    assert_eq!(task.task_id, render.id);
    let done = waiter.await.unwrap().unwrap();
    assert_eq!(done.state, pb::JobState::Succeeded as i32);
    let renders = client.artifacts(&job.id, "render_stylized/").await.unwrap();
    assert_eq!(renders.len(), 2);

    coordinator.shutdown().await.unwrap();
}

#[tokio::test]
async fn errors_are_clear() {
    // Nothing listens on a port that was just released.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let err = Client::connect(&format!("127.0.0.1:{port}"), Some(ALICE))
        .await
        .unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, ClientError::Unreachable { .. }), "{err:?}");
    assert!(
        text.starts_with(&format!(
            "cannot reach coordinator at http://127.0.0.1:{port}: "
        )),
        "{text}"
    );
    assert!(text.to_lowercase().contains("refused"), "{text}");

    let dir = tempfile::tempdir().unwrap();
    let coordinator = start(&dir.path().join("coord")).await;
    let endpoint = coordinator.endpoint();

    let stranger = Client::connect(&endpoint, Some("not-a-known-token-000"))
        .await
        .unwrap();
    let err = stranger.get("j-1").await.unwrap_err();
    assert!(
        matches!(err, ClientError::Unauthenticated { .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("rejected the token"), "{err}");
    let anonymous = Client::connect(&endpoint, None).await.unwrap();
    assert!(matches!(
        anonymous.list(&ListFilter::default()).await,
        Err(ClientError::Unauthenticated { .. })
    ));
    let worker = Client::connect(&endpoint, Some(WORKER)).await.unwrap();
    let err = worker.get("j-1").await.unwrap_err();
    assert!(
        matches!(err, ClientError::PermissionDenied { .. }),
        "{err:?}"
    );

    let client = Client::connect(&endpoint, Some(ALICE)).await.unwrap();
    for err in [
        client.get("j-nope").await.unwrap_err(),
        client.cancel("j-nope", "").await.unwrap_err(),
        client.artifacts("j-nope", "").await.err().unwrap(),
        client
            .watch("j-nope", WatchOptions::default())
            .await
            .err()
            .unwrap(),
    ] {
        assert!(matches!(err, ClientError::NotFound { .. }), "{err:?}");
        assert!(err.to_string().contains("j-nope"), "{err}");
    }

    // Field-level details of INVALID_ARGUMENT.
    let mut spec = job_spec(dir.path());
    spec.preset = Some("huge".into());
    let err = client.submit(&spec).await.unwrap_err();
    assert_eq!(err.violations().len(), 1, "{err:?}");
    assert_eq!(err.violations()[0].field, "preset");
    let text = err.to_string();
    assert!(
        text.starts_with("invalid request: preset: unknown preset \"huge\""),
        "{text}"
    );
    spec.preset = None;
    spec.style_blend = vec![pb::StyleWeight {
        style_index: 5,
        weight: 1.0,
    }];
    let err = client.submit(&spec).await.unwrap_err();
    assert_eq!(
        err.violations()[0].field,
        "style_blend[0].style_index",
        "{err}"
    );
    spec.style_blend.clear();
    spec.styles = vec![Input::UploadId("u-missing".into())];
    let err = client.submit(&spec).await.unwrap_err();
    assert_eq!(err.violations()[0].field, "styles[0].upload_id", "{err}");

    // A scene whose image is missing is refused by the coordinator's validation...
    let broken = dir.path().join("broken");
    write_scene(&broken);
    std::fs::remove_file(broken.join("train/r_1.png")).unwrap();
    let err = client.upload_dataset(&broken).await.unwrap_err();
    assert_eq!(err.violations()[0].field, "data", "{err}");
    assert!(err.to_string().contains("r_1"), "{err}");
    // ... a folder without a scene file before anything is sent, and so is a non-image style.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    std::fs::write(empty.join("notes.txt"), b"hello").unwrap();
    let err = client.upload_dataset(&empty).await.unwrap_err();
    assert!(matches!(err, ClientError::InvalidInput(_)), "{err:?}");
    let err = client
        .upload_style(empty.join("notes.txt"))
        .await
        .unwrap_err();
    assert_eq!(err.violations()[0].field, "data", "{err}");

    coordinator.shutdown().await.unwrap();
}

/// A TCP proxy to `upstream` that cuts each of its first `cuts` connections after `after`
/// bytes from the client; counts connections and the bytes it forwarded to `upstream`.
struct CuttingProxy {
    addr: std::net::SocketAddr,
    connections: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    forwarded: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl CuttingProxy {
    async fn start(upstream: std::net::SocketAddr, cuts: usize, after: u64) -> CuttingProxy {
        use std::sync::atomic::Ordering::SeqCst;
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let connections = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let forwarded = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
        let (count, total) = (connections.clone(), forwarded.clone());
        tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                let n = count.fetch_add(1, SeqCst);
                let limit = if n < cuts { after } else { u64::MAX };
                let total = total.clone();
                tokio::spawn(async move {
                    let server = tokio::net::TcpStream::connect(upstream).await.unwrap();
                    let (mut from_client, mut to_client) = client.into_split();
                    let (mut from_server, mut to_server) = server.into_split();
                    let back = tokio::spawn(async move {
                        let _ = tokio::io::copy(&mut from_server, &mut to_client).await;
                    });
                    let mut sent = 0u64;
                    let mut buf = vec![0u8; 16 << 10];
                    while sent < limit {
                        let want = buf.len().min((limit - sent) as usize);
                        match from_client.read(&mut buf[..want]).await {
                            Ok(0) | Err(_) => break,
                            Ok(n) => {
                                if to_server.write_all(&buf[..n]).await.is_err() {
                                    break;
                                }
                                sent += n as u64;
                                total.fetch_add(n as u64, SeqCst);
                            }
                        }
                    }
                    // The link breaks: both directions go down.
                    back.abort();
                });
            }
        });
        CuttingProxy {
            addr,
            connections,
            forwarded,
        }
    }
}

#[tokio::test]
async fn an_upload_resumes_where_a_broken_link_left_it() {
    use std::sync::atomic::Ordering::SeqCst;
    let dir = tempfile::tempdir().unwrap();
    let coordinator = start(&dir.path().join("coord")).await;
    // A scene with a 4 MiB member of incompressible bytes; the link breaks three times, each
    // after 1.5 MiB: one whole 1 MiB data message gets through each time (a message cut
    // in half is lost: the coordinator commits whole messages).
    let scene = dir.path().join("lego");
    write_scene(&scene);
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let noise: Vec<u8> = (0..4 << 20)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state as u8
        })
        .collect();
    std::fs::write(scene.join("notes.bin"), &noise).unwrap();
    let cut = 3 << 19;
    let proxy = CuttingProxy::start(coordinator.local_addr(), 3, cut).await;
    let client = Client::connect(&format!("http://{}", proxy.addr), Some(ALICE))
        .await
        .unwrap();
    let receipt = client
        .upload_dataset(&scene)
        .await
        .expect("uploads through the cuts");
    assert!(receipt.summary.contains("2 frames"), "{}", receipt.summary);
    assert!(receipt.size > noise.len() as u64);
    assert!(
        proxy.connections.load(SeqCst) >= 4,
        "the link was cut three times"
    );
    // Each attempt went on from what the coordinator had committed: starting over would have
    // sent the three cut-off prefixes again on top of the whole archive.
    let forwarded = proxy.forwarded.load(SeqCst);
    assert!(
        forwarded < receipt.size + 2 * cut,
        "{forwarded} bytes forwarded for {} bytes of content",
        receipt.size
    );
    // The upload is whole: a job can use it.
    let mut spec = job_spec(dir.path());
    spec.dataset = Some(Input::UploadId(receipt.upload_id));
    client.submit(&spec).await.expect("a job from the upload");
}

#[tokio::test]
async fn a_folder_of_photos_or_a_video_is_submitted_as_a_job_that_starts_with_poses() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = start(&dir.path().join("coord")).await;
    let client = Client::connect(&coordinator.endpoint(), Some(ALICE))
        .await
        .unwrap();
    let photos = dir.path().join("holiday");
    std::fs::create_dir_all(photos.join("raw")).unwrap();
    for i in 0..4 {
        write_png(&photos.join(format!("raw/IMG_{i}.png")), 20);
    }
    let mut spec = job_spec(dir.path());
    let dataset = spec.dataset.take();
    spec.photos = Some(Input::path(&photos));
    let submitted = client.submit(&spec).await.unwrap();
    assert_eq!(submitted.uploads[0].summary, "4 photos in raw/");
    let job = submitted.job;
    assert_eq!(job.tasks.len(), Source::Photos.stages().len());
    assert_eq!(job.tasks[0].stage(), pb::Stage::Poses);

    // A video goes as it is.
    let video = dir.path().join("walk.mov");
    std::fs::write(
        &video,
        [&[0, 0, 0, 0x14][..], b"ftypqt  ", &[0; 64]].concat(),
    )
    .unwrap();
    let receipt = client.upload_photos(&video).await.unwrap();
    assert_eq!(receipt.summary, "mov video");

    // Too few photos fail before anything is sent; both inputs at once are refused.
    let few = dir.path().join("few");
    std::fs::create_dir_all(&few).unwrap();
    write_png(&few.join("a.png"), 20);
    let err = client.upload_photos(&few).await.unwrap_err().to_string();
    assert!(
        err.contains("1 PNG/JPEG photos") && err.contains("at least 3"),
        "{err}"
    );
    spec.dataset = dataset;
    let err = client.submit(&spec).await.unwrap_err().to_string();
    assert!(err.contains("not both"), "{err}");
}
