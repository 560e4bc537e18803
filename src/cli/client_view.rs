//! The live view of `stylenerf watch` (and `submit --wait`). On a terminal: a job line (stages
//! done, time since submission, the job's ETA) and one progress bar per stage task with its
//! step, loss, the metrics a person reads, the time it has run and its ETA, redrawn within the
//! terminal's width. Without a terminal on stderr: one line per state change (with the job's
//! ETA when a stage ends), and a progress line per running stage at most every
//! [`PLAIN_PROGRESS_EVERY`], so a log shows the job moving.
//!
//! The job's ETA is the running stage's own ETA plus, for the stages still to come, how long
//! they took in the caller's newest succeeded job of the same preset ([`StageTimes`]); with
//! no such job, none is shown.

use super::client_format::{describe_progress, duration, now_ms};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::collections::HashMap;
use std::io::IsTerminal;
use std::time::{Duration, Instant};
use stylenerf_client::{names, pb, Client, ListFilter};

/// How long each stage took in an earlier job: the basis of the job's ETA.
#[derive(Debug, Clone, Default)]
pub struct StageTimes {
    /// The job they come from.
    pub job_id: String,
    /// Seconds by stage (the first task of each stage).
    pub seconds: HashMap<i32, f64>,
}

impl StageTimes {
    /// The stage times of the caller's newest succeeded job with `job`'s preset, other than
    /// `job` itself; `None` when there is none (or the listing fails).
    pub async fn of_last_similar(client: &Client, job: &pb::Job) -> Option<StageTimes> {
        let filter = ListFilter {
            states: vec![pb::JobState::Succeeded],
            page_size: 20,
            include_tasks: true,
            ..Default::default()
        };
        let page = client.list(&filter).await.ok()?;
        let similar = page
            .jobs
            .into_iter()
            .find(|j| j.id != job.id && j.preset == job.preset)?;
        Some(StageTimes::of(&similar))
    }

    /// The stage times of a finished job.
    pub fn of(job: &pb::Job) -> StageTimes {
        let mut seconds = HashMap::new();
        for task in &job.tasks {
            if task.started_at_ms > 0 && task.finished_at_ms >= task.started_at_ms {
                seconds
                    .entry(task.stage)
                    .or_insert((task.finished_at_ms - task.started_at_ms) as f64 / 1000.0);
            }
        }
        StageTimes {
            job_id: job.id.clone(),
            seconds,
        }
    }
}

/// What the job's ETA needs to know of one task.
#[derive(Debug, Clone, Copy, PartialEq)]
struct TaskClock {
    stage: i32,
    state: i32,
    /// The task's own ETA from its last progress (0: none yet).
    eta_seconds: f64,
    /// Seconds it has run in its current attempt (0 when not running).
    ran_seconds: f64,
}

/// Seconds until every task has ended: a running task's own ETA (or, before it has one, its
/// stage's earlier time less what it has run), plus the earlier time of each stage still to
/// come; `None` when a stage still to come has no earlier time.
fn job_eta(tasks: &[TaskClock], times: &StageTimes) -> Option<f64> {
    let mut left = 0.0;
    for task in tasks {
        let before = times.seconds.get(&task.stage).copied();
        left += match pb::TaskState::try_from(task.state).unwrap_or_default() {
            pb::TaskState::Succeeded | pb::TaskState::Failed | pb::TaskState::Cancelled => 0.0,
            pb::TaskState::Leased if task.eta_seconds > 0.0 => task.eta_seconds,
            pb::TaskState::Leased => (before? - task.ran_seconds).max(0.0),
            _ => before?,
        };
    }
    Some(left)
}

/// Without a terminal, a running stage's progress is printed at most this often.
const PLAIN_PROGRESS_EVERY: Duration = Duration::from_secs(30);

