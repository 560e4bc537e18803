//! `stylenerf bench coordinator`: an embedded coordinator on loopback with a real SQLite file,
//! measuring job creation throughput, lease→heartbeat→complete cycles with concurrent fake
//! workers, and GetJob latency under many concurrent clients.

use crate::auth::{AuthConfig, Role, TokenEntry};
use crate::config::CoordinatorConfig;
use crate::coordinator::Coordinator;
use sha2::{Digest, Sha256};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use stylenerf_proto::bearer::{Authed, Bearer};
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::job_service_client::JobServiceClient;
use stylenerf_proto::v1::worker_service_client::WorkerServiceClient;
use tonic::transport::Channel;

/// Options of the coordinator benchmark.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchOptions {
    /// Jobs to create (each brings five tasks for the lease phase).
    #[arg(long, default_value_t = 1000)]
    pub jobs: usize,
    /// Concurrent submitters while creating jobs.
    #[arg(long, default_value_t = 16)]
    pub submitters: usize,
    /// Concurrent fake workers in the lease phase.
    #[arg(long, default_value_t = 16)]
    pub workers: usize,
    /// Concurrent clients in the GetJob phase, each on its own connection.
    #[arg(long, default_value_t = 100)]
    pub clients: usize,
    /// GetJob calls per client.
    #[arg(long, default_value_t = 100)]
    pub requests_per_client: usize,
}

/// Results of one run.
#[derive(Debug, Clone)]
pub struct BenchReport {
    pub jobs: usize,
    pub jobs_per_second: f64,
    pub cycles: usize,
    pub cycles_per_second: f64,
    pub get_job_requests: usize,
    pub get_job_per_second: f64,
    pub get_job_p50: Duration,
    pub get_job_p99: Duration,
    /// Process CPU time per created job, per cycle and per GetJob call (client and server
    /// together), when the platform reports it.
    pub cpu_per_op: Option<[Duration; 3]>,
}

impl std::fmt::Display for BenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "jobs created:       {:>6} jobs,   {:>8.0} jobs/s",
            self.jobs, self.jobs_per_second
        )?;
        writeln!(
            f,
            "lease cycles:       {:>6} cycles, {:>8.0} cycles/s (lease -> heartbeat -> complete)",
            self.cycles, self.cycles_per_second
        )?;
        write!(
            f,
            "GetJob:             {:>6} calls,  {:>8.0} calls/s, p50 {:.2} ms, p99 {:.2} ms",
            self.get_job_requests,
            self.get_job_per_second,
            self.get_job_p50.as_secs_f64() * 1e3,
            self.get_job_p99.as_secs_f64() * 1e3
        )?;
        if let Some([job, cycle, get]) = self.cpu_per_op {
            write!(
                f,
                "\nCPU per operation (client + server): create {:.2} ms, cycle {:.2} ms, GetJob {:.2} ms",
                job.as_secs_f64() * 1e3,
                cycle.as_secs_f64() * 1e3,
                get.as_secs_f64() * 1e3
            )?;
        }
        Ok(())
    }
}

const CLIENT_TOKEN: &str = "bench-client-token-0000";
const WORKER_TOKEN: &str = "bench-worker-token-0000";

async fn connect(endpoint: &str, token: &str) -> anyhow::Result<(Channel, Bearer)> {
    let channel = Channel::from_shared(endpoint.to_string())?
        .tcp_nodelay(true)
        .connect()
        .await?;
    Ok((channel, Bearer::new(Some(token))?))
}

async fn job_client(endpoint: &str) -> anyhow::Result<JobServiceClient<Authed>> {
    let (channel, bearer) = connect(endpoint, CLIENT_TOKEN).await?;
    Ok(JobServiceClient::with_interceptor(channel, bearer))
}

