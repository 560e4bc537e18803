//! Resumable uploads: a stream cut off mid-way keeps what arrived, the session survives a
//! coordinator restart, appends must continue at the committed size, the finish checks the
//! SHA-256 and is repeatable, sessions are private, bounded per owner and swept when idle.

use futures::StreamExt;
use std::path::Path;
use std::time::{Duration, Instant};
use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;
use tonic::Code;

fn resume(session_id: &str, offset: u64) -> pb::UploadSessionChunk {
    pb::UploadSessionChunk {
        part: Some(pb::upload_session_chunk::Part::Resume(pb::UploadResume {
            session_id: session_id.into(),
            offset,
        })),
    }
}

fn data(bytes: &[u8]) -> pb::UploadSessionChunk {
    pb::UploadSessionChunk {
        part: Some(pb::upload_session_chunk::Part::Data(bytes.to_vec())),
    }
}

async fn start_session(
    client: &mut JobServiceClient,
    kind: pb::UploadKind,
    total_size: u64,
) -> Result<pb::UploadSession, tonic::Status> {
    client
        .start_upload(pb::StartUploadRequest {
            kind: kind as i32,
            filename: "input.bin".into(),
            total_size,
        })
        .await
        .map(|r| r.into_inner())
}

async fn append(
    client: &mut JobServiceClient,
    session_id: &str,
    offset: u64,
    bytes: &[u8],
) -> Result<pb::UploadSession, tonic::Status> {
    let messages = vec![resume(session_id, offset), data(bytes)];
    client
        .append_upload(tokio_stream::iter(messages))
        .await
        .map(|r| r.into_inner())
}

async fn session(
    client: &mut JobServiceClient,
    session_id: &str,
) -> Result<pb::UploadSession, tonic::Status> {
    client
        .get_upload_session(pb::GetUploadSessionRequest {
            session_id: session_id.into(),
        })
        .await
        .map(|r| r.into_inner())
}

async fn finish(
    client: &mut JobServiceClient,
    session_id: &str,
    content: &[u8],
) -> Result<pb::UploadReceipt, tonic::Status> {
    client
        .finish_upload(pb::FinishUploadRequest {
            session_id: session_id.into(),
            sha256: sha256(content),
            total_size: content.len() as u64,
        })
        .await
        .map(|r| r.into_inner())
}

type JobServiceClient = stylenerf_server::proto::v1::job_service_client::JobServiceClient<Authed>;

/// Files under `upload-sessions/` in the local store.
fn stored_parts(store: &Path) -> usize {
    let dir = store.join("upload-sessions");
    walk(&dir)
}

fn walk(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| {
            if e.path().is_dir() {
                walk(&e.path())
            } else {
                1
            }
        })
        .sum()
}

