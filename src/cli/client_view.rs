//! The live view of `stylenerf watch` (and `submit --wait`). On a terminal: a job line (stages
//! done, time since submission) and one progress bar per stage task with its step, loss, the
//! metrics a person reads, the time it has run and its ETA, redrawn within the terminal's width.
//! Without a terminal on stderr: one line per state change, and a progress line per running
//! stage at most every [`PLAIN_PROGRESS_EVERY`], so a log shows the job moving.

use super::client::{describe_progress, duration, now_ms};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::collections::HashMap;
use std::io::IsTerminal;
use std::time::{Duration, Instant};
use stylenerf_client::{names, pb};

/// Without a terminal, a running stage's progress is printed at most this often.
const PLAIN_PROGRESS_EVERY: Duration = Duration::from_secs(30);

/// One stage task as the view knows it.
struct TaskView {
    bar: ProgressBar,
    /// When its current attempt started (epoch ms; 0 when not running).
    started_at_ms: i64,
    /// When its progress was last printed as a plain line.
    printed: Option<Instant>,
}

/// The bars of one job, keyed by task id.
pub struct WatchView {
    job_id: String,
    multi: MultiProgress,
    job_bar: ProgressBar,
    tasks: HashMap<u64, TaskView>,
    tty: bool,
}

fn stage_style() -> ProgressStyle {
    ProgressStyle::with_template("{prefix:>16} [{bar:16}] {wide_msg}")
        .expect("valid template")
        .progress_chars("=> ")
}

fn job_style() -> ProgressStyle {
    ProgressStyle::with_template("{prefix:>16} [{bar:16}] {pos}/{len} stages, {elapsed} {wide_msg}")
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
        let multi = MultiProgress::with_draw_target(target);
        let since_submission = Duration::from_millis((now_ms() - job.created_at_ms).max(0) as u64);
        let job_bar = multi
            .add(ProgressBar::new(job.tasks.len().max(1) as u64).with_elapsed(since_submission));
        job_bar.set_style(job_style());
        job_bar.set_prefix("job");
        if tty {
            job_bar.enable_steady_tick(Duration::from_secs(1));
        }
        let mut view = WatchView {
            job_id: job.id.clone(),
            multi,
            job_bar,
            tasks: HashMap::new(),
            tty,
        };
        view.line(format!(
            "job {} ({}): {}",
            job.id,
            job.preset,
            names::job_state(job.state)
        ));
        for task in &job.tasks {
            view.task(task.id, task.stage).started_at_ms = task.started_at_ms;
            view.show_state(task.id, task.state, task.attempt, &task.error);
            if let Some(p) = &task.progress {
                if task.state == pb::TaskState::Leased as i32 {
                    view.show_progress(task.id, p);
                }
            }
        }
        view.count_done(job);
        view
    }

    fn line(&self, text: String) {
        if self.tty {
            let _ = self.multi.println(text);
        } else {
            eprintln!("{text}");
        }
    }

    fn task(&mut self, task_id: u64, stage: i32) -> &mut TaskView {
        let multi = &self.multi;
        self.tasks.entry(task_id).or_insert_with(|| {
            let bar = multi.add(ProgressBar::new(1));
            bar.set_style(stage_style());
            bar.set_prefix(names::stage(stage));
            TaskView {
                bar,
                started_at_ms: 0,
                printed: None,
            }
        })
    }

    fn count_done(&self, job: &pb::Job) {
        let done = job
            .tasks
            .iter()
            .filter(|t| t.state == pb::TaskState::Succeeded as i32)
            .count();
        self.job_bar.set_length(job.tasks.len().max(1) as u64);
        self.job_bar.set_position(done as u64);
    }

    /// A running task's step, metrics, time run and ETA.
    fn show_progress(&mut self, task_id: u64, p: &pb::Progress) {
        let tty = self.tty;
        let Some(task) = self.tasks.get_mut(&task_id) else {
            return;
        };
        task.bar.set_length(p.total.max(1));
        task.bar.set_position(p.step.min(p.total.max(1)));
        let ran = if task.started_at_ms > 0 {
            format!(
                "{} ",
                duration((now_ms() - task.started_at_ms).max(0) as f64 / 1000.0)
            )
        } else {
            String::new()
        };
        let text = format!("{ran}{}", describe_progress(p));
        if !tty
            && task
                .printed
                .is_none_or(|at| at.elapsed() >= PLAIN_PROGRESS_EVERY)
        {
            task.printed = Some(Instant::now());
            eprintln!("{} {text}", task.bar.prefix());
        }
        task.bar.set_message(text);
    }

    fn show_state(&mut self, task_id: u64, state: i32, attempt: u32, error: &str) {
        let Some(task) = self.tasks.get_mut(&task_id) else {
            return;
        };
        let bar = &task.bar;
        match pb::TaskState::try_from(state).unwrap_or_default() {
            pb::TaskState::Pending | pb::TaskState::Unspecified => bar.set_message("waiting"),
            pb::TaskState::Ready if attempt > 0 => {
                bar.set_message(format!("queued again (attempt {attempt} ended: {error})"))
            }
            pb::TaskState::Ready => bar.set_message("queued"),
            pb::TaskState::Leased => {
                if !bar.message().contains('/') {
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

    /// Updates the view with one event.
    pub fn apply(&mut self, event: &pb::Event) {
        match pb::EventKind::try_from(event.kind).unwrap_or_default() {
            pb::EventKind::TaskProgress => {
                if let Some(p) = &event.progress {
                    self.task(event.task_id, event.stage);
                    self.show_progress(event.task_id, p);
                }
            }
            pb::EventKind::TaskState => {
                let task = self.task(event.task_id, event.stage);
                if event.task_state == pb::TaskState::Leased as i32 {
                    task.started_at_ms = event.at_ms;
                    task.printed = None;
                }
                self.show_state(
                    event.task_id,
                    event.task_state,
                    event.attempt,
                    &event.message,
                );
                if event.task_state == pb::TaskState::Succeeded as i32 {
                    self.job_bar.inc(1);
                }
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
    pub fn finish(mut self, job: &pb::Job) {
        for task in &job.tasks {
            self.show_state(task.id, task.state, task.attempt, &task.error);
        }
        self.count_done(job);
        self.job_bar.finish_and_clear();
        for task in self.tasks.values() {
            if !task.bar.is_finished() {
                task.bar.abandon();
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
                "job {} succeeded{took}; download it with `stylenerf fetch {} --out DIR`",
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
