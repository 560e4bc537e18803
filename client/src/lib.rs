//! Client library for the StylizedNeRF coordinator, for Rust web backends and the `stylenerf`
//! command line: upload a scene folder and style images, submit jobs, follow their progress,
//! cancel them, download their artifacts and request new stylized renders.
//!
//! ```no_run
//! # async fn demo() -> stylenerf_client::Result<()> {
//! use stylenerf_client::{Client, Input, JobSpec, WatchOptions};
//! use futures::StreamExt;
//!
//! let client = Client::connect("http://127.0.0.1:50051", Some("my-client-token")).await?;
//! let mut spec = JobSpec::new(Input::path("scenes/lego"), [Input::path("starry.jpg")]);
//! spec.preset = Some("quick".into());
//! spec.overrides.insert("nerf_pretrain.steps".into(), 500.into());
//! let job = client.submit(&spec).await?.job;
//! let mut events = client.watch(&job.id, WatchOptions::default()).await?;
//! while let Some(event) = events.next().await {
//!     println!("{}", stylenerf_client::json::message(&event?));
//! }
//! client.download(&job.id, "out/lego").await?;
//! # Ok(()) }
//! ```
//!
//! Only the protocol crate is needed: no engine, no candle.

mod client;
mod download;
mod error;
pub mod json;
pub mod names;
mod spec;
pub mod transport;
mod upload;
mod watch;

pub use client::Client;
pub use download::{DownloadOptions, DownloadedFile};
pub use error::{ClientError, FieldViolation, Result};
pub use spec::{Input, JobPage, JobSpec, ListFilter, RenderSpec, Submission, WatchOptions};
pub use stylenerf_proto::v1 as pb;
pub use transport::{ConnectOptions, DEFAULT_ENDPOINT};
pub use upload::{hash_file, pack_scene, PreparedUpload};
pub use watch::EventStream;
