//! Files written whole or not at all: every file drape writes goes through here.
//!
//! A writer writes into a hidden sibling of its output (`.NAME.partial-PID.EXT`, on
//! the same file system, so the final step is a rename) and renames it into place when
//! everything is written. A failure (an error, a panic, a kill) before that leaves the
//! earlier file, if any, intact and, once the staging is dropped, nothing new. The
//! extension stays last in the sibling's name because writers choose the format by it.
//!
//! - [`write`] and [`write_with`]: one file, from bytes or from a writer;
//! - [`StagedFile`]: a file (and its companions, such as an EXR's depth file) written
//!   by code that wants a path, committed together;
//! - [`StagedDir`]: a whole output directory, replacing an earlier one whole.
//!
//! `std::fs::write` and `std::fs::rename` are disallowed elsewhere in the workspace
//! (`clippy.toml`), so that no writer can leave half a file under its final name.
#![forbid(unsafe_code)]
// This crate is the one place the workspace's clippy.toml lets rename and write.
#![allow(clippy::disallowed_methods)]

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// The sibling of `target` that a write stages in (`tag` "partial") or that an
/// earlier output is moved aside to (`tag` "replaced").
fn sibling(target: &Path, tag: &str) -> io::Result<PathBuf> {
    let name = target.file_name().ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{}: not a file or directory name", target.display()),
        )
    })?;
    let parent = target
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = name.to_string_lossy();
    let pid = std::process::id();
    Ok(match name.rsplit_once('.') {
        Some((stem, ext)) if !stem.is_empty() && tag == "partial" => {
            parent.join(format!(".{stem}.{tag}-{pid}.{ext}"))
        }
        _ => parent.join(format!(".{name}.{tag}-{pid}")),
    })
}

/// Creates the missing ancestors of `path`, returning the topmost one it created (to
/// be removed again if the output is abandoned).
fn create_parents(path: &Path) -> io::Result<Option<PathBuf>> {
    let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) else {
        return Ok(None);
    };
    if parent.exists() && !parent.is_dir() {
        return Err(io::Error::new(
            io::ErrorKind::NotADirectory,
            format!("{}: is not a directory", parent.display()),
        ));
    }
    let mut top = None;
    let mut p = parent;
    while !p.exists() {
        top = Some(p.to_path_buf());
        match p.parent().filter(|q| !q.as_os_str().is_empty()) {
            Some(q) => p = q,
            None => break,
        }
    }
    fs::create_dir_all(parent)?;
    Ok(top)
}

/// Writes `contents` to `path` whole or not at all (see the module header): the
/// drop-in for `std::fs::write`. The parent directory must exist.
pub fn write(path: impl AsRef<Path>, contents: impl AsRef<[u8]>) -> io::Result<()> {
    let contents = contents.as_ref();
    write_with(path, |w| w.write_all(contents))
}

/// Writes `path` whole or not at all through a buffered writer that `fill` fills:
/// for writers that stream (images, arrays, meshes). The parent directory must exist;
/// an error from `fill` leaves nothing behind.
pub fn write_with<T>(
    path: impl AsRef<Path>,
    fill: impl FnOnce(&mut io::BufWriter<fs::File>) -> io::Result<T>,
) -> io::Result<T> {
    let path = path.as_ref();
    let mut staging = Staging(Some(sibling(path, "partial")?));
    let staged = staging.0.clone().unwrap_or_default();
    let mut writer = io::BufWriter::new(fs::File::create(&staged)?);
    let value = fill(&mut writer)?;
    let file = writer.into_inner().map_err(|e| e.into_error())?;
    file.sync_all()?;
    drop(file);
    fs::rename(&staged, path)?;
    staging.0 = None;
    Ok(value)
}

/// A staged path removed when dropped while still set (the write failed or panicked).
struct Staging(Option<PathBuf>);

impl Drop for Staging {
    fn drop(&mut self) {
        if let Some(path) = &self.0 {
            let _ = fs::remove_file(path);
        }
    }
}

