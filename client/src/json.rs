//! JSON for scripts and web backends: the protocol's messages in proto JSON — the serde mapping
//! pbjson generates from `proto/` (one mapping, shared with anything else that prints them):
//! `.proto` field names (`created_at_ms`), enums by their full names (`"JOB_STATE_RUNNING"`),
//! 64-bit integers as strings, every field present. What a proto JSON parser in any language
//! reads back into the message. Plus the CLI's view of a downloaded file, which is not a message.

use crate::download::DownloadedFile;
use serde_json::{json, Value};

/// A protocol message as proto JSON.
pub fn message<M: serde::Serialize>(message: &M) -> Value {
    serde_json::to_value(message).unwrap_or_else(|e| json!({ "error": e.to_string() }))
}

pub fn downloaded(d: &DownloadedFile) -> Value {
    json!({
        "key": d.key,
        "path": d.path,
        "size": d.size.to_string(),
        "sha256": d.sha256,
        "skipped": d.skipped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use stylenerf_proto::v1 as pb;

    #[test]
    fn messages_round_trip_through_proto_json() {
        let job = pb::Job {
            id: "j-1".into(),
            state: pb::JobState::Running as i32,
            created_at_ms: 1_700_000_000_123,
            tasks: vec![pb::Task {
                id: 7,
                stage: pb::Stage::NerfPretrain as i32,
                progress: Some(pb::Progress {
                    step: 3,
                    metrics: [("psnr".to_string(), 21.5)].into(),
                    ..Default::default()
                }),
                ..Default::default()
            }],
            ..Default::default()
        };
        let value = message(&job);
        assert_eq!(value["state"], "JOB_STATE_RUNNING");
        assert_eq!(value["created_at_ms"], "1700000000123");
        assert_eq!(value["tasks"][0]["stage"], "STAGE_NERF_PRETRAIN");
        assert_eq!(value["tasks"][0]["progress"]["metrics"]["psnr"], 21.5);
        // Defaults are printed too.
        assert_eq!(value["error"], "");
        let back: pb::Job = serde_json::from_value(value).unwrap();
        assert_eq!(back, job);
    }
}
