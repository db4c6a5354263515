//! A run's output folder, written as one transaction, so that a folder never holds two runs'
//! files and a killed run never destroys the previous one.
//!
//! [`OutputFolder::begin`] checks the target before any work: it may be new, empty, or a
//! folder that holds nothing but outputs of ours (replaced only with `force`); a folder that
//! holds anything else is refused, so no user file is ever deleted; the folder must also
//! hold [`OUTPUT_MARKER`], which every output folder gets, as names alone prove nothing.
//! Files are then written
//! into a fresh hidden sibling, `.<name>.deepmorph-<pid>`, whose creation is the proof that
//! the target can be written (before hours of solving, not after). [`OutputFolder::commit`]
//! moves it into place: on Linux one atomic exchange (`renameat2(RENAME_EXCHANGE)`), after
//! which the old contents are deleted; elsewhere two renames. A run that fails or is dropped
//! removes its staging folder; one that is killed (SIGKILL, power loss) leaves it, and the
//! next run into the same parent removes the staging folders of processes that no longer
//! exist.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// A staging folder to write into, and the target it becomes on [`OutputFolder::commit`].
#[derive(Debug)]
pub struct OutputFolder {
    target: PathBuf,
    staging: PathBuf,
    committed: bool,
}

/// What marks a staging folder of ours: `.<target name>` + this + the process id.
const STAGING_TAG: &str = ".deepmorph-";
/// What marks a previous output moved aside while two plain renames replace it.
const ASIDE_TAG: &str = "old-";
/// The file every output folder of this program holds: a folder without it is never taken
/// for a previous output, whatever its file names (issue 43 #15: a user's own `a.png` and
/// `config.json` were replaced by `--force`).
pub const OUTPUT_MARKER: &str = ".deepmorph-output";

