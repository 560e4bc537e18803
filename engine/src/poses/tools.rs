//! The external programs the poses step runs (COLMAP, ffmpeg): finding them, and running one
//! step with its output in a log file, cancellable, failing with the step's name and the end of
//! its log.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use crate::stages::StageControl;
use crate::{EngineError, Result};

/// An external program: its name in messages, and the command that starts it.
#[derive(Debug, Clone)]
pub struct Tool {
    pub name: &'static str,
    pub program: PathBuf,
}

/// The stages' programs installed here, by their catalogue names (`colmap`, `ffmpeg`), each
/// with where it is or why it is missing: what a worker advertises and logs at start.
pub fn installed() -> Vec<(&'static str, Result<Tool>)> {
    vec![
        (stylenerf_plan::stage::COLMAP, Tool::colmap()),
        (stylenerf_plan::stage::FFMPEG, Tool::ffmpeg()),
    ]
}

impl Tool {
    /// COLMAP: `$STYLENERF_COLMAP`, else `colmap` on the `PATH`.
    pub fn colmap() -> Result<Self> {
        Self::find("colmap", "STYLENERF_COLMAP", "colmap")
    }

    /// ffmpeg: `$STYLENERF_FFMPEG`, else `ffmpeg` on the `PATH`.
    pub fn ffmpeg() -> Result<Self> {
        Self::find("ffmpeg", "STYLENERF_FFMPEG", "ffmpeg")
    }

    fn find(name: &'static str, env: &str, package: &str) -> Result<Self> {
        let program = match std::env::var_os(env) {
            Some(p) => {
                let p = PathBuf::from(p);
                if !is_executable(&p) {
                    return Err(tool_error(
                        name,
                        format!("{env}={} is not an executable file", p.display()),
                    ));
                }
                p
            }
            None => search_path(name).ok_or_else(|| {
                tool_error(
                    name,
                    format!(
                        "not installed: `{name}` is not on the PATH; install it from the OS \
                         packages (Debian/Ubuntu: apt-get install {package}) or point {env} at it"
                    ),
                )
            })?,
        };
        Ok(Self { name, program })
    }

    /// Runs `self args…` as the step `step`, its stdout and stderr appended to `log`. Polls
    /// `control` and kills the program when the stage is cancelled.
    pub fn run(
        &self,
        step: &str,
        args: &[String],
        log: &Path,
        control: &StageControl,
    ) -> Result<()> {
        use std::io::Write;
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .map_err(|e| EngineError::io(log, e))?;
        writeln!(file, "\n$ {} {}", self.program.display(), args.join(" "))
            .map_err(|e| EngineError::io(log, e))?;
        let err_file = file.try_clone().map_err(|e| EngineError::io(log, e))?;
        tracing::info!(
            tool = self.name,
            step,
            "running {}",
            args.first().map_or("", |a| a)
        );
        let mut child = Command::new(&self.program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(file)
            .stderr(err_file)
            .spawn()
            .map_err(|e| tool_error(self.name, format!("{step}: cannot start: {e}")))?;
        let status = loop {
            if control.is_cancelled() {
                let _ = child.kill();
                let _ = child.wait();
                return Err(EngineError::Cancelled);
            }
            match child.try_wait() {
                Ok(Some(status)) => break status,
                Ok(None) => std::thread::sleep(Duration::from_millis(100)),
                Err(e) => return Err(tool_error(self.name, format!("{step}: {e}"))),
            }
        };
        if status.success() {
            Ok(())
        } else {
            Err(tool_error(
                self.name,
                format!(
                    "{step} failed ({status}); the end of its log {}:\n{}",
                    log.display(),
                    log_tail(log, 12)
                ),
            ))
        }
    }
}

fn tool_error(tool: &str, reason: String) -> EngineError {
    EngineError::Tool {
        tool: tool.to_string(),
        reason,
    }
}

fn is_executable(path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        path.metadata()
            .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
    }
    #[cfg(not(unix))]
    {
        path.is_file()
    }
}

fn search_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(name))
        .find(|p| is_executable(p))
}

/// The last `lines` lines of a log file (empty when it cannot be read).
pub(crate) fn log_tail(log: &Path, lines: usize) -> String {
    let mut text = String::new();
    if let Ok(mut f) = std::fs::File::open(log) {
        let _ = f.read_to_string(&mut text);
    }
    let all: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    all[all.len().saturating_sub(lines)..].join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shell() -> Tool {
        Tool {
            name: "sh",
            program: "/bin/sh".into(),
        }
    }

    #[test]
    fn a_missing_program_is_named_with_how_to_install_it() {
        let err = Tool::find("no-such-program-x", "STYLENERF_TEST_UNSET_VAR", "pkg").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("no-such-program-x"), "{msg}");
        assert!(msg.contains("apt-get install pkg"), "{msg}");
    }

    #[test]
    fn a_failing_step_reports_the_end_of_its_log() {
        let dir = tempfile::tempdir().unwrap();
        let sh = shell();
        let log = dir.path().join("log.txt");
        let args = [
            "-c".to_string(),
            "echo first; echo why it failed >&2; exit 3".into(),
        ];
        let err = sh
            .run("probe", &args, &log, &StageControl::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains("probe failed"), "{err}");
        assert!(err.contains("why it failed"), "{err}");
        let ok = ["-c".to_string(), "true".into()];
        sh.run("probe", &ok, &log, &StageControl::default())
            .unwrap();
    }

    #[test]
    fn a_cancelled_stage_kills_the_program() {
        let dir = tempfile::tempdir().unwrap();
        let sh = shell();
        let control = StageControl::default();
        let flag = control.cancel_flag();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(200));
            flag.store(true, std::sync::atomic::Ordering::Relaxed);
        });
        let start = std::time::Instant::now();
        let args = ["-c".to_string(), "sleep 30".into()];
        let err = sh.run("wait", &args, &dir.path().join("log"), &control);
        assert!(matches!(err, Err(EngineError::Cancelled)));
        assert!(start.elapsed() < Duration::from_secs(10));
    }
}