/// A file output being written by code that wants a path (see the module header):
/// the writer writes [`StagedFile::path`] (and any [`companion`](Self::companion)
/// paths); [`commit`](Self::commit) moves them all into place. Dropped uncommitted, it
/// removes what was staged and the directories it created.
#[derive(Debug)]
pub struct StagedFile {
    target: PathBuf,
    staging: PathBuf,
    /// (staged, final) paths of files committed with this one.
    companions: Vec<(PathBuf, PathBuf)>,
    created_parent: Option<PathBuf>,
    committed: bool,
}

impl StagedFile {
    /// Starts the output file `target`, creating its missing parent directories; a
    /// directory at `target` is refused.
    pub fn new(target: &Path) -> io::Result<Self> {
        if target.is_dir() {
            return Err(io::Error::new(
                io::ErrorKind::IsADirectory,
                format!("{}: is a directory", target.display()),
            ));
        }
        let created_parent = create_parents(target)?;
        let staging = sibling(target, "partial")?;
        Ok(Self {
            target: target.to_path_buf(),
            staging,
            companions: Vec::new(),
            created_parent,
            committed: false,
        })
    }

    /// Where to write.
    pub fn path(&self) -> &Path {
        &self.staging
    }

    /// The file's final path.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// A companion file named after this one with `suffix` before the extension
    /// (`x.depth.exr` beside `x.exr` for ".depth"), staged beside [`Self::path`] and
    /// committed with it. Returns the staged path to write; a directory at the
    /// companion's final path is refused.
    pub fn companion(&mut self, suffix: &str) -> io::Result<PathBuf> {
        let with = |p: &Path| {
            let stem = p.file_stem().unwrap_or_default().to_string_lossy();
            let ext = p
                .extension()
                .map(|e| format!(".{}", e.to_string_lossy()))
                .unwrap_or_default();
            p.with_file_name(format!("{stem}{suffix}{ext}"))
        };
        let (staged, target) = (with(&self.staging), with(&self.target));
        if target.is_dir() {
            return Err(io::Error::new(
                io::ErrorKind::IsADirectory,
                format!("{}: is a directory", target.display()),
            ));
        }
        self.companions.push((staged.clone(), target));
        Ok(staged)
    }

    /// Moves the companions, then the file, into place, each on disk before its
    /// rename makes it the file. A companion that fails to move leaves every final path
    /// as it was; the file itself is the last rename.
    pub fn commit(mut self) -> io::Result<()> {
        for staged in self
            .companions
            .iter()
            .map(|(s, _)| s)
            .chain([&self.staging])
        {
            fs::File::open(staged)
                .and_then(|f| f.sync_all())
                .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", staged.display())))?;
        }
        let mut moved: Vec<usize> = Vec::new();
        for (i, (staged, target)) in self.companions.iter().enumerate() {
            if let Err(e) = fs::rename(staged, target) {
                for &j in &moved {
                    let _ = fs::remove_file(&self.companions[j].1);
                }
                return Err(io::Error::new(
                    e.kind(),
                    format!("{}: cannot move into place: {e}", target.display()),
                ));
            }
            moved.push(i);
        }
        if let Err(e) = fs::rename(&self.staging, &self.target) {
            for &j in &moved {
                let _ = fs::remove_file(&self.companions[j].1);
            }
            return Err(io::Error::new(
                e.kind(),
                format!("{}: cannot move into place: {e}", self.target.display()),
            ));
        }
        self.committed = true;
        Ok(())
    }
}

impl Drop for StagedFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_file(&self.staging);
            for (staged, _) in &self.companions {
                let _ = fs::remove_file(staged);
            }
            if let Some(p) = &self.created_parent {
                let _ = fs::remove_dir_all(p);
            }
        }
    }
}

/// A directory output being written: files go under [`StagedDir::path`], and
/// [`commit`](Self::commit) replaces whatever was at the target with it, whole.
/// Dropped uncommitted, it removes the staging and the directories it created. What
/// may be replaced is the caller's decision (the CLI refuses directories that are not
/// its own earlier output).
#[derive(Debug)]
pub struct StagedDir {
    target: PathBuf,
    staging: PathBuf,
    created_parent: Option<PathBuf>,
    committed: bool,
}