#[tokio::test]
async fn a_cut_off_upload_resumes_across_a_restart_and_finishes_once() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let store = Path::new(server.storage_url().trim_start_matches("file://")).to_path_buf();
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let content = scene_tar();
    let half = content.len() / 2;
    let opened = start_session(&mut alice, pb::UploadKind::DatasetArchive, 0)
        .await
        .unwrap();
    assert_eq!(opened.committed_size, 0);
    assert!(opened.expires_at_ms > 0);
    let id = opened.session_id.clone();

    // The link breaks after the first half: the call is dropped with the stream still open.
    let hanging = tokio_stream::iter(vec![resume(&id, 0), data(&content[..half])])
        .chain(futures::stream::pending());
    let cut = tokio::time::timeout(Duration::from_millis(500), alice.append_upload(hanging)).await;
    assert!(cut.is_err(), "the append was still waiting for data");
    // What arrived is committed (the coordinator sees the reset and stores it).
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let now = session(&mut alice, &id).await.unwrap();
        if now.committed_size == half as u64 {
            break;
        }
        assert!(Instant::now() < deadline, "never committed: {now:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(stored_parts(&store), 1);

    // The session is the owner's alone.
    let mut bob = jobs_client(&server, Some(BOB)).await;
    for status in [
        session(&mut bob, &id).await.unwrap_err(),
        append(&mut bob, &id, half as u64, b"x").await.unwrap_err(),
        finish(&mut bob, &id, &content).await.unwrap_err(),
    ] {
        assert_eq!(status.code(), Code::NotFound, "{status:?}");
    }

    // A coordinator restarted on the same files still has the committed half.
    server.shutdown().await.unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    assert_eq!(
        session(&mut alice, &id).await.unwrap().committed_size,
        half as u64
    );
    // Appending from anywhere but the committed size is refused, naming it.
    let wrong = append(&mut alice, &id, 0, &content).await.unwrap_err();
    assert_eq!(wrong.code(), Code::FailedPrecondition);
    assert!(
        wrong.message().contains(&format!("append from {half}")),
        "{wrong:?}"
    );
    let done = append(&mut alice, &id, half as u64, &content[half..])
        .await
        .unwrap();
    assert_eq!(done.committed_size, content.len() as u64);

    // The finish checks the content's checksum and size...
    let bad = finish(&mut alice, &id, b"other content").await.unwrap_err();
    assert_eq!(bad.code(), Code::InvalidArgument);
    assert_eq!(bad_fields(&bad), ["total_size"], "{bad:?}");
    let bad = alice
        .finish_upload(pb::FinishUploadRequest {
            session_id: id.clone(),
            sha256: sha256(b"x"),
            total_size: 0,
        })
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&bad), ["sha256"], "{bad:?}");
    // ...validates it like a one-stream upload, and is repeatable.
    let receipt = finish(&mut alice, &id, &content).await.unwrap();
    assert!(receipt.summary.contains("2 frames"), "{receipt:?}");
    assert_eq!(receipt.size, content.len() as u64);
    let again = finish(&mut alice, &id, &content).await.unwrap();
    assert_eq!(again.upload_id, receipt.upload_id);
    assert_eq!(
        session(&mut alice, &id).await.unwrap().upload_id,
        receipt.upload_id
    );
    assert_eq!(stored_parts(&store), 0, "the parts are deleted once joined");
    let finished = append(&mut alice, &id, content.len() as u64, b"x")
        .await
        .unwrap_err();
    assert_eq!(finished.code(), Code::FailedPrecondition);

    // The upload makes a job like any other.
    let mut request = job_request(&mut alice).await;
    request.dataset = Some(pb::InputRef {
        source: Some(pb::input_ref::Source::UploadId(receipt.upload_id)),
    });
    alice.create_job(request).await.expect("a job from it");
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn sessions_are_bounded_checked_and_swept_when_idle() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.limits.max_upload_sessions = 2;
    config.upload_session_ttl = Duration::from_secs(2);
    let server = start(config).await;
    let store = Path::new(server.storage_url().trim_start_matches("file://")).to_path_buf();
    let mut alice = jobs_client(&server, Some(ALICE)).await;

    // A declared size is a bound on the appends.
    let small = start_session(&mut alice, pb::UploadKind::StyleImage, 10)
        .await
        .unwrap();
    let over = append(&mut alice, &small.session_id, 0, &[0u8; 20])
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&over), ["data"], "{over:?}");
    assert_eq!(
        session(&mut alice, &small.session_id)
            .await
            .unwrap()
            .committed_size,
        0,
        "nothing of a refused stream is kept"
    );
    // Content is validated at the finish like a one-stream upload's.
    let junk = b"not an image at all";
    let style = start_session(&mut alice, pb::UploadKind::StyleImage, 0)
        .await
        .unwrap();
    append(&mut alice, &style.session_id, 0, junk)
        .await
        .unwrap();
    let refused = finish(&mut alice, &style.session_id, junk)
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&refused), ["data"], "{refused:?}");

    // Two open sessions per owner here; bob has his own count.
    let third = start_session(&mut alice, pb::UploadKind::StyleImage, 0)
        .await
        .unwrap_err();
    assert_eq!(third.code(), Code::ResourceExhausted, "{third:?}");
    let mut bob = jobs_client(&server, Some(BOB)).await;
    start_session(&mut bob, pb::UploadKind::StyleImage, 0)
        .await
        .expect("bob's first session");
    // Bad starts name the field.
    let bad = alice
        .start_upload(pb::StartUploadRequest {
            kind: 0,
            filename: "../x.png".into(),
            total_size: 0,
        })
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&bad), ["kind"], "{bad:?}");

    // Idle sessions go, with their bytes; the owner may then open new ones.
    assert_eq!(stored_parts(&store), 1);
    let deadline = Instant::now() + Duration::from_secs(15);
    while session(&mut alice, &style.session_id).await.is_ok() {
        assert!(
            Instant::now() < deadline,
            "the idle session was never swept"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let gone = session(&mut alice, &small.session_id).await.unwrap_err();
    assert_eq!(gone.code(), Code::NotFound);
    assert_eq!(stored_parts(&store), 0);
    start_session(&mut alice, pb::UploadKind::StyleImage, 0)
        .await
        .expect("room again");
    server.shutdown().await.unwrap();
}
