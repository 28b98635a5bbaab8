//! The files a command reads and writes, checked before any work: no file
//! written may be a file read or another file written (through symbolic
//! and hard links), and every directory written to is made, as the write
//! would make it, and must take a new file. A run so fails before it reads
//! its first frame, not after it (or after its last frame, for the report).
//! The writes themselves stay atomic (`io::exr::write_atomic`).

use std::collections::HashMap;
use std::io::ErrorKind;
use std::path::{Component, Path, PathBuf};

use harmonizer_core::{Error, Result};

/// One file: what it is in messages ("input frame 3", "--report file")
/// and its path as given.
struct File {
    what: String,
    path: PathBuf,
}

impl File {
    fn name(&self) -> String {
        format!("{} {}", self.what, self.path.display())
    }
}

/// Where a path leads: two paths are the same file when they share a key.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
enum Key {
    /// The directory entry itself (its directory resolved, the name kept),
    /// or, for an existing file, the file a symbolic link leads to.
    Path(PathBuf),
    /// Device and inode of an existing file (hard links share them).
    Inode(u64, u64),
}

impl Key {
    fn how(&self) -> String {
        match self {
            Key::Path(p) => format!("both are {}", p.display()),
            Key::Inode(dev, ino) => format!("hard links to one file, device {dev} inode {ino}"),
        }
    }
}

/// A directory as the operating system would reach it, made absolute:
/// the existing part canonicalized (symbolic links followed), the part
/// still to be made joined name by name (`..` drops the last name, as it
/// will once the directories are made).
fn resolve_dir(dir: &Path) -> PathBuf {
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    if let Ok(c) = dir.canonicalize() {
        return c;
    }
    let abs = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
    let parts: Vec<Component> = abs.components().collect();
    // The longest prefix that exists; the root always does.
    let (mut at, rest) = (1..=parts.len())
        .rev()
        .find_map(|k| {
            let prefix: PathBuf = parts[..k].iter().collect();
            prefix.canonicalize().ok().map(|c| (c, &parts[k..]))
        })
        .unwrap_or_else(|| (abs.clone(), &[][..]));
    for c in rest {
        match c {
            Component::ParentDir => {
                at.pop();
            }
            Component::Normal(n) => {
                at.push(n);
                // A name further on may lead back into existing directories.
                if let Ok(c) = at.canonicalize() {
                    at = c;
                }
            }
            _ => {}
        }
    }
    at
}

/// The directory a file is written in (`.` for a bare name).
fn dir_of(path: &Path) -> &Path {
    path.parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
}

/// Every key of `path`: its entry, and for an existing file the file it
/// leads to and its inode.
fn keys(path: &Path) -> Vec<Key> {
    let mut keys = Vec::with_capacity(3);
    if let Some(name) = path.file_name() {
        keys.push(Key::Path(resolve_dir(dir_of(path)).join(name)));
    }
    if let Ok(c) = path.canonicalize() {
        if !keys.contains(&Key::Path(c.clone())) {
            keys.push(Key::Path(c));
        }
    }
    #[cfg(unix)]
    if let Ok(m) = std::fs::metadata(path) {
        use std::os::unix::fs::MetadataExt;
        keys.push(Key::Inode(m.dev(), m.ino()));
    }
    keys
}

/// The files one command reads and writes.
#[derive(Default)]
pub struct Files {
    inputs: Vec<File>,
    outputs: Vec<File>,
}

impl Files {
    /// A file the command reads.
    pub fn input(&mut self, what: impl Into<String>, path: impl Into<PathBuf>) {
        self.inputs.push(File {
            what: what.into(),
            path: path.into(),
        });
    }

    /// A file the command writes.
    pub fn output(&mut self, what: impl Into<String>, path: impl Into<PathBuf>) {
        self.outputs.push(File {
            what: what.into(),
            path: path.into(),
        });
    }

    /// Refuses an output that is an input or another output, then makes
    /// the outputs' directories and checks that each takes a new file.
    pub fn check(&self) -> Result<()> {
        self.refuse_overlaps()?;
        self.prepare_dirs()
    }

    fn refuse_overlaps(&self) -> Result<()> {
        let mut read: HashMap<Key, usize> = HashMap::new();
        for (i, f) in self.inputs.iter().enumerate() {
            for k in keys(&f.path) {
                read.entry(k).or_insert(i);
            }
        }
        let mut written: HashMap<Key, usize> = HashMap::new();
        for (i, f) in self.outputs.iter().enumerate() {
            for k in keys(&f.path) {
                if let Some(&j) = read.get(&k) {
                    return Err(Error::invalid(format!(
                        "{} would overwrite {}, an input file of this run ({}); inputs are never overwritten",
                        f.name(),
                        self.inputs[j].name(),
                        k.how()
                    )));
                }
                match written.get(&k) {
                    Some(&j) if j != i => {
                        return Err(Error::invalid(format!(
                            "{} and {} are the same file ({}); each output must be a file of its own",
                            f.name(),
                            self.outputs[j].name(),
                            k.how()
                        )));
                    }
                    Some(_) => {}
                    None => {
                        written.insert(k, i);
                    }
                }
            }
        }
        Ok(())
    }

    /// Makes each output's directory as `write_atomic` would, and creates
    /// and removes the temporary file it would write there
    /// (`name.tmp-<pid>`), so a failure reads as it would have at the write.
    fn prepare_dirs(&self) -> Result<()> {
        let fail = |f: &File, at: &Path, e: &dyn std::fmt::Display| {
            Error::Io(format!("cannot write {}: {}: {e}", f.name(), at.display()))
        };
        let mut probed: Vec<&Path> = Vec::new();
        for f in &self.outputs {
            let name = f
                .path
                .file_name()
                .ok_or_else(|| fail(f, &f.path, &"has no file name"))?;
            if std::fs::symlink_metadata(&f.path).is_ok_and(|m| m.is_dir()) {
                return Err(Error::Io(format!(
                    "cannot write {}: a directory is there",
                    f.name()
                )));
            }
            let dir = dir_of(&f.path);
            if probed.contains(&dir) {
                continue;
            }
            probed.push(dir);
            if !dir.is_dir() {
                std::fs::create_dir_all(dir).map_err(|e| fail(f, dir, &e))?;
            }
            let tmp = dir.join(format!(
                "{}.tmp-{}",
                name.to_string_lossy(),
                std::process::id()
            ));
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&tmp)
            {
                Ok(file) => {
                    drop(file);
                    std::fs::remove_file(&tmp).map_err(|e| fail(f, &tmp, &e))?;
                }
                // Someone else's file: left alone; the directory takes files.
                Err(e) if e.kind() == ErrorKind::AlreadyExists => {}
                Err(e) => return Err(fail(f, &tmp, &e)),
            }
        }
        Ok(())
    }
}