impl StagedDir {
    /// Starts the directory output `target`, creating its missing parents.
    pub fn new(target: &Path) -> io::Result<Self> {
        let created_parent = create_parents(target)?;
        let staging = sibling(target, "partial")?;
        let _ = fs::remove_dir_all(&staging);
        fs::create_dir(&staging).map_err(|e| {
            io::Error::new(
                e.kind(),
                format!("{}: cannot create: {e}", staging.display()),
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

    /// Moves the finished output into place, replacing an earlier one whole: the old
    /// one is moved aside first and put back if the new one cannot move in.
    pub fn commit(mut self) -> io::Result<()> {
        let old = sibling(&self.target, "replaced")?;
        let had = self.target.exists();
        if had {
            fs::rename(&self.target, &old).map_err(|e| {
                io::Error::new(
                    e.kind(),
                    format!(
                        "{}: cannot move the earlier output aside: {e}",
                        self.target.display()
                    ),
                )
            })?;
        }
        if let Err(e) = fs::rename(&self.staging, &self.target) {
            if had {
                let _ = fs::rename(&old, &self.target);
            }
            return Err(io::Error::new(
                e.kind(),
                format!(
                    "{}: cannot move the new output into place: {e}",
                    self.target.display()
                ),
            ));
        }
        self.committed = true;
        if had {
            let _ = fs::remove_dir_all(&old);
        }
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.staging);
            if let Some(p) = &self.created_parent {
                let _ = fs::remove_dir_all(p);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("drape-io-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_failed_write_leaves_the_earlier_file_and_nothing_else() {
        let dir = scratch("failed");
        let path = dir.join("a.txt");
        write(&path, "old").unwrap();
        let err = write_with(&path, |w| {
            w.write_all(b"half of the new")?;
            Err::<(), _>(io::Error::other("the writer failed"))
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "the writer failed");
        assert_eq!(fs::read_to_string(&path).unwrap(), "old");
        assert_eq!(names(&dir), ["a.txt"]);
    }

    #[test]
    fn a_staged_file_commits_its_companion_with_it() {
        let dir = scratch("companion");
        let target = dir.join("sub/x.exr");
        let mut staged = StagedFile::new(&target).unwrap();
        let depth = staged.companion(".depth").unwrap();
        assert!(depth.to_string_lossy().ends_with(".depth.exr"), "{depth:?}");
        write(staged.path(), "colour").unwrap();
        write(&depth, "depth").unwrap();
        // Nothing under a final name before the commit.
        assert!(!target.exists() && !dir.join("sub/x.depth.exr").exists());
        staged.commit().unwrap();
        assert_eq!(names(&dir.join("sub")), ["x.depth.exr", "x.exr"]);
        assert_eq!(
            fs::read_to_string(dir.join("sub/x.depth.exr")).unwrap(),
            "depth"
        );
    }

    #[test]
    fn an_uncommitted_staged_file_removes_what_it_made() {
        let dir = scratch("uncommitted");
        let mut staged = StagedFile::new(&dir.join("new/deeper/x.exr")).unwrap();
        let depth = staged.companion(".depth").unwrap();
        write(staged.path(), "colour").unwrap();
        write(&depth, "depth").unwrap();
        drop(staged);
        assert!(names(&dir).is_empty(), "{:?}", names(&dir));
    }

    #[test]
    fn a_staged_directory_replaces_the_earlier_one_whole() {
        let dir = scratch("dir");
        let target = dir.join("out");
        fs::create_dir(&target).unwrap();
        write(target.join("stale.png"), "stale").unwrap();
        let staged = StagedDir::new(&target).unwrap();
        write(staged.path().join("fresh.png"), "fresh").unwrap();
        staged.commit().unwrap();
        assert_eq!(names(&target), ["fresh.png"]);
        assert_eq!(names(&dir), ["out"]);
    }
}