/// One stage task as the view knows it.
struct TaskView {
    bar: ProgressBar,
    stage: i32,
    state: i32,
    /// Its ETA from the last progress of the current attempt (0: none).
    eta_seconds: f64,
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
    /// Earlier stage times, for the job's ETA.
    times: Option<StageTimes>,
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
    /// A view of `job` with a bar for each of its tasks; `times` (an earlier job's) give the
    /// job's ETA.
    pub fn new(job: &pb::Job, times: Option<StageTimes>) -> Self {
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
            times,
        };
        view.line(format!(
            "job {} ({}): {}",
            job.id,
            job.preset,
            names::job_state(job.state)
        ));
        for task in &job.tasks {
            let view_task = view.task(task.id, task.stage);
            view_task.started_at_ms = task.started_at_ms;
            view_task.state = task.state;
            view.show_state(task.id, task.state, task.attempt, &task.error);
            if let Some(p) = &task.progress {
                if task.state == pb::TaskState::Leased as i32 {
                    view.show_progress(task.id, p);
                }
            }
        }
        view.count_done(job);
        view.show_job_eta();
        view
    }

    /// The job's ETA, if earlier stage times allow one.
    fn job_eta(&self) -> Option<f64> {
        let now = now_ms();
        let clocks: Vec<TaskClock> = self
            .tasks
            .values()
            .map(|t| TaskClock {
                stage: t.stage,
                state: t.state,
                eta_seconds: t.eta_seconds,
                ran_seconds: if t.started_at_ms > 0 {
                    (now - t.started_at_ms).max(0) as f64 / 1000.0
                } else {
                    0.0
                },
            })
            .collect();
        job_eta(&clocks, self.times.as_ref()?)
    }

    fn job_eta_text(&self) -> Option<String> {
        let eta = self.job_eta()?;
        let from = self.times.as_ref()?;
        Some(format!(
            "job ETA ~{} (stage times of {})",
            duration(eta),
            from.job_id
        ))
    }

    fn show_job_eta(&self) {
        self.job_bar
            .set_message(self.job_eta_text().unwrap_or_default());
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
                stage,
                state: pb::TaskState::Pending as i32,
                eta_seconds: 0.0,
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
        task.eta_seconds = p.eta_seconds.max(0.0);
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
                    self.show_job_eta();
                }
            }
            pb::EventKind::TaskState => {
                let task = self.task(event.task_id, event.stage);
                task.state = event.task_state;
                if event.task_state == pb::TaskState::Leased as i32 {
                    task.started_at_ms = event.at_ms;
                    task.eta_seconds = 0.0;
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
                self.show_job_eta();
                if !self.tty {
                    let reason = if event.message.is_empty() {
                        String::new()
                    } else {
                        format!(": {}", event.message)
                    };
                    let eta = match self.job_eta_text() {
                        Some(eta) if event.task_state == pb::TaskState::Succeeded as i32 => {
                            format!("; {eta}")
                        }
                        _ => String::new(),
                    };
                    eprintln!(
                        "{} {} (attempt {}){reason}{eta}",
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

#[cfg(test)]
mod tests {
    use super::*;

    fn clock(stage: pb::Stage, state: pb::TaskState, eta: f64, ran: f64) -> TaskClock {
        TaskClock {
            stage: stage as i32,
            state: state as i32,
            eta_seconds: eta,
            ran_seconds: ran,
        }
    }

    fn job(times: &[(pb::Stage, i64, i64)]) -> pb::Job {
        pb::Job {
            id: "j-before".into(),
            tasks: times
                .iter()
                .map(|&(stage, started, finished)| pb::Task {
                    stage: stage as i32,
                    started_at_ms: started,
                    finished_at_ms: finished,
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn the_job_eta_adds_the_running_stage_s_eta_to_the_earlier_times_of_the_rest() {
        use pb::{Stage as S, TaskState as T};
        let before = StageTimes::of(&job(&[
            (S::NerfPretrain, 1_000, 61_000),
            (S::RenderViews, 61_000, 71_000),
            (S::DecoderPretrain, 71_000, 101_000),
            // A second render of the earlier job does not replace its first.
            (S::RenderViews, 200_000, 900_000),
        ]));
        assert_eq!(before.seconds[&(S::NerfPretrain as i32)], 60.0);
        assert_eq!(before.seconds[&(S::RenderViews as i32)], 10.0);
        let tasks = [
            clock(S::NerfPretrain, T::Succeeded, 0.0, 0.0),
            clock(S::RenderViews, T::Leased, 4.0, 6.0),
            clock(S::DecoderPretrain, T::Pending, 0.0, 0.0),
        ];
        assert_eq!(job_eta(&tasks, &before), Some(4.0 + 30.0));
        // Before its first progress a running stage counts its earlier time less what it ran,
        // and never less than nothing.
        let early = [clock(S::RenderViews, T::Leased, 0.0, 6.0)];
        assert_eq!(job_eta(&early, &before), Some(4.0));
        let late = [clock(S::RenderViews, T::Leased, 0.0, 60.0)];
        assert_eq!(job_eta(&late, &before), Some(0.0));
        // A stage to come that the earlier job has no time for: no ETA at all.
        let unknown = [clock(S::MutualLearning, T::Ready, 0.0, 0.0)];
        assert_eq!(job_eta(&unknown, &before), None);
    }
}
