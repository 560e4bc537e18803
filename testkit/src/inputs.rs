//! Test inputs and how they reach a coordinator: tiny PNGs, tar archives (a two-frame
//! NeRF-synthetic scene, or any folder), chunked uploads, job requests and the field
//! violations of a refusal.

use sha2::{Digest, Sha256};
use std::path::Path;
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::job_service_client::JobServiceClient;
use tonic::Status;

use crate::clients::Authed;

pub fn sha256(data: &[u8]) -> String {
    hex::encode(Sha256::digest(data))
}

/// A `width`×`height` gradient PNG.
pub fn png(width: u32, height: u32) -> Vec<u8> {
    let image = image::RgbImage::from_fn(width, height, |x, y| {
        image::Rgb([(x * 40) as u8, (y * 40) as u8, 128])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    image.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A tar archive with the given regular members.
pub fn tar_of(members: &[(&str, &[u8])]) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for (path, data) in members {
        let mut header = tar::Header::new_gnu();
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        builder.append_data(&mut header, path, *data).unwrap();
    }
    builder.into_inner().unwrap()
}

/// A tar archive of the folder `dir`, under the name `name`.
pub fn tar_dir(name: &str, dir: &Path) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    builder.append_dir_all(name, dir).unwrap();
    builder.into_inner().unwrap()
}

/// The transforms of a two-frame NeRF-synthetic scene, `./train/r_0` and `./train/r_1`.
pub const SCENE_TRANSFORMS: &[u8] = br#"{"camera_angle_x": 0.69, "frames": [
    {"file_path": "./train/r_0", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]},
    {"file_path": "./train/r_1", "transform_matrix": [[0,0,1,4],[0,1,0,0],[-1,0,0,0],[0,0,0,1]]}
]}"#;

/// A small NeRF-synthetic scene in `lego/`: [`SCENE_TRANSFORMS`] and two 4×4 images.
pub fn scene_tar() -> Vec<u8> {
    let image = png(4, 4);
    tar_of(&[
        ("lego/transforms_train.json", SCENE_TRANSFORMS),
        ("lego/train/r_0.png", &image),
        ("lego/train/r_1.png", &image),
    ])
}

/// Writes the scene the training tests share to `dir`: generated, 32×32, 8 views.
#[cfg(feature = "scenes")]
pub fn tiny_scene(dir: &Path) {
    use stylenerf_engine::scene::generate::{generate, GenerateOptions};
    let options = GenerateOptions {
        size: 32,
        views: 8,
        ..Default::default()
    };
    generate(&options, dir).expect("scene generated");
}

/// Uploads `data` with an explicit header (for malformed-upload tests), in 64 KiB chunks.
pub async fn upload_raw(
    client: &mut JobServiceClient<Authed>,
    header: pb::UploadHeader,
    data: &[u8],
) -> Result<pb::UploadReceipt, Status> {
    let mut messages = vec![pb::UploadChunk {
        part: Some(pb::upload_chunk::Part::Header(header)),
    }];
    for chunk in data.chunks(64 << 10) {
        messages.push(pb::UploadChunk {
            part: Some(pb::upload_chunk::Part::Data(chunk.to_vec())),
        });
    }
    client
        .upload(tokio_stream::iter(messages))
        .await
        .map(|r| r.into_inner())
}

pub async fn upload(
    client: &mut JobServiceClient<Authed>,
    kind: pb::UploadKind,
    filename: &str,
    data: &[u8],
) -> Result<pb::UploadReceipt, Status> {
    let header = pb::UploadHeader {
        kind: kind as i32,
        filename: filename.into(),
        total_size: data.len() as u64,
        sha256: sha256(data),
    };
    upload_raw(client, header, data).await
}

/// An input naming an upload.
pub fn uploaded(receipt: &pb::UploadReceipt) -> pb::InputRef {
    pb::InputRef {
        source: Some(pb::input_ref::Source::UploadId(receipt.upload_id.clone())),
    }
}

/// Uploads the test scene and two styles and returns a `tiny` create request for them.
pub async fn job_request(client: &mut JobServiceClient<Authed>) -> pb::CreateJobRequest {
    let dataset = upload(
        client,
        pb::UploadKind::DatasetArchive,
        "lego.tar",
        &scene_tar(),
    )
    .await
    .expect("dataset upload");
    let mut styles = Vec::new();
    for size in [8, 12] {
        let receipt = upload(
            client,
            pb::UploadKind::StyleImage,
            "style.png",
            &png(size, size),
        )
        .await
        .expect("style upload");
        styles.push(uploaded(&receipt));
    }
    pb::CreateJobRequest {
        name: "lego".into(),
        dataset: Some(uploaded(&dataset)),
        styles,
        preset: "tiny".into(),
        ..Default::default()
    }
}

/// Creates the job of `request`, which must be accepted.
pub async fn create(
    client: &mut JobServiceClient<Authed>,
    request: pb::CreateJobRequest,
) -> pb::Job {
    client
        .create_job(request)
        .await
        .expect("job created")
        .into_inner()
        .job
        .expect("the reply holds the job")
}

/// Creates a job of [`job_request`].
pub async fn create_job(client: &mut JobServiceClient<Authed>) -> pb::Job {
    let request = job_request(client).await;
    create(client, request).await
}

/// The job's events after `after_seq` (`skip_progress`: without progress events), then live.
pub async fn watch(
    client: &mut JobServiceClient<Authed>,
    job_id: &str,
    after_seq: u64,
    skip_progress: bool,
) -> tonic::Streaming<pb::Event> {
    client
        .watch_job(pb::WatchJobRequest {
            job_id: job_id.into(),
            after_seq,
            skip_progress,
        })
        .await
        .expect("watch job")
        .into_inner()
}

pub async fn get_job(client: &mut JobServiceClient<Authed>, id: &str) -> pb::Job {
    client
        .get_job(pb::GetJobRequest { job_id: id.into() })
        .await
        .expect("get job")
        .into_inner()
}

/// The BadRequest field violations of a status.
pub fn bad_fields(status: &Status) -> Vec<String> {
    use tonic_types::StatusExt;
    status
        .get_details_bad_request()
        .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default()
}
