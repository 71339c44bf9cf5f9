//! The two ways shoal touches files it is handed: a bounded reader for every
//! small input (fleet files, calibrations, manifests), and an output that
//! appears only when complete ([`OutputFile`]).

use std::io::Read;
use std::path::{Path, PathBuf};

/// Largest configuration-like file shoal reads (fleet TOML, camera YAML, JSON
/// manifests): real ones are a few kilobytes.
pub const MAX_CONFIG_BYTES: u64 = 16 << 20;

/// Read a text file of at most `max` bytes; a larger one (or an endless
/// device such as `/dev/zero`) is refused without reading more than `max + 1` bytes.
pub fn read_text_bounded(path: &Path, max: u64) -> std::io::Result<String> {
    let file = std::fs::File::open(path)?;
    let mut text = String::new();
    let read = file.take(max + 1).read_to_string(&mut text)?;
    if read as u64 > max {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("larger than the {max}-byte limit for this kind of file"),
        ));
    }
    Ok(text)
}

/// Whether `a` and `b` name the same existing file (same device and inode,
/// so hard links and `./x` versus `x` are caught).
pub fn same_file(a: &Path, b: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (std::fs::metadata(a), std::fs::metadata(b)) {
            (Ok(ma), Ok(mb)) => ma.dev() == mb.dev() && ma.ino() == mb.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        match (a.canonicalize(), b.canonicalize()) {
            (Ok(ca), Ok(cb)) => ca == cb,
            _ => false,
        }
    }
}

/// Why an output cannot be started.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error("{}: the output is the input {}; choose another output file", output.display(), input.display())]
    IsInput { output: PathBuf, input: PathBuf },
    #[error("{}: cannot create the temporary file beside it", path.display())]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: cannot write", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: cannot move the finished file into place", path.display())]
    Commit {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// A file written under a temporary name in the target's directory and
/// renamed onto the target only by [`OutputFile::commit`]: an existing file
/// is never truncated by a run that fails, and a failed run leaves no partial
/// output (the temporary file is removed on drop).
#[derive(Debug)]
pub struct OutputFile {
    target: PathBuf,
    temp: PathBuf,
    committed: bool,
}

impl OutputFile {
    /// Prepare `target`, refusing it when it is one of `inputs`. The
    /// temporary file is created empty (so the directory is known writable).
    pub fn new(target: &Path, inputs: &[&Path]) -> Result<Self, OutputError> {
        if let Some(input) = inputs.iter().find(|i| same_file(i, target)) {
            return Err(OutputError::IsInput {
                output: target.to_path_buf(),
                input: input.to_path_buf(),
            });
        }
        let name = target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "output".into());
        let temp = target.with_file_name(format!(".{name}.partial-{}", std::process::id()));
        std::fs::File::create(&temp).map_err(|source| OutputError::Create {
            path: target.to_path_buf(),
            source,
        })?;
        Ok(Self {
            target: target.to_path_buf(),
            temp,
            committed: false,
        })
    }

    /// Write `bytes` to `target` whole or not at all (refusing `inputs`, as [`OutputFile::new`]).
    pub fn write_whole(
        target: &Path,
        inputs: &[&Path],
        bytes: &[u8],
    ) -> Result<PathBuf, OutputError> {
        let out = Self::new(target, inputs)?;
        std::fs::write(out.temp_path(), bytes).map_err(|source| OutputError::Write {
            path: target.to_path_buf(),
            source,
        })?;
        out.commit()
    }

    /// Where to write until [`commit`](Self::commit).
    pub fn temp_path(&self) -> &Path {
        &self.temp
    }

    /// The final name.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Move the finished temporary file onto the target.
    pub fn commit(mut self) -> Result<PathBuf, OutputError> {
        std::fs::rename(&self.temp, &self.target).map_err(|source| OutputError::Commit {
            path: self.target.clone(),
            source,
        })?;
        self.committed = true;
        Ok(self.target.clone())
    }
}

impl Drop for OutputFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.temp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("shoal-files-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).expect("temp dir");
        d
    }

    #[test]
    fn an_uncommitted_output_leaves_the_existing_file_untouched_and_no_debris() {
        let d = dir("uncommitted");
        let target = d.join("out.bin");
        std::fs::write(&target, b"precious").expect("write");
        {
            let out = OutputFile::new(&target, &[]).expect("output");
            std::fs::write(out.temp_path(), b"half").expect("write temp");
        }
        assert_eq!(std::fs::read(&target).expect("read"), b"precious");
        assert_eq!(std::fs::read_dir(&d).expect("list").count(), 1);
        let out = OutputFile::new(&target, &[]).expect("output");
        std::fs::write(out.temp_path(), b"new").expect("write temp");
        out.commit().expect("commit");
        assert_eq!(std::fs::read(&target).expect("read"), b"new");
        std::fs::remove_dir_all(&d).expect("clean");
    }

    #[test]
    fn an_output_that_is_an_input_is_refused_however_it_is_spelled() {
        let d = dir("is-input");
        let input = d.join("a.mcap");
        std::fs::write(&input, b"log").expect("write");
        let spelled = d.join(".").join("a.mcap");
        let linked = d.join("b.mcap");
        std::fs::hard_link(&input, &linked).expect("link");
        for target in [&input, &spelled, &linked] {
            assert!(matches!(
                OutputFile::new(target, &[&input]),
                Err(OutputError::IsInput { .. })
            ));
        }
        assert_eq!(std::fs::read(&input).expect("read"), b"log");
        std::fs::remove_dir_all(&d).expect("clean");
    }

    #[test]
    fn bounded_reads_refuse_endless_and_oversized_files() {
        let err = read_text_bounded(Path::new("/dev/zero"), 1 << 10).expect_err("endless");
        assert_eq!(err.kind(), std::io::ErrorKind::InvalidData);
        let d = dir("bounded");
        let f = d.join("fleet.toml");
        std::fs::write(&f, "x".repeat(100)).expect("write");
        assert_eq!(read_text_bounded(&f, 100).expect("fits").len(), 100);
        assert!(read_text_bounded(&f, 99).is_err());
        std::fs::remove_dir_all(&d).expect("clean");
    }
}
