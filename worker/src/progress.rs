//! The latest progress of a running task, fed by the engine's progress reports and read by the
//! heartbeat loop: step, total, loss, metrics (PSNR…), an ETA from the step rate of this run,
//! and a status line (`downloading inputs`, `step 40/150, resumed from step 20`, …).

use std::sync::Mutex;
use std::time::Instant;

use stylenerf_engine::stages::Progress;
use stylenerf_proto::v1 as pb;

/// Shared progress of one task.
#[derive(Debug)]
pub struct ProgressTracker {
    state: Mutex<State>,
}

#[derive(Debug)]
struct State {
    stage: &'static str,
    progress: pb::Progress,
    /// The first report of this run: (step, when), for the step rate.
    first: Option<(u64, Instant)>,
    resumed_from: u64,
}

impl ProgressTracker {
    pub fn new(stage: &'static str) -> Self {
        Self {
            state: Mutex::new(State {
                stage,
                progress: pb::Progress {
                    eta_seconds: -1.0,
                    message: format!("{stage}: starting"),
                    ..Default::default()
                },
                first: None,
                resumed_from: 0,
            }),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Sets the status line (before the stage reports steps: downloads, restores…).
    pub fn set_message(&self, message: impl Into<String>) {
        self.lock().progress.message = message.into();
    }

    /// Records the checkpoint step the stage resumes from.
    pub fn set_resumed_from(&self, step: u64) {
        let mut s = self.lock();
        s.resumed_from = step;
        s.progress.step = step;
        s.progress
            .metrics
            .insert("resumed_from".into(), step as f64);
        s.progress.message = format!("{}: resuming from checkpoint step {step}", s.stage);
    }

    /// Takes an engine progress report.
    pub fn update(&self, p: &Progress) {
        let mut s = self.lock();
        let now = Instant::now();
        let (first_step, first_at) = *s.first.get_or_insert((p.step, now));
        let resumed_from = s.resumed_from.max(p.resumed_from);
        s.resumed_from = resumed_from;
        let elapsed = now.duration_since(first_at).as_secs_f64();
        let eta = if p.total > 0 && p.step > first_step && elapsed > 0.0 {
            let rate = (p.step - first_step) as f64 / elapsed;
            p.total.saturating_sub(p.step) as f64 / rate
        } else {
            -1.0
        };
        let mut metrics: std::collections::HashMap<String, f64> =
            p.metrics.iter().map(|(k, v)| (k.clone(), *v)).collect();
        let mut message = format!("{}: step {}/{}", s.stage, p.step, p.total);
        if resumed_from > 0 {
            metrics.insert("resumed_from".into(), resumed_from as f64);
            message.push_str(&format!(", resumed from step {resumed_from}"));
        }
        s.progress = pb::Progress {
            step: p.step,
            total: p.total,
            loss: p.loss.unwrap_or(0.0),
            metrics,
            eta_seconds: eta,
            message,
        };
    }

    /// The progress to send with the next heartbeat.
    pub fn snapshot(&self) -> pb::Progress {
        self.lock().progress.clone()
    }

    /// The step the stage resumed from (0 for a fresh start).
    pub fn resumed_from(&self) -> u64 {
        self.lock().resumed_from
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_resume_step_loss_and_eta() {
        let t = ProgressTracker::new("nerf_pretrain");
        t.set_resumed_from(20);
        assert!(t
            .snapshot()
            .message
            .contains("resuming from checkpoint step 20"));
        let mut p = Progress {
            stage: "nerf_pretrain".into(),
            step: 30,
            total: 100,
            loss: Some(0.25),
            ..Default::default()
        };
        p.metrics.insert("psnr".into(), 6.0);
        t.update(&p);
        assert!(t.snapshot().eta_seconds < 0.0, "no rate after one report");
        std::thread::sleep(std::time::Duration::from_millis(20));
        p.step = 40;
        t.update(&p);
        let s = t.snapshot();
        assert_eq!((s.step, s.total, s.loss), (40, 100, 0.25));
        assert!(s.eta_seconds > 0.0);
        assert_eq!(s.metrics["psnr"], 6.0);
        assert_eq!(s.metrics["resumed_from"], 20.0);
        assert!(
            s.message.contains("step 40/100, resumed from step 20"),
            "{}",
            s.message
        );
    }
}
