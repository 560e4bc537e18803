//! Malformed and oversized uploads are refused with INVALID_ARGUMENT naming the field: unsafe
//! archive members, links, missing scene files, bad checksums, sizes over the limits or not
//! matching the header, and style images that do not decode.

use stylenerf_server::proto::v1 as pb;
use stylenerf_testkit::*;
use tonic::Code;

/// A tar whose single member has a raw (unchecked) name and type.
fn raw_tar(name: &str, kind: tar::EntryType, link: Option<&str>) -> Vec<u8> {
    let mut header = tar::Header::new_gnu();
    let bytes = name.as_bytes();
    header.as_old_mut().name[..bytes.len()].copy_from_slice(bytes);
    header.set_entry_type(kind);
    header.set_mode(0o644);
    if let Some(target) = link {
        header.as_old_mut().linkname[..target.len()].copy_from_slice(target.as_bytes());
    }
    let data: &[u8] = if kind == tar::EntryType::Regular {
        b"evil"
    } else {
        b""
    };
    header.set_size(data.len() as u64);
    header.set_cksum();
    let mut builder = tar::Builder::new(Vec::new());
    builder.append(&header, data).unwrap();
    builder.into_inner().unwrap()
}

async fn rejected(
    client: &mut stylenerf_server::proto::v1::job_service_client::JobServiceClient<Authed>,
    kind: pb::UploadKind,
    data: &[u8],
) -> tonic::Status {
    upload(client, kind, "input.bin", data).await.unwrap_err()
}

#[tokio::test]
async fn malformed_and_oversized_uploads_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = config(dir.path());
    config.limits.max_dataset_bytes = 256 << 10;
    config.limits.max_style_bytes = 64 << 10;
    let server = start(config).await;
    let mut client = jobs_client(&server, Some(ALICE)).await;
    let dataset = pb::UploadKind::DatasetArchive;

    let cases: Vec<(Vec<u8>, &str)> = vec![
        (
            raw_tar("../escape.txt", tar::EntryType::Regular, None),
            "`..`",
        ),
        (
            raw_tar("/etc/passwd", tar::EntryType::Regular, None),
            "absolute",
        ),
        (
            raw_tar("link", tar::EntryType::Symlink, Some("/etc/passwd")),
            "symbolic link",
        ),
        (
            raw_tar("hard", tar::EntryType::Link, Some("x")),
            "hard link",
        ),
        (tar_of(&[("image.png", &png(2, 2))]), "no scene file"),
        (tar_of(&[("transforms.json", b"{\"frames\": 3}")]), "frames"),
        (
            b"definitely not a tar archive, just some text".repeat(20),
            "tar",
        ),
    ];
    for (data, expected) in cases {
        let status = rejected(&mut client, dataset, &data).await;
        assert_eq!(status.code(), Code::InvalidArgument, "{}", status.message());
        assert!(
            status.message().contains(expected),
            "{expected}: {}",
            status.message()
        );
        assert_eq!(bad_fields(&status), ["data"]);
    }

    // Checksum mismatch.
    let scene = scene_tar();
    let mut header = pb::UploadHeader {
        kind: dataset as i32,
        filename: "scene.tar".into(),
        total_size: scene.len() as u64,
        sha256: sha256(b"something else"),
    };
    let status = upload_raw(&mut client, header.clone(), &scene)
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&status), ["header.sha256"]);
    assert!(status.message().contains("checksum mismatch"));
    // Declared too large for the limit.
    header.sha256 = sha256(&scene);
    header.total_size = 1 << 30;
    let status = upload_raw(&mut client, header.clone(), &scene)
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&status), ["header.total_size"]);
    // More data than declared, and less.
    header.total_size = 100;
    let status = upload_raw(&mut client, header.clone(), &scene)
        .await
        .unwrap_err();
    assert!(
        status.message().contains("more data than"),
        "{}",
        status.message()
    );
    header.total_size = scene.len() as u64 + 10;
    let status = upload_raw(&mut client, header.clone(), &scene)
        .await
        .unwrap_err();
    assert!(
        status.message().contains("ended after"),
        "{}",
        status.message()
    );
    // Bad file name and kind.
    header.total_size = scene.len() as u64;
    header.filename = "../scene.tar".into();
    let status = upload_raw(&mut client, header.clone(), &scene)
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&status), ["header.filename"]);
    header.filename = "scene.tar".into();
    header.kind = 0;
    let status = upload_raw(&mut client, header, &scene).await.unwrap_err();
    assert_eq!(bad_fields(&status), ["header.kind"]);

    // Style images: not an image, truncated, too large.
    let style = pb::UploadKind::StyleImage;
    let status = rejected(&mut client, style, b"GIF? no, plain text").await;
    assert!(
        status.message().contains("not an image"),
        "{}",
        status.message()
    );
    let truncated = &png(16, 16)[..60];
    let status = rejected(&mut client, style, truncated).await;
    assert!(
        status.message().contains("cannot decode"),
        "{}",
        status.message()
    );
    let status = rejected(&mut client, style, &vec![0u8; 70 << 10]).await;
    assert_eq!(bad_fields(&status), ["header.total_size"]);
    // A dataset is not a style, and job creation checks its arguments.
    let ok = upload(&mut client, dataset, "scene.tar", &scene)
        .await
        .unwrap();
    assert!(ok.summary.contains("blender"), "{}", ok.summary);
    let status = client
        .create_job(pb::CreateJobRequest {
            dataset: Some(pb::InputRef {
                source: Some(pb::input_ref::Source::UploadId(ok.upload_id.clone())),
            }),
            styles: vec![pb::InputRef {
                source: Some(pb::input_ref::Source::UploadId(ok.upload_id.clone())),
            }],
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(bad_fields(&status), ["styles[0].upload_id"]);
    let status = client
        .create_job(pb::CreateJobRequest {
            preset: "gigantic".into(),
            config_overrides_json: "[1, 2]".into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(
        bad_fields(&status),
        ["preset", "styles", "config_overrides_json"]
    );
    server.shutdown().await.unwrap();
}
