//! The commands' outputs, written all or nothing through [`drape_io`] (staged in a
//! hidden sibling, renamed into place when everything is written), with the refusals
//! and errors named after the option that gave the path. A directory output replaces
//! the whole of an earlier one (no stale frames), but only one drape wrote: it holds
//! the [`MARKER`] file. Anything else there is refused, naming the option.

use std::path::Path;

use anyhow::Context as _;

/// The file that marks a directory as drape's output (what it may replace).
pub const MARKER: &str = ".drape-output";

/// A directory output being written (see the module header).
#[derive(Debug)]
pub struct StagedDir {
    inner: drape_io::StagedDir,
}

impl StagedDir {
    /// Starts the output `target` given by `option`. `target` must be missing, empty,
    /// an earlier drape output, or (`owned`) a directory drape itself chose inside a run.
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
        let inner = drape_io::StagedDir::new(target)
            .with_context(|| format!("{option} {}", target.display()))?;
        Ok(Self { inner })
    }

    /// Where to write.
    pub fn path(&self) -> &Path {
        self.inner.path()
    }

    /// The directory the output will have once committed.
    pub fn target(&self) -> &Path {
        self.inner.target()
    }

    /// Marks the output as drape's and moves it into place, replacing an earlier one
    /// whole.
    pub fn commit(self) -> anyhow::Result<()> {
        let marker = self.inner.path().join(MARKER);
        drape_io::write(
            &marker,
            "written by drape; a rerun of the command may replace this directory\n",
        )
        .with_context(|| format!("{}: cannot write", marker.display()))?;
        self.inner.commit()?;
        Ok(())
    }
}

/// A file output being written (see the module header): the writer gets
/// [`StagedFile::path`], a hidden sibling with the same extension, and any
/// [`companion`](Self::companion) files, all moved into place by
/// [`commit`](Self::commit).
#[derive(Debug)]
pub struct StagedFile {
    inner: drape_io::StagedFile,
    option: String,
}

impl StagedFile {
    /// Starts the output file `target`, given by `option`; a directory there is refused.
    pub fn new(target: &Path, option: &str) -> anyhow::Result<Self> {
        let inner = drape_io::StagedFile::new(target).with_context(|| option.to_string())?;
        Ok(Self {
            inner,
            option: option.to_string(),
        })
    }

    /// Where to write.
    pub fn path(&self) -> &Path {
        self.inner.path()
    }

    /// A file committed with this one, named with `suffix` before the extension
    /// (`x.depth.exr` for `x.exr` and ".depth"): returns the staged path to write.
    pub fn companion(&mut self, suffix: &str) -> anyhow::Result<std::path::PathBuf> {
        let option = &self.option;
        let target = self.inner.target().display().to_string();
        self.inner
            .companion(suffix)
            .with_context(|| format!("{option} {target}: its companion file"))
    }

    /// Moves the finished file and its companions into place.
    pub fn commit(self) -> anyhow::Result<()> {
        self.inner.commit()?;
        Ok(())
    }
}
