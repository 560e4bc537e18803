//! What a hostile but legitimate caller tried: other tenants' objects named by key, another
//! worker's lease and objects, names that carry terminal escapes, odd keys and offsets, and
//! archives as people make them (`tar -C dir .`, gzip, duplicates, deep or absolute paths).

use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;
use tonic::Code;

fn object(key: &str) -> Option<pb::InputRef> {
    Some(pb::InputRef {
        source: Some(pb::input_ref::Source::ObjectKey(key.into())),
    })
}

/// The field violations of a status with their descriptions.
fn violations(status: &tonic::Status) -> Vec<(String, String)> {
    use tonic_types::StatusExt;
    status
        .get_details_bad_request()
        .map(|b| {
            b.field_violations
                .into_iter()
                .map(|v| (v.field, v.description))
                .collect()
        })
        .unwrap_or_default()
}

#[tokio::test]
async fn object_keys_reach_only_the_callers_own_objects() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let mut bob = jobs_client(&server, Some(BOB)).await;
    let job = create_job(&mut alice).await;
    let alice_scene = format!("jobs/{}/inputs/scene.tar", job.id);
    let alice_upload = upload(
        &mut alice,
        pb::UploadKind::DatasetArchive,
        "scene.tar",
        &scene_tar(),
    )
    .await
    .unwrap();
    // An operator stages a scene for bob.
    let staged = dir.path().join("artifacts/staged/bob/scene.tar");
    std::fs::create_dir_all(staged.parent().unwrap()).unwrap();
    std::fs::write(&staged, scene_tar()).unwrap();

    let with_dataset = |client_request: &pb::CreateJobRequest, key: &str| pb::CreateJobRequest {
        dataset: object(key),
        ..client_request.clone()
    };
    let bob_request = job_request(&mut bob).await;
    let stored = dir.path().join("artifacts/uploads");
    let upload_key = std::fs::read_dir(stored.join(&alice_upload.upload_id))
        .unwrap()
        .map(|e| {
            format!(
                "uploads/{}/{}",
                alice_upload.upload_id,
                e.unwrap().file_name().to_string_lossy()
            )
        })
        .next()
        .unwrap();
    let mut answers = Vec::new();
    for key in [
        alice_scene.as_str(),
        upload_key.as_str(),
        "jobs/j-0000/inputs/scene.tar",
        "staged/alice/scene.tar",
    ] {
        let refused = bob
            .create_job(with_dataset(&bob_request, key))
            .await
            .unwrap_err();
        let found = violations(&refused);
        assert_eq!(found.len(), 1, "{key}: {refused:?}");
        assert_eq!(found[0].0, "dataset.object_key");
        // Someone else's object and a missing one get the same answer.
        answers.push(found[0].1.replace(key, "KEY"));
    }
    answers.dedup();
    assert_eq!(answers.len(), 1, "{answers:?}");

    // Bob's staged scene and alice's own job input are fine for their owners.
    bob.create_job(with_dataset(&bob_request, "staged/bob/scene.tar"))
        .await
        .expect("bob's staged scene");
    let alice_request = job_request(&mut alice).await;
    for _ in 0..5 {
        alice
            .create_job(with_dataset(&alice_request, &alice_scene))
            .await
            .expect("alice's own job input (validated after a complete copy)");
    }
}

