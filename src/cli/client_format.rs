//! How the client commands print for people: jobs, events and progress lines, durations,
//! times and sizes (the JSON output is the proto JSON mapping, printed as is).

use serde_json::Value;
use std::io::Write;
use stylenerf_client::{names, pb};

pub(crate) fn print_json(out: &mut dyn Write, value: &Value) -> anyhow::Result<()> {
    serde_json::to_writer_pretty(&mut *out, value)?;
    writeln!(out)?;
    Ok(())
}

/// One line per event: `#12 14:03:21 nerf_pretrain leased (attempt 1)`.
pub(crate) fn describe_event(event: &pb::Event) -> String {
    let kind = pb::EventKind::try_from(event.kind).unwrap_or_default();
    let what = match kind {
        pb::EventKind::JobCreated => "job created".to_string(),
        pb::EventKind::JobState => format!("job {}", names::job_state(event.job_state)),
        pb::EventKind::TaskState => format!(
            "{} {} (attempt {})",
            names::stage(event.stage),
            names::task_state(event.task_state),
            event.attempt
        ),
        pb::EventKind::TaskProgress => format!(
            "{} {}",
            names::stage(event.stage),
            event
                .progress
                .as_ref()
                .map(describe_progress)
                .unwrap_or_default()
        ),
        pb::EventKind::Unspecified => names::event_kind(event.kind),
    };
    let message = if event.message.is_empty() {
        String::new()
    } else {
        format!(": {}", event.message)
    };
    format!("#{} {} {what}{message}", event.seq, clock(event.at_ms))
}

/// `value` with four significant digits (`24.31`, `0.003000`, `1235`), in scientific notation
/// when it is tiny (`5.00e-5`): a learning rate must not show as `0.00`.
pub(crate) fn significant(value: f64) -> String {
    if value == 0.0 || !value.is_finite() {
        return value.to_string();
    }
    let magnitude = value.abs().log10().floor() as i32;
    if magnitude < -3 {
        return format!("{value:.2e}");
    }
    let decimals = (3 - magnitude).clamp(0, 6) as usize;
    format!("{value:.decimals$}")
}

/// The metrics a person reads, in this order; the others a stage reports (`rays`,
/// `samples_per_ray`, `occupied`, `resumed_from`, …) are for benchmarks and `-o json`.
const SHOWN_METRICS: [&str; 4] = ["psnr", "style", "content", "lr"];

/// `120/800 ETA 1m20s loss 0.01230 psnr 24.31 lr 0.005000`: step and the stage's ETA first
/// (what a narrow terminal keeps), then the loss and the curated metrics with four significant
/// digits, then the worker's message.
pub fn describe_progress(p: &pb::Progress) -> String {
    let mut parts = Vec::new();
    if p.total > 0 {
        parts.push(format!("{}/{}", p.step, p.total));
    } else if p.step > 0 {
        parts.push(format!("step {}", p.step));
    }
    if p.eta_seconds > 0.0 && p.total > 0 && p.step < p.total {
        parts.push(format!("ETA {}", duration(p.eta_seconds)));
    }
    if p.loss != 0.0 {
        parts.push(format!("loss {}", significant(p.loss)));
    }
    for name in SHOWN_METRICS {
        if let Some(value) = p.metrics.get(name) {
            parts.push(format!("{name} {}", significant(*value)));
        }
    }
    if !p.message.is_empty() {
        parts.push(p.message.clone());
    }
    parts.join(" ")
}

pub(crate) fn print_job(out: &mut dyn Write, job: &pb::Job) -> anyhow::Result<()> {
    let name = if job.name.is_empty() {
        String::new()
    } else {
        format!(" ({})", job.name)
    };
    writeln!(out, "job {}{name}: {}", job.id, names::job_state(job.state))?;
    writeln!(
        out,
        "  preset {}, owner {}, created {}",
        job.preset,
        job.owner,
        ago(job.created_at_ms)
    )?;
    if !job.error.is_empty() {
        writeln!(out, "  error: {}", job.error)?;
    }
    for task in &job.tasks {
        let mut detail = match pb::TaskState::try_from(task.state).unwrap_or_default() {
            pb::TaskState::Leased => task
                .progress
                .as_ref()
                .map(describe_progress)
                .unwrap_or_default(),
            pb::TaskState::Succeeded if task.finished_at_ms > 0 && task.started_at_ms > 0 => {
                format!(
                    "in {}",
                    duration((task.finished_at_ms - task.started_at_ms) as f64 / 1000.0)
                )
            }
            _ => String::new(),
        };
        if !task.error.is_empty() {
            detail = format!("{detail} error: {}", task.error);
        }
        writeln!(
            out,
            "  {:<16} {:<10} attempt {}/{}  {}",
            names::stage(task.stage),
            names::task_state(task.state),
            task.attempt,
            task.max_attempts,
            detail.trim()
        )?;
    }
    Ok(())
}

pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// `3m ago`.
pub(crate) fn ago(at_ms: i64) -> String {
    if at_ms <= 0 {
        return "-".into();
    }
    format!(
        "{} ago",
        duration(((now_ms() - at_ms).max(0) as f64) / 1000.0)
    )
}

/// `14:03:21` (UTC) of an epoch-ms time.
pub(crate) fn clock(at_ms: i64) -> String {
    let secs = at_ms.div_euclid(1000).rem_euclid(86_400);
    format!("{:02}:{:02}:{:02}", secs / 3600, secs / 60 % 60, secs % 60)
}

/// `45s`, `12m03s`, `2h05m`.
pub fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match s {
        0..=59 => format!("{s}s"),
        60..=3599 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, s / 60 % 60),
    }
}

pub(crate) fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 4] = ["B", "KiB", "MiB", "GiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn progress_lines_durations_and_clocks() {
        assert_eq!(duration(75.0), "1m15s");
        // The metrics a person reads, in a fixed order with four significant digits; the
        // internal ones stay out of the line.
        let progress = pb::Progress {
            step: 120,
            total: 800,
            loss: 0.0123,
            eta_seconds: 80.0,
            metrics: [
                ("lr".to_string(), 0.00005),
                ("rays".to_string(), 8192.0),
                ("psnr".to_string(), 24.3149),
                ("samples_per_ray".to_string(), 29.5),
                ("style".to_string(), 1.5),
            ]
            .into(),
            ..Default::default()
        };
        let line = describe_progress(&progress);
        assert_eq!(
            line,
            "120/800 ETA 1m20s loss 0.01230 psnr 24.31 style 1.500 lr 5.00e-5"
        );
        // In the watch view (16-column stage name, bar, time run) at 80 columns, what is cut
        // is the end of the metrics, never the step or the ETA.
        let shown = 80 - 16 - 20 - "12m03s ".len();
        assert!(
            line.find("ETA 1m20s").unwrap() + "ETA 1m20s".len() <= shown,
            "{line}"
        );
        assert_eq!(clock(3_723_000), "01:02:03");
    }
}
