//! The live view of `stylenerf watch` (and `submit --wait`): one indicatif progress bar per
//! stage task with step/total, loss and metrics, the worker's ETA and the task's state, fed by
//! the job's events. Without a terminal on stderr it prints one line per state change instead.

use super::client::{describe_progress, duration};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::collections::HashMap;
use std::io::IsTerminal;
use stylenerf_client::{names, pb};

/// Progress bars of one job's tasks, keyed by task id.
pub struct WatchView {
    job_id: String,
    multi: MultiProgress,
    bars: HashMap<u64, ProgressBar>,
    tty: bool,
}

fn bar_style() -> ProgressStyle {
    ProgressStyle::with_template("{prefix:>16} [{bar:30}] {wide_msg}")
        .expect("valid template")
        .progress_chars("=> ")
}

impl WatchView {
    /// A view of `job` with a bar for each of its tasks.
    pub fn new(job: &pb::Job) -> Self {
        let tty = std::io::stderr().is_terminal();
        let target = if tty {
            ProgressDrawTarget::stderr()
        } else {
            ProgressDrawTarget::hidden()
        };
        let mut view = WatchView {
            job_id: job.id.clone(),
            multi: MultiProgress::with_draw_target(target),
            bars: HashMap::new(),
            tty,
        };
        view.line(format!(
            "job {} ({}): {}",
            job.id,
            job.preset,
            names::job_state(job.state)
        ));
        for task in &job.tasks {
            let bar = view.bar(task.id, task.stage);
            if let Some(p) = &task.progress {
                set_progress(&bar, p);
            }
            set_state(&bar, task.state, task.attempt, &task.error);
        }
        view
    }

    fn line(&self, text: String) {
        if self.tty {
            let _ = self.multi.println(text);
        } else {
            eprintln!("{text}");
        }
    }

    fn bar(&mut self, task_id: u64, stage: i32) -> ProgressBar {
        self.bars
            .entry(task_id)
            .or_insert_with(|| {
                let bar = self.multi.add(ProgressBar::new(1));
                bar.set_style(bar_style());
                bar.set_prefix(names::stage(stage));
                bar
            })
            .clone()
    }

    /// Updates the bars with one event.
    pub fn apply(&mut self, event: &pb::Event) {
        match pb::EventKind::try_from(event.kind).unwrap_or_default() {
            pb::EventKind::TaskProgress => {
                if let Some(p) = &event.progress {
                    let bar = self.bar(event.task_id, event.stage);
                    set_progress(&bar, p);
                    bar.set_message(describe_progress(p));
                }
            }
            pb::EventKind::TaskState => {
                let bar = self.bar(event.task_id, event.stage);
                set_state(&bar, event.task_state, event.attempt, &event.message);
                if !self.tty {
                    let reason = if event.message.is_empty() {
                        String::new()
                    } else {
                        format!(": {}", event.message)
                    };
                    eprintln!(
                        "{} {} (attempt {}){reason}",
                        names::stage(event.stage),
                        names::task_state(event.task_state),
                        event.attempt
                    );
                }
            }
            pb::EventKind::JobState => {
                let reason = if event.message.is_empty() {
                    String::new()
                } else {
                    format!(": {}", event.message)
                };
                self.line(format!(
                    "job {}: {}{reason}",
                    self.job_id,
                    names::job_state(event.job_state)
                ));
            }
            pb::EventKind::JobCreated | pb::EventKind::Unspecified => {}
        }
    }

    /// Final state of every bar and a summary line.
    pub fn finish(self, job: &pb::Job) {
        for task in &job.tasks {
            if let Some(bar) = self.bars.get(&task.id) {
                set_state(bar, task.state, task.attempt, &task.error);
            }
        }
        for bar in self.bars.values() {
            if !bar.is_finished() {
                bar.abandon();
            }
        }
        let took = if job.finished_at_ms > 0 && job.created_at_ms > 0 {
            format!(
                " in {}",
                duration((job.finished_at_ms - job.created_at_ms) as f64 / 1000.0)
            )
        } else {
            String::new()
        };
        let summary = match pb::JobState::try_from(job.state).unwrap_or_default() {
            pb::JobState::Succeeded => format!(
                "job {} succeeded{took}; download it with `stylenerf fetch {} -o DIR`",
                job.id, job.id
            ),
            _ if job.error.is_empty() => {
                format!("job {} {}{took}", job.id, names::job_state(job.state))
            }
            _ => format!(
                "job {} {}{took}: {}",
                job.id,
                names::job_state(job.state),
                job.error
            ),
        };
        self.line(summary);
    }
}

fn set_progress(bar: &ProgressBar, p: &pb::Progress) {
    bar.set_length(p.total.max(1));
    bar.set_position(p.step.min(p.total.max(1)));
}

fn set_state(bar: &ProgressBar, state: i32, attempt: u32, error: &str) {
    match pb::TaskState::try_from(state).unwrap_or_default() {
        pb::TaskState::Pending | pb::TaskState::Unspecified => bar.set_message("waiting"),
        pb::TaskState::Ready if attempt > 0 => {
            bar.set_message(format!("queued again (attempt {attempt} ended: {error})"))
        }
        pb::TaskState::Ready => bar.set_message("queued"),
        pb::TaskState::Leased => {
            if bar.message().is_empty() || !bar.message().contains('/') {
                bar.set_message(format!("running (attempt {attempt})"));
            }
        }
        pb::TaskState::Succeeded => {
            let length = bar.length().unwrap_or(1);
            bar.set_position(length);
            bar.finish_with_message("done");
        }
        pb::TaskState::Failed => bar.abandon_with_message(format!("failed: {error}")),
        pb::TaskState::Cancelled => bar.abandon_with_message("cancelled"),
    }
}