#[tokio::test]
async fn workers_act_only_on_their_own_leases_and_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut alice).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    let task = worker.lease(5000).await.expect("a task");
    let inputs = format!("jobs/{}/inputs/scene.tar", job.id);

    // Another principal's worker can neither take the id nor act under it.
    let mut intruder = FakeWorker::register_as(&server, OTHER_WORKER, "cpu", 0).await;
    let taken = intruder
        .workers
        .register_worker(pb::RegisterWorkerRequest {
            name: "intruder".into(),
            worker_id: worker.id.clone(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(taken.code(), Code::PermissionDenied, "{taken:?}");
    let mut impostor = FakeWorker {
        id: worker.id.clone(),
        workers: intruder.workers.clone(),
        artifacts: intruder.artifacts.clone(),
    };
    let heartbeat = impostor.heartbeat(&task, 1).await.unwrap_err();
    assert_eq!(heartbeat.code(), Code::PermissionDenied, "{heartbeat:?}");
    let completed = impostor.complete(&task).await.unwrap_err();
    assert_eq!(completed.code(), Code::PermissionDenied, "{completed:?}");
    let failed = impostor
        .workers
        .fail_task(pb::FailTaskRequest {
            worker_id: worker.id.clone(),
            task_id: task.task_id,
            fencing_token: task.fencing_token,
            reason: "nope".into(),
            retryable: false,
        })
        .await
        .unwrap_err();
    assert_eq!(failed.code(), Code::PermissionDenied, "{failed:?}");
    // Its own worker holds no lease on the job: no reading, listing or writing there.
    let read = intruder
        .artifacts
        .get_object(pb::GetObjectRequest {
            key: inputs.clone(),
            offset: 0,
        })
        .await
        .unwrap_err();
    assert_eq!(read.code(), Code::PermissionDenied, "{read:?}");
    for prefix in ["jobs/", &format!("jobs/{}/", job.id)] {
        let listed = intruder
            .artifacts
            .list_objects(pb::ListObjectsRequest {
                prefix: prefix.to_string(),
            })
            .await
            .unwrap_err();
        assert!(
            matches!(
                listed.code(),
                Code::PermissionDenied | Code::InvalidArgument
            ),
            "{prefix}: {listed:?}"
        );
    }
    assert!(
        intruder.lease(100).await.is_none(),
        "the only task is taken"
    );

    // The lease holder reads the job's inputs but writes only under its output prefix.
    let mut stream = worker
        .artifacts
        .get_object(pb::GetObjectRequest {
            key: inputs.clone(),
            offset: 0,
        })
        .await
        .expect("the lease holder reads its inputs")
        .into_inner();
    assert!(stream.message().await.unwrap().is_some());
    let overwrite = put(&mut worker, &inputs, b"replaced").await.unwrap_err();
    assert_eq!(overwrite.code(), Code::PermissionDenied, "{overwrite:?}");
    put(&mut worker, &format!("{}x.bin", task.output_prefix), b"ok")
        .await
        .expect("writes under its prefix");

    // A second worker of the same principal with a stale view learns nothing about the holder.
    let mut sibling = FakeWorker::register(&server, "cpu", 0).await;
    let stale = sibling.heartbeat(&task, 1).await.unwrap_err();
    assert_eq!(stale.code(), Code::FailedPrecondition);
    assert!(!stale.message().contains(&worker.id), "{stale:?}");

    worker.complete(&task).await.expect("the holder completes");
}

async fn put(
    worker: &mut FakeWorker,
    key: &str,
    data: &[u8],
) -> Result<pb::Artifact, tonic::Status> {
    let messages = vec![
        pb::PutObjectChunk {
            part: Some(pb::put_object_chunk::Part::Header(pb::PutObjectHeader {
                key: key.into(),
                size: data.len() as u64,
                sha256: sha256(data),
            })),
        },
        pb::PutObjectChunk {
            part: Some(pb::put_object_chunk::Part::Data(data.to_vec())),
        },
    ];
    worker
        .artifacts
        .put_object(tokio_stream::iter(messages))
        .await
        .map(|r| r.into_inner())
}

#[tokio::test]
async fn odd_keys_offsets_and_names_get_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let mut alice = jobs_client(&server, Some(ALICE)).await;
    let job = create_job(&mut alice).await;
    let mut worker = FakeWorker::register(&server, "cpu", 0).await;
    worker.lease(5000).await.expect("a task");

    let folder = put(&mut worker, "jobs/", b"x").await.unwrap_err();
    assert_eq!(folder.code(), Code::InvalidArgument, "{folder:?}");
    assert!(folder.message().contains("folder"), "{folder:?}");

    let key = format!("jobs/{}/inputs/scene.tar", job.id);
    let size = scene_tar().len() as u64;
    let download = |offset: u64| {
        let mut alice = alice.clone();
        let request = pb::DownloadArtifactRequest {
            job_id: job.id.clone(),
            key: key.clone(),
            offset,
        };
        async move {
            let mut stream = alice.download_artifact(request).await?.into_inner();
            let mut bytes = 0;
            while let Some(chunk) = stream.message().await? {
                bytes += chunk.data.len();
            }
            Ok::<_, tonic::Status>(bytes)
        }
    };
    assert_eq!(download(size - 10).await.unwrap(), 10);
    assert_eq!(
        download(size).await.unwrap(),
        0,
        "resuming a finished download"
    );
    let beyond = download(size + 1).await.unwrap_err();
    assert_eq!(beyond.code(), Code::InvalidArgument, "{beyond:?}");

    let mut request = job_request(&mut alice).await;
    request.name = "report\x1b]0;pwned\x07\r\0".into();
    request.requirements = Some(pb::Requirements {
        labels: vec!["zone\x1b[2J".into()],
        ..Default::default()
    });
    let refused = alice.create_job(request).await.unwrap_err();
    let mut fields = bad_fields(&refused);
    fields.sort();
    assert_eq!(fields, ["name", "requirements.labels[0]"], "{refused:?}");
    let reason = alice
        .cancel_job(pb::CancelJobRequest {
            job_id: job.id.clone(),
            reason: "\x1b[31mred".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&reason), ["reason"]);
}

/// A tar member with its raw name, as `tar -C dir .` writes them (`./`, `./x`).
fn raw_tar(members: &[(&str, Option<&[u8]>)]) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for (name, data) in members {
        let mut header = tar::Header::new_ustar();
        let field = &mut header.as_ustar_mut().unwrap().name;
        field[..name.len()].copy_from_slice(name.as_bytes());
        match data {
            None => {
                header.set_entry_type(tar::EntryType::Directory);
                header.set_size(0);
                header.set_mode(0o755);
                header.set_cksum();
                builder.append(&header, std::io::empty()).unwrap();
            }
            Some(data) => {
                header.set_entry_type(tar::EntryType::Regular);
                header.set_size(data.len() as u64);
                header.set_mode(0o644);
                header.set_cksum();
                builder.append(&header, *data).unwrap();
            }
        }
    }
    builder.into_inner().unwrap()
}