impl OutputFolder {
    /// Checks `target` and creates the staging folder beside it.
    ///
    /// `owned` says which file names this program writes into such a folder (a file in a
    /// subfolder as `sub/name`: a subfolder is ours when `owned("sub/")` holds and every file
    /// in it is owned, one level deep); `force` allows replacing a non-empty folder that
    /// holds only such files.
    ///
    /// # Errors
    ///
    /// [`Error::OutputFolder`] if `target` is not a folder, holds files this program did not
    /// write, holds a previous output and `force` is off; [`Error::Overwrite`] if an input lies
    /// inside it; [`Error::Io`] if the staging folder cannot be created or written.
    pub fn begin(
        target: &Path,
        inputs: &[&Path],
        owned: impl Fn(&str) -> bool,
        force: bool,
    ) -> Result<Self> {
        let refuse = |detail: String| Error::OutputFolder {
            path: target.to_path_buf(),
            detail,
        };
        let io_error = |path: &Path| {
            let path = path.to_path_buf();
            move |cause| Error::Io { path, cause }
        };
        let absolute = std::path::absolute(target).map_err(io_error(target))?;
        let name = absolute
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .ok_or_else(|| refuse("names no folder (a root or `..`)".into()))?;
        let parent = absolute.parent().unwrap_or(Path::new("/")).to_path_buf();
        let unwritable = |cause: std::io::Error| {
            refuse(format!("cannot be written: {cause} ({})", parent.display()))
        };
        std::fs::create_dir_all(&parent).map_err(unwritable)?;
        let parent = parent.canonicalize().map_err(unwritable)?;
        // The staging folder's name is the target's with a dot, a tag and the process id.
        let longest = 255 - 1 - STAGING_TAG.len() - ASIDE_TAG.len() - 10;
        if name.len() > longest {
            return Err(refuse(format!(
                "has a last component of {} bytes: at most {longest} (the hidden staging \
                 folder beside it adds {} to the name)",
                name.len(),
                255 - longest
            )));
        }
        let target_path = parent.join(&name);
        if let Ok(meta) = std::fs::symlink_metadata(&target_path) {
            if meta.file_type().is_symlink() {
                let to = std::fs::read_link(&target_path).unwrap_or_default();
                return Err(refuse(format!(
                    "is a symbolic link (to {}): the output folder is replaced whole, so give \
                     the folder itself or a new one",
                    to.display()
                )));
            }
            if !meta.is_dir() {
                return Err(refuse("exists and is not a folder".into()));
            }
            for input in inputs {
                if let Ok(input) = input.canonicalize()
                    && input.starts_with(&target_path)
                {
                    return Err(Error::Overwrite {
                        output: target.to_path_buf(),
                        input: input.clone(),
                    });
                }
            }
            let mut foreign = Vec::new();
            let mut entries = 0;
            let mut marked = false;
            for entry in std::fs::read_dir(&target_path).map_err(io_error(&target_path))? {
                let entry = entry.map_err(io_error(&target_path))?;
                let file_name = entry.file_name().to_string_lossy().into_owned();
                let kind = entry.file_type().ok();
                if file_name == OUTPUT_MARKER && kind.is_some_and(|t| t.is_file()) {
                    marked = true;
                    continue;
                }
                let ours = match kind {
                    Some(t) if t.is_file() => owned(&file_name),
                    Some(t) if t.is_dir() => {
                        owned(&format!("{file_name}/"))
                            && owned_subfolder(&entry.path(), &file_name, &owned)
                    }
                    _ => false,
                };
                if !ours {
                    foreign.push(file_name);
                }
                entries += 1;
            }
            if !foreign.is_empty() {
                foreign.sort();
                let shown = foreign
                    .iter()
                    .take(3)
                    .cloned()
                    .collect::<Vec<_>>()
                    .join(", ");
                let more = foreign.len().saturating_sub(3);
                return Err(refuse(format!(
                    "holds files that deepmorph does not write ({shown}{}); choose a new or \
                     empty folder",
                    if more > 0 {
                        format!(" and {more} more")
                    } else {
                        String::new()
                    }
                )));
            }
            if entries > 0 && !marked {
                return Err(refuse(format!(
                    "holds files named like deepmorph's outputs but not its {OUTPUT_MARKER} \
                     file, so they are not known to be a previous output (they may be yours, \
                     or from a version before the marker); choose a new or empty folder"
                )));
            }
            if entries > 0 && !force {
                return Err(refuse(
                    "holds a previous output: pass --force to replace it (it stays intact \
                     until the new one is complete) or choose another -o"
                        .into(),
                ));
            }
        }
        // Finding no other live writer and creating ours is one step under a lock on the
        // parent: two runs into one target cannot both pass (issue 43 #1: both wrote, the
        // last one's result silently replaced the first's). The lock is held for
        // milliseconds; the live staging folder is what keeps a second run out.
        let lock = ParentLock::take(&parent);
        if let Some(pid) = remove_stale(&parent, &name) {
            return Err(refuse(format!(
                "is being written by another deepmorph run (process {pid}): wait for it to \
                 finish or choose another -o"
            )));
        }
        let staging = parent.join(format!(".{name}{STAGING_TAG}{}", std::process::id()));
        if staging.exists() {
            std::fs::remove_dir_all(&staging).map_err(io_error(&staging))?;
        }
        std::fs::create_dir(&staging).map_err(unwritable)?;
        drop(lock);
        let folder = Self {
            target: target_path,
            staging,
            committed: false,
        };
        // Creating a folder can succeed where writing into it cannot (quotas, odd mounts):
        // the marker is the first file written.
        mark_as_output(&folder.staging).map_err(|e| match e {
            Error::Io { cause, .. } => unwritable(cause),
            other => other,
        })?;
        Ok(folder)
    }

    /// The folder to write the outputs into (the staging folder until
    /// [`OutputFolder::commit`]).
    pub fn path(&self) -> &Path {
        &self.staging
    }

    /// Moves the staging folder into place, replacing a previous output; returns the target.
    ///
    /// # Errors
    ///
    /// [`Error::Io`] if a rename fails; the staging folder is then kept (its path is in the
    /// message) and the previous output is untouched or, between two plain renames, back in
    /// place.
    pub fn commit(mut self) -> Result<PathBuf> {
        let io_error = |path: &Path| {
            let path = path.to_path_buf();
            move |cause| Error::Io { path, cause }
        };
        if std::fs::symlink_metadata(&self.target).is_ok() {
            if exchange(&self.staging, &self.target).is_ok() {
                // The staging path now holds the previous output.
                let _ = std::fs::remove_dir_all(&self.staging);
            } else {
                let aside = self.aside();
                std::fs::rename(&self.target, &aside).map_err(io_error(&self.target))?;
                if let Err(cause) = std::fs::rename(&self.staging, &self.target) {
                    let _ = std::fs::rename(&aside, &self.target);
                    self.committed = true; // keep the staging folder: it holds this run
                    return Err(Error::Io {
                        path: self.staging.clone(),
                        cause,
                    });
                }
                let _ = std::fs::remove_dir_all(&aside);
            }
        } else {
            std::fs::rename(&self.staging, &self.target).map_err(io_error(&self.staging))?;
        }
        self.committed = true;
        Ok(self.target.clone())
    }

