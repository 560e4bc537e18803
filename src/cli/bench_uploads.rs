//! `stylenerf bench uploads`: what a resumable upload (the client library's and the CLI's way:
//! `StartUpload`, `AppendUpload`, `FinishUpload`, each committed stream stored as a part and
//! joined at the finish) costs against a one-stream `Upload` (as the client sent it before:
//! hashed first, then streamed), for the same dataset archive file on an embedded coordinator
//! (loopback gRPC, SQLite file, local store). The two alternate, a few
//! rounds, so that both see the same machine.

use std::path::Path;
use std::time::Instant;

use futures::StreamExt;
use stylenerf_client::{hash_file, pack_scene, pb, Client};
use stylenerf_server::{Coordinator, CoordinatorConfig};

/// Options of `stylenerf bench uploads`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchUploadsArgs {
    /// Size of the archive's padding member, in MiB (the archive is a little larger).
    #[arg(long, default_value_t = 256)]
    pub mib: u64,
    /// Rounds of (one-stream, resumable) uploads.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
}

/// A scene folder with one tiny frame and `mib` MiB of incompressible padding.
fn write_scene(dir: &Path, mib: u64) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    std::fs::write(
        dir.join("transforms.json"),
        br#"{"camera_angle_x": 0.7, "frames": [{"file_path": "r_0.png",
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}"#,
    )?;
    stylenerf_engine::image_io::save_rgb_png(&dir.join("r_0.png"), 4, 4, &[0.5; 48])?;
    let mut rng = stylenerf_engine::Rng::new(1);
    let mut padding = vec![0u8; (mib << 20) as usize];
    for chunk in padding.chunks_mut(8) {
        let word = rng.next_u64().to_le_bytes();
        chunk.copy_from_slice(&word[..chunk.len()]);
    }
    std::fs::write(dir.join("padding.bin"), padding)?;
    Ok(())
}

/// One `Upload` stream as the client library sent it before resumable uploads: the file
/// hashed first (the header needs the SHA-256), then the header and the file in 1 MiB messages.
async fn one_stream(client: &Client, path: &Path) -> anyhow::Result<()> {
    let owned = path.to_path_buf();
    let (size, sha256) = tokio::task::spawn_blocking(move || hash_file(&owned)).await??;
    let file = tokio::fs::File::open(path).await?;
    let header = pb::UploadChunk {
        part: Some(pb::upload_chunk::Part::Header(pb::UploadHeader {
            kind: pb::UploadKind::DatasetArchive as i32,
            filename: "scene.tar".into(),
            total_size: size,
            sha256,
        })),
    };
    let error = std::sync::Arc::new(std::sync::Mutex::new(None));
    let data =
        stylenerf_proto::chunks::file_chunks(file, 1 << 20, error).map(|buf| pb::UploadChunk {
            part: Some(pb::upload_chunk::Part::Data(buf)),
        });
    client
        .raw()
        .upload(futures::stream::iter([header]).chain(data))
        .await?;
    Ok(())
}

pub fn run(args: BenchUploadsArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let dir = tempfile::tempdir()?;
        write_scene(&dir.path().join("scene"), args.mib)?;
        let archive = pack_scene(&dir.path().join("scene"))?;
        let coordinator =
            Coordinator::start(CoordinatorConfig::local(&dir.path().join("coordinator"))).await?;
        let client = Client::connect(&coordinator.endpoint(), None).await?;
        let mib = archive.size as f64 / f64::from(1 << 20);
        println!(
            "uploads benchmark: a {mib:.1} MiB dataset archive, embedded coordinator on \
             loopback, local store, {} rounds",
            args.rounds
        );
        println!("| round | one-stream Upload, MiB/s | resumable upload, MiB/s | ratio |");
        println!("|---|---|---|---|");
        let (mut one_total, mut resumable_total) = (0.0, 0.0);
        for round in 1..=args.rounds {
            let started = Instant::now();
            one_stream(&client, &archive.path).await?;
            let one = mib / started.elapsed().as_secs_f64();
            let started = Instant::now();
            client.upload_dataset(&archive.path).await?;
            let resumable = mib / started.elapsed().as_secs_f64();
            println!(
                "| {round} | {one:.0} | {resumable:.0} | {:.2} |",
                resumable / one
            );
            one_total += one;
            resumable_total += resumable;
        }
        let n = args.rounds.max(1) as f64;
        println!(
            "| mean | {:.0} | {:.0} | {:.2} |",
            one_total / n,
            resumable_total / n,
            resumable_total / one_total
        );
        coordinator.shutdown().await?;
        Ok(())
    })
}