#[tokio::test]
async fn archives_as_people_make_them() {
    let dir = tempfile::tempdir().unwrap();
    let server = start(config(dir.path())).await;
    let alice = jobs_client(&server, Some(ALICE)).await;
    let image = png(4, 4);
    let transforms = |path: &str, matrix: &str| {
        format!(
            r#"{{"camera_angle_x": 0.69, "frames": [{{"file_path": "{path}", "transform_matrix": {matrix}}}]}}"#
        )
        .into_bytes()
    };
    let four = "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]";
    let three = "[[1,0,0,0],[0,1,0,0],[0,0,1,4]]";
    let send = |data: Vec<u8>| {
        let mut alice = alice.clone();
        async move {
            upload(
                &mut alice,
                pb::UploadKind::DatasetArchive,
                "scene.tar",
                &data,
            )
            .await
        }
    };

    // `tar -cf scene.tar -C my_scene .`, with a 3×4 matrix.
    let recipe = raw_tar(&[
        ("./", None),
        (
            "./transforms.json",
            Some(&transforms("images/a.png", three)),
        ),
        ("./images/", None),
        ("./images/a.png", Some(&image)),
    ]);
    send(recipe).await.expect("the documented tar recipe");

    let mut gzip = vec![0x1f, 0x8b, 8, 0];
    gzip.extend_from_slice(&[0; 600]);
    let nested = |depth: usize| {
        let dir = "d/".repeat(depth);
        raw_tar(&[
            (
                &format!("{dir}transforms.json"),
                Some(&transforms("a.png", four)),
            ),
            (&format!("{dir}a.png"), Some(&image)),
        ])
    };
    let mut garbage = vec![0x1bu8; 512];
    garbage[..5].copy_from_slice(b"\x07\x1b[2J");
    for (data, expect) in [
        (gzip, "compressed archives are not supported"),
        (
            raw_tar(&[
                ("transforms.json", Some(&transforms("a.png", four))),
                ("a.png", Some(&image)),
                ("a.png", Some(b"other")),
            ]),
            "appears twice",
        ),
        (nested(3), "no scene file"),
        (
            raw_tar(&[
                ("transforms.json", Some(&transforms("/a.png", four))),
                ("a.png", Some(&image)),
            ]),
            "relative path",
        ),
        (garbage, "tar archive"),
    ] {
        let refused = send(data).await.unwrap_err();
        let found = violations(&refused);
        assert_eq!(found.len(), 1, "{refused:?}");
        assert!(found[0].1.contains(expect), "{expect}: {found:?}");
        assert!(!found[0].1.chars().any(char::is_control), "{found:?}");
    }
    send(nested(2))
        .await
        .expect("two folders down, as the worker looks");
}