    fn aside(&self) -> PathBuf {
        let name = self
            .target
            .file_name()
            .unwrap_or_default()
            .to_string_lossy();
        self.target.with_file_name(format!(
            ".{name}{STAGING_TAG}{ASIDE_TAG}{}",
            std::process::id()
        ))
    }
}

impl Drop for OutputFolder {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.staging);
        }
    }
}

/// Whether every entry of the subfolder `dir` (named `name`) is a file that `owned` accepts
/// as `name/file`, or its own [`OUTPUT_MARKER`] (a chain's segment folders are outputs of
/// their own, which `--resume` may replace).
fn owned_subfolder(dir: &Path, name: &str, owned: &impl Fn(&str) -> bool) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    entries.into_iter().all(|entry| {
        entry.is_ok_and(|e| {
            let file = e.file_name().to_string_lossy().into_owned();
            e.file_type().is_ok_and(|t| t.is_file())
                && (file == OUTPUT_MARKER || owned(&format!("{name}/{file}")))
        })
    })
}

/// Marks `dir` as an output folder of this program (what [`OutputFolder::begin`] does for
/// the folders it creates; a chain's segment folders get it this way).
///
/// # Errors
///
/// [`Error::Io`] if the marker cannot be written.
pub fn mark_as_output(dir: &Path) -> Result<()> {
    let marker = format!("written by deepmorph {}\n", env!("CARGO_PKG_VERSION"));
    std::fs::write(dir.join(OUTPUT_MARKER), marker).map_err(|cause| Error::Io {
        path: dir.join(OUTPUT_MARKER),
        cause,
    })
}

/// Removes the staging folders in `parent` left by processes that no longer run, whatever
/// target they were for (issue 43 #16: only the same target's were cleaned), and puts back
/// a previous output that a killed run had moved aside (`name`'s first: its run is about to
/// look at it). Returns the process id of another live run staging `name`, if any: only
/// where liveness can be known (Linux); elsewhere a killed run's folder would lock the
/// target for good.
fn remove_stale(parent: &Path, name: &str) -> Option<u32> {
    let entries = std::fs::read_dir(parent).ok()?;
    let mut stale: Vec<(String, bool, PathBuf)> = Vec::new();
    let mut live = None;
    for entry in entries.flatten() {
        let file_name = entry.file_name().to_string_lossy().into_owned();
        let Some((target, rest)) = file_name
            .strip_prefix('.')
            .and_then(|n| n.rsplit_once(STAGING_TAG))
        else {
            continue;
        };
        let (aside, pid) = match rest.strip_prefix(ASIDE_TAG) {
            Some(pid) => (true, pid),
            None => (false, rest),
        };
        let Ok(pid) = pid.parse::<u32>() else {
            continue;
        };
        if target.is_empty() || pid == std::process::id() {
            continue;
        }
        if process_runs(pid) {
            if target == name && !aside && cfg!(target_os = "linux") {
                live = Some(pid);
            }
            continue;
        }
        stale.push((target.to_string(), aside, entry.path()));
    }
    stale.sort_by_key(|(target, _, _)| target != name);
    for (target, aside, path) in stale {
        let target = parent.join(target);
        if aside && !target.exists() {
            let _ = std::fs::rename(&path, &target);
        } else {
            let _ = std::fs::remove_dir_all(&path);
        }
    }
    live
}

/// An exclusive `flock` on a folder, released on drop; nothing where the file system does
/// not lock (the check it guards then runs unguarded, as it did before).
struct ParentLock {
    /// Held only to be closed on drop, which releases the lock.
    _file: Option<std::fs::File>,
}

impl ParentLock {
    #[cfg(target_os = "linux")]
    fn take(dir: &Path) -> Self {
        use rustix::fs::{FlockOperation, flock};
        let file = std::fs::File::open(dir).ok();
        Self {
            _file: file.filter(|f| flock(f, FlockOperation::LockExclusive).is_ok()),
        }
    }

    #[cfg(not(target_os = "linux"))]
    fn take(_: &Path) -> Self {
        Self { _file: None }
    }
}

/// Whether process `pid` exists. Where that cannot be known it is assumed to run, so that
/// nothing of a live run is ever removed.
fn process_runs(pid: u32) -> bool {
    if cfg!(target_os = "linux") {
        Path::new("/proc").join(pid.to_string()).exists()
    } else {
        true
    }
}

