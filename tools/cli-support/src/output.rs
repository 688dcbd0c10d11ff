//! Outputs written all or nothing. A command writes into a hidden sibling of its
//! output (`.NAME.partial-PID`, on the same file system) and renames it into place
//! when everything is written; dropped without [`StagedDir::commit`] (an error, a
//! panic), the sibling is removed, so a failure leaves nothing new and an earlier
//! output intact. A directory output replaces the whole of an earlier one (no stale
//! frames), but only one drape wrote: it holds the [`MARKER`] file. Anything else
//! there is refused, naming the option.

use std::path::{Path, PathBuf};

use anyhow::Context as _;

/// The file that marks a directory as drape's output (what it may replace).
pub const MARKER: &str = ".drape-output";

fn sibling(target: &Path, tag: &str) -> anyhow::Result<PathBuf> {
    let name = target
        .file_name()
        .with_context(|| format!("{}: not a file or directory name", target.display()))?;
    let parent = target
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = name.to_string_lossy();
    // The extension stays last: writers choose the format by it.
    Ok(match name.rsplit_once('.') {
        Some((stem, ext)) if !stem.is_empty() && tag == "partial" => {
            parent.join(format!(".{stem}.{tag}-{}.{ext}", std::process::id()))
        }
        _ => parent.join(format!(".{name}.{tag}-{}", std::process::id())),
    })
}

/// Creates the missing ancestors of `path`, returning the topmost it created (to be
/// removed again if the output is abandoned).
fn create_parents(path: &Path) -> anyhow::Result<Option<PathBuf>> {
    let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) else {
        return Ok(None);
    };
    let mut top = None;
    let mut p = parent;
    while !p.exists() {
        top = Some(p.to_path_buf());
        match p.parent().filter(|q| !q.as_os_str().is_empty()) {
            Some(q) => p = q,
            None => break,
        }
    }
    if !parent.is_dir() && parent.exists() {
        anyhow::bail!("{}: is not a directory", parent.display());
    }
    std::fs::create_dir_all(parent)
        .with_context(|| format!("{}: cannot create", parent.display()))?;
    Ok(top)
}

/// A directory output being written (see the module header).
#[derive(Debug)]
pub struct StagedDir {
    target: PathBuf,
    staging: PathBuf,
    created_parent: Option<PathBuf>,
    committed: bool,
}

impl StagedDir {
    /// Starts the output `target` of `command`, given by `option`. `target` must be
    /// missing, empty, an earlier drape output, or (`owned`) a directory drape itself
    /// chose inside a run.
    pub fn new(target: &Path, option: &str, owned: bool) -> anyhow::Result<Self> {
        if target.exists() {
            anyhow::ensure!(
                target.is_dir(),
                "{option} {}: exists and is not a directory",
                target.display()
            );
            let empty = std::fs::read_dir(target)
                .with_context(|| format!("{option} {}: cannot read", target.display()))?
                .next()
                .is_none();
            anyhow::ensure!(
                empty || owned || target.join(MARKER).is_file(),
                "{option} {}: exists, is not empty and is no earlier drape output (it has no {MARKER}); choose another directory",
                target.display()
            );
        }
        let created_parent = create_parents(target).with_context(|| option.to_string())?;
        let staging = sibling(target, "partial")?;
        let _ = std::fs::remove_dir_all(&staging);
        std::fs::create_dir(&staging).with_context(|| {
            format!(
                "{option} {}: cannot create {}",
                target.display(),
                staging.display()
            )
        })?;
        Ok(Self {
            target: target.to_path_buf(),
            staging,
            created_parent,
            committed: false,
        })
    }

    /// Where to write.
    pub fn path(&self) -> &Path {
        &self.staging
    }

    /// The directory the output will have once committed.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Moves the finished output into place, replacing an earlier one whole.
    pub fn commit(mut self) -> anyhow::Result<()> {
        std::fs::write(
            self.staging.join(MARKER),
            "written by drape; a rerun of the command may replace this directory\n",
        )
        .with_context(|| format!("{}: cannot write", self.staging.display()))?;
        let old = sibling(&self.target, "replaced")?;
        let had = self.target.exists();
        if had {
            std::fs::rename(&self.target, &old).with_context(|| {
                format!(
                    "{}: cannot move the earlier output aside",
                    self.target.display()
                )
            })?;
        }
        if let Err(e) = std::fs::rename(&self.staging, &self.target) {
            if had {
                let _ = std::fs::rename(&old, &self.target);
            }
            return Err(e).with_context(|| {
                format!(
                    "{}: cannot move the new output into place",
                    self.target.display()
                )
            });
        }
        self.committed = true;
        if had {
            let _ = std::fs::remove_dir_all(&old);
        }
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.staging);
            if let Some(p) = &self.created_parent {
                let _ = std::fs::remove_dir_all(p);
            }
        }
    }
}

/// A file output being written (see the module header): the writer gets
/// [`StagedFile::path`], a hidden sibling with the same extension.
#[derive(Debug)]
pub struct StagedFile {
    target: PathBuf,
    staging: PathBuf,
    created_parent: Option<PathBuf>,
    committed: bool,
}

impl StagedFile {
    /// Starts the output file `target`, given by `option`; a directory there is refused.
    pub fn new(target: &Path, option: &str) -> anyhow::Result<Self> {
        anyhow::ensure!(
            !target.is_dir(),
            "{option} {}: is a directory",
            target.display()
        );
        let created_parent = create_parents(target).with_context(|| option.to_string())?;
        let staging = sibling(target, "partial")?;
        Ok(Self {
            target: target.to_path_buf(),
            staging,
            created_parent,
            committed: false,
        })
    }

    /// Where to write.
    pub fn path(&self) -> &Path {
        &self.staging
    }

    /// A companion file the writer derived from [`Self::path`] (e.g. `x.depth.exr` for
    /// `x.exr`), committed with it: returns (staged, final).
    pub fn companion(&self, suffix_before_ext: &str) -> (PathBuf, PathBuf) {
        let with = |p: &Path| {
            let stem = p
                .file_stem()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            let ext = p
                .extension()
                .map(|e| format!(".{}", e.to_string_lossy()))
                .unwrap_or_default();
            p.with_file_name(format!("{stem}{suffix_before_ext}{ext}"))
        };
        (with(&self.staging), with(&self.target))
    }

    /// Renames the finished file over the target.
    pub fn commit(mut self) -> anyhow::Result<()> {
        std::fs::rename(&self.staging, &self.target).with_context(|| {
            format!(
                "{}: cannot move the new file into place",
                self.target.display()
            )
        })?;
        self.committed = true;
        Ok(())
    }
}

impl Drop for StagedFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.staging);
            if let Some(p) = &self.created_parent {
                let _ = std::fs::remove_dir_all(p);
            }
        }
    }
}
