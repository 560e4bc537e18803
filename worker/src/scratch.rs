//! The worker's scratch folders: `<root>/<worker id>/`, held with an exclusive lock on its
//! `.lock` file for as long as the worker runs. A worker that was killed leaves its folder
//! behind unlocked (the OS drops the lock with the process), so each worker that starts
//! removes the unlocked folders it finds under the same root: killed workers' scratch space is
//! reclaimed without touching that of workers still running.

use std::fs::{File, TryLockError};
use std::path::{Path, PathBuf};

const LOCK: &str = ".lock";

/// A scratch folder owned by this process while the value lives.
#[derive(Debug)]
pub struct ScratchDir {
    path: PathBuf,
    _lock: File,
}

impl ScratchDir {
    /// Creates and locks `<root>/<name>/`, then removes the unlocked folders of other workers
    /// under `root`.
    pub fn claim(root: &Path, name: &str) -> std::io::Result<ScratchDir> {
        let path = root.join(name);
        std::fs::create_dir_all(&path)?;
        let lock = File::create(path.join(LOCK))?;
        lock.try_lock().map_err(|e| match e {
            TryLockError::WouldBlock => std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                format!("{} is in use by another worker process", path.display()),
            ),
            TryLockError::Error(e) => e,
        })?;
        reclaim(root, &path);
        Ok(ScratchDir { path, _lock: lock })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Removes the folders under `root` (other than `mine`) whose `.lock` no process holds.
fn reclaim(root: &Path, mine: &Path) {
    let Ok(entries) = std::fs::read_dir(root) else {
        return;
    };
    for entry in entries.flatten() {
        let dir = entry.path();
        if dir == mine || !dir.join(LOCK).is_file() {
            continue;
        }
        let Ok(lock) = File::open(dir.join(LOCK)) else {
            continue;
        };
        if lock.try_lock().is_ok() {
            match std::fs::remove_dir_all(&dir) {
                Ok(()) => {
                    tracing::info!(dir = %dir.display(), "removed a stopped worker's scratch folder")
                }
                Err(error) => {
                    tracing::warn!(dir = %dir.display(), %error, "cannot remove a stopped worker's scratch folder")
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stopped_workers_folders_are_reclaimed_and_live_ones_kept() {
        let root = tempfile::tempdir().unwrap();
        let live = ScratchDir::claim(root.path(), "w-live").unwrap();
        std::fs::write(live.path().join("task.bin"), b"in use").unwrap();
        // A killed worker: its folder and lock file remain, nobody holds the lock.
        let dead = root.path().join("w-dead");
        std::fs::create_dir_all(dead.join("task-7")).unwrap();
        std::fs::write(dead.join(LOCK), b"").unwrap();
        // Something else in the root that is not a worker's folder.
        std::fs::create_dir_all(root.path().join("notes")).unwrap();

        let again = ScratchDir::claim(root.path(), "w-live");
        assert!(again.is_err(), "a folder is claimed once");
        let new = ScratchDir::claim(root.path(), "w-new").unwrap();
        assert!(!dead.exists(), "the killed worker's folder is reclaimed");
        assert!(live.path().join("task.bin").exists());
        assert!(root.path().join("notes").exists());
        drop(live);
        drop(new);
    }
}