/// Swaps two paths atomically.
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> std::io::Result<()> {
    use rustix::fs::{CWD, RenameFlags, renameat_with};
    renameat_with(CWD, a, CWD, b, RenameFlags::EXCHANGE).map_err(std::io::Error::from)
}

#[cfg(not(target_os = "linux"))]
fn exchange(_: &Path, _: &Path) -> std::io::Result<()> {
    Err(std::io::ErrorKind::Unsupported.into())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "deepmorph-output-folder-{name}-{}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn ours(name: &str) -> bool {
        name.ends_with(".out")
    }

    fn listing(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn a_new_folder_appears_only_on_commit() {
        let dir = scratch("new");
        let target = dir.join("run");
        let folder = OutputFolder::begin(&target, &[], ours, false).unwrap();
        std::fs::write(folder.path().join("a.out"), b"1").unwrap();
        assert!(!target.exists());
        assert_eq!(folder.commit().unwrap(), target);
        assert_eq!(listing(&dir), ["run"]);
        assert_eq!(listing(&target), [OUTPUT_MARKER, "a.out"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_previous_output_is_replaced_whole_and_only_with_force() {
        let dir = scratch("replace");
        let target = dir.join("run");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("old.out"), b"old").unwrap();
        std::fs::write(target.join("stale.out"), b"old").unwrap();
        // Our names without our marker: never replaced.
        let err = OutputFolder::begin(&target, &[], ours, true).unwrap_err();
        assert!(err.to_string().contains(OUTPUT_MARKER), "{err}");
        std::fs::write(target.join(OUTPUT_MARKER), b"").unwrap();
        let err = OutputFolder::begin(&target, &[], ours, false).unwrap_err();
        assert!(err.to_string().contains("--force"), "{err}");
        let folder = OutputFolder::begin(&target, &[], ours, true).unwrap();
        std::fs::write(folder.path().join("new.out"), b"new").unwrap();
        // Dropped without commit (a failed run): the previous output is untouched.
        drop(folder);
        assert_eq!(listing(&dir), ["run"]);
        assert_eq!(listing(&target), [OUTPUT_MARKER, "old.out", "stale.out"]);
        let folder = OutputFolder::begin(&target, &[], ours, true).unwrap();
        std::fs::write(folder.path().join("new.out"), b"new").unwrap();
        folder.commit().unwrap();
        assert_eq!(listing(&dir), ["run"]);
        assert_eq!(listing(&target), [OUTPUT_MARKER, "new.out"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn foreign_files_and_inputs_inside_are_refused_even_with_force() {
        let dir = scratch("foreign");
        let target = dir.join("run");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("a.out"), b"").unwrap();
        std::fs::write(target.join("thesis.tex"), b"precious").unwrap();
        let err = OutputFolder::begin(&target, &[], ours, true).unwrap_err();
        assert!(err.to_string().contains("thesis.tex"), "{err}");
        std::fs::remove_file(target.join("thesis.tex")).unwrap();
        let input = target.join("a.out");
        let err = OutputFolder::begin(&target, &[&input], ours, true).unwrap_err();
        assert!(matches!(err, Error::Overwrite { .. }), "{err}");
        let file = dir.join("file.out");
        std::fs::write(&file, b"").unwrap();
        let err = OutputFolder::begin(&file, &[], ours, true).unwrap_err();
        assert!(err.to_string().contains("not a folder"), "{err}");
        assert_eq!(listing(&dir), ["file.out", "run"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn staging_folders_of_dead_processes_are_removed() {
        let dir = scratch("stale");
        // No process has a pid this large (Linux's maximum is 2^22).
        let dead = dir.join(format!(".run{STAGING_TAG}4194305"));
        std::fs::create_dir(&dead).unwrap();
        std::fs::write(dead.join(".frame_00.png.tmp-4194305"), b"half").unwrap();
        // A previous output moved aside by a killed run comes back.
        let aside = dir.join(format!(".run{STAGING_TAG}{ASIDE_TAG}4194306"));
        std::fs::create_dir(&aside).unwrap();
        std::fs::write(aside.join("old.out"), b"old").unwrap();
        std::fs::write(aside.join(OUTPUT_MARKER), b"").unwrap();
        let folder = OutputFolder::begin(&dir.join("run"), &[], ours, true).unwrap();
        if cfg!(target_os = "linux") {
            assert!(!dead.exists());
            assert_eq!(listing(&dir.join("run")), [OUTPUT_MARKER, "old.out"]);
        }
        drop(folder);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
