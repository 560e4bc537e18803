//! Short lower-case names of the protocol's enums (`nerf_pretrain`, `running`, `leased`,
//! `task_progress`), derived from the generated `as_str_name`, for display, JSON output and
//! command-line filters.

use stylenerf_proto::v1 as pb;

fn short(name: &str, prefix: &str) -> String {
    name.strip_prefix(prefix)
        .unwrap_or(name)
        .to_ascii_lowercase()
}

/// `STAGE_NERF_PRETRAIN` → `nerf_pretrain`.
pub fn stage(stage: i32) -> String {
    pb::Stage::try_from(stage)
        .map(|s| short(s.as_str_name(), "STAGE_"))
        .unwrap_or_else(|_| format!("stage_{stage}"))
}

/// `JOB_STATE_RUNNING` → `running`.
pub fn job_state(state: i32) -> String {
    pb::JobState::try_from(state)
        .map(|s| short(s.as_str_name(), "JOB_STATE_"))
        .unwrap_or_else(|_| format!("state_{state}"))
}

/// `TASK_STATE_LEASED` → `leased`.
pub fn task_state(state: i32) -> String {
    pb::TaskState::try_from(state)
        .map(|s| short(s.as_str_name(), "TASK_STATE_"))
        .unwrap_or_else(|_| format!("state_{state}"))
}

/// `EVENT_KIND_TASK_PROGRESS` → `task_progress`.
pub fn event_kind(kind: i32) -> String {
    pb::EventKind::try_from(kind)
        .map(|k| short(k.as_str_name(), "EVENT_KIND_"))
        .unwrap_or_else(|_| format!("kind_{kind}"))
}

/// `running` (any case, with or without the `JOB_STATE_` prefix) → `JobState::Running`.
pub fn parse_job_state(text: &str) -> Option<pb::JobState> {
    let upper = text.trim().to_ascii_uppercase();
    let full = if upper.starts_with("JOB_STATE_") {
        upper
    } else {
        format!("JOB_STATE_{upper}")
    };
    pb::JobState::from_str_name(&full).filter(|s| *s != pb::JobState::Unspecified)
}

/// Whether a job in this state is finished (succeeded, failed or cancelled).
pub fn is_terminal(state: i32) -> bool {
    matches!(
        pb::JobState::try_from(state),
        Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
    )
}

/// Whether the event puts its job in a terminal state (the last event of a watch).
pub fn is_terminal_event(event: &pb::Event) -> bool {
    event.kind == pb::EventKind::JobState as i32 && is_terminal(event.job_state)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        assert_eq!(stage(pb::Stage::NerfPretrain as i32), "nerf_pretrain");
        assert_eq!(job_state(pb::JobState::Cancelled as i32), "cancelled");
        assert_eq!(task_state(pb::TaskState::Leased as i32), "leased");
        assert_eq!(
            event_kind(pb::EventKind::TaskProgress as i32),
            "task_progress"
        );
        assert_eq!(parse_job_state("Running"), Some(pb::JobState::Running));
        assert_eq!(
            parse_job_state("JOB_STATE_FAILED"),
            Some(pb::JobState::Failed)
        );
        assert_eq!(parse_job_state("unspecified"), None);
        assert_eq!(parse_job_state("done"), None);
        assert!(is_terminal(pb::JobState::Succeeded as i32));
        assert!(!is_terminal(pb::JobState::Running as i32));
    }
}