/// A one-frame scene and a tiny style image, uploaded once and reused by every job.
async fn upload_inputs(
    client: &mut JobServiceClient<Authed>,
) -> anyhow::Result<pb::CreateJobRequest> {
    let image = {
        let img = image::RgbImage::from_pixel(4, 4, image::Rgb([200, 100, 50]));
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)?;
        out.into_inner()
    };
    let transforms = br#"{"camera_angle_x": 0.7, "frames": [{"file_path": "r_0.png",
        "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}"#;
    let mut builder = tar::Builder::new(Vec::new());
    for (name, data) in [("transforms.json", &transforms[..]), ("r_0.png", &image)] {
        let mut header = tar::Header::new_gnu();
        header.set_size(data.len() as u64);
        header.set_mode(0o644);
        header.set_cksum();
        builder.append_data(&mut header, name, data)?;
    }
    let scene = builder.into_inner()?;
    let mut ids = Vec::new();
    for (kind, name, data) in [
        (pb::UploadKind::DatasetArchive, "scene.tar", &scene),
        (pb::UploadKind::StyleImage, "style.png", &image),
    ] {
        let messages = vec![
            pb::UploadChunk {
                part: Some(pb::upload_chunk::Part::Header(pb::UploadHeader {
                    kind: kind as i32,
                    filename: name.into(),
                    total_size: data.len() as u64,
                    sha256: hex::encode(Sha256::digest(data)),
                })),
            },
            pb::UploadChunk {
                part: Some(pb::upload_chunk::Part::Data(data.clone())),
            },
        ];
        ids.push(
            client
                .upload(tokio_stream::iter(messages))
                .await?
                .into_inner()
                .upload_id,
        );
    }
    let input = |id: &String| pb::InputRef {
        source: Some(pb::input_ref::Source::UploadId(id.clone())),
    };
    Ok(pb::CreateJobRequest {
        name: "bench".into(),
        dataset: Some(input(&ids[0])),
        styles: vec![input(&ids[1])],
        preset: "tiny".into(),
        ..Default::default()
    })
}

/// CPU time (user + system) this process has used, from `/proc/self/stat` on Linux.
fn process_cpu() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are the 12th and 13th.
    let rest = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    // The kernel reports clock ticks of USER_HZ, 100 per second on Linux.
    Some(Duration::from_millis(ticks * 10))
}

/// Runs the benchmark against a fresh coordinator in a temporary directory.
pub async fn run(options: &BenchOptions) -> anyhow::Result<BenchReport> {
    let dir = tempfile::tempdir()?;
    let mut config = CoordinatorConfig::local(dir.path());
    config.auth = AuthConfig::Tokens(vec![
        TokenEntry {
            role: Role::Client,
            name: "bench".into(),
            token: CLIENT_TOKEN.into(),
        },
        TokenEntry {
            role: Role::Worker,
            name: "bench-worker".into(),
            token: WORKER_TOKEN.into(),
        },
    ]);
    let coordinator = Coordinator::start(config).await?;
    let endpoint = coordinator.endpoint();

    // Phase 1: job creation.
    let request = upload_inputs(&mut job_client(&endpoint).await?).await?;
    let created = Arc::new(AtomicUsize::new(0));
    let cpu_start = process_cpu();
    let started = Instant::now();
    let mut submitters = Vec::new();
    for _ in 0..options.submitters.max(1) {
        let mut client = job_client(&endpoint).await?;
        let (request, created, total) = (request.clone(), created.clone(), options.jobs);
        submitters.push(tokio::spawn(async move {
            let mut ids = Vec::new();
            while created.fetch_add(1, Ordering::Relaxed) < total {
                let job = client.create_job(request.clone()).await?.into_inner().job;
                ids.extend(job.map(|j| j.id));
            }
            anyhow::Ok(ids)
        }));
    }
    let mut job_ids = Vec::new();
    for s in submitters {
        job_ids.extend(s.await??);
    }
    let jobs_secs = started.elapsed().as_secs_f64();
    let cpu_jobs = process_cpu();

    // Phase 2: lease -> heartbeat -> complete with concurrent workers.
    let cycles = Arc::new(AtomicUsize::new(0));
    let started = Instant::now();
    let mut workers = Vec::new();
    for n in 0..options.workers.max(1) {
        let (channel, bearer) = connect(&endpoint, WORKER_TOKEN).await?;
        let mut client = WorkerServiceClient::with_interceptor(channel, bearer);
        let cycles = cycles.clone();
        workers.push(tokio::spawn(async move {
            let worker_id = client
                .register_worker(pb::RegisterWorkerRequest {
                    name: format!("bench-{n}"),
                    capabilities: Some(pb::Capabilities {
                        device: "cpu".into(),
                        ..Default::default()
                    }),
                    worker_id: String::new(),
                })
                .await?
                .into_inner()
                .worker_id;
            loop {
                let lease = client
                    .lease_task(pb::LeaseTaskRequest {
                        worker_id: worker_id.clone(),
                        wait_ms: 300,
                        free_memory_bytes: 0,
                    })
                    .await?
                    .into_inner();
                let Some(task) = lease.task else { break };
                client
                    .heartbeat(pb::HeartbeatRequest {
                        worker_id: worker_id.clone(),
                        task_id: task.task_id,
                        fencing_token: task.fencing_token,
                        progress: Some(pb::Progress {
                            step: 1,
                            total: 1,
                            loss: 0.1,
                            ..Default::default()
                        }),
                    })
                    .await?;
                client
                    .complete_task(pb::CompleteTaskRequest {
                        worker_id: worker_id.clone(),
                        task_id: task.task_id,
                        fencing_token: task.fencing_token,
                        outputs: vec![pb::Artifact {
                            key: format!("{}out.bin", task.output_prefix),
                            size: 1,
                            sha256: "0".repeat(64),
                        }],
                        metrics: Default::default(),
                    })
                    .await?;
                cycles.fetch_add(1, Ordering::Relaxed);
            }
            anyhow::Ok(())
        }));
    }
    for w in workers {
        w.await??;
    }
    let cycles = cycles.load(Ordering::Relaxed);
    // The last lease waited for nothing; do not count that idle wait.
    let cycle_secs = (started.elapsed().as_secs_f64() - 0.3).max(1e-3);
    let cpu_cycles = process_cpu();

    // Phase 3: GetJob latency under concurrent clients.
    let job_ids = Arc::new(job_ids);
    let started = Instant::now();
    let mut clients = Vec::new();
    for c in 0..options.clients.max(1) {
        let mut client = job_client(&endpoint).await?;
        let (ids, n) = (job_ids.clone(), options.requests_per_client);
        clients.push(tokio::spawn(async move {
            let mut latencies = Vec::with_capacity(n);
            for i in 0..n {
                let id = ids[(c * 7919 + i * 104729) % ids.len()].clone();
                let t = Instant::now();
                client.get_job(pb::GetJobRequest { job_id: id }).await?;
                latencies.push(t.elapsed());
            }
            anyhow::Ok(latencies)
        }));
    }
    let mut latencies = Vec::new();
    for c in clients {
        latencies.extend(c.await??);
    }
    let get_secs = started.elapsed().as_secs_f64();
    let cpu_gets = process_cpu();
    latencies.sort();
    let pct = |p: f64| latencies[((latencies.len() as f64 * p) as usize).min(latencies.len() - 1)];
    coordinator.shutdown().await?;
    let per_op =
        |from: Duration, to: Duration, n: usize| (to.saturating_sub(from)) / n.max(1) as u32;
    let cpu_per_op = match (cpu_start, cpu_jobs, cpu_cycles, cpu_gets) {
        (Some(a), Some(b), Some(c), Some(d)) => Some([
            per_op(a, b, job_ids.len()),
            per_op(b, c, cycles),
            per_op(c, d, latencies.len()),
        ]),
        _ => None,
    };
    Ok(BenchReport {
        jobs: job_ids.len(),
        jobs_per_second: job_ids.len() as f64 / jobs_secs,
        cycles,
        cycles_per_second: cycles as f64 / cycle_secs,
        get_job_requests: latencies.len(),
        get_job_per_second: latencies.len() as f64 / get_secs,
        get_job_p50: pct(0.50),
        get_job_p99: pct(0.99),
        cpu_per_op,
    })
}
