//! Writing files without ever leaving a half-written one behind: everything flowram writes goes
//! to a temporary file in the same folder, is flushed to disk, and is then renamed over the
//! target, so a crash or a full disk leaves either the old file or the new one.
use std::io::Write;
use std::path::Path;

/// 64-bit FNV-1a of a byte string (a corruption check, not a cryptographic hash).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// [`fnv1a64`] as the 16 hex digits the file formats record.
pub fn fnv1a64_hex(bytes: &[u8]) -> String {
    format!("{:016x}", fnv1a64(bytes))
}

/// Writes `bytes` to `path` atomically, creating missing parent folders.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_with(path, |tmp| {
        let mut file = std::fs::File::create(tmp)?;
        file.write_all(bytes)
    })
}

/// Writes `path` atomically through `write`, which gets a temporary path in the same folder to
/// write to (for writers that want a path: safetensors, plotters). The temporary name ends
/// with the target's name, so writers that choose a format by extension still see it. The file
/// is fsynced, renamed over `path`, and the folder fsynced so the rename is durable.
pub fn write_atomic_with(path: &Path, write: impl FnOnce(&Path) -> std::io::Result<()>) -> std::io::Result<()> {
    write_atomic_or(path, write, |e| e)
}

/// [`write_atomic_with`] for writers with their own error type `E`: an error of `write` is
/// returned as it was; an I/O error of the temporary file, the fsyncs or the rename is turned
/// into `E` by `io_error`. On any error the temporary file is removed and `path` is untouched.
pub fn write_atomic_or<E>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl FnOnce(std::io::Error) -> E,
) -> Result<(), E> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = match path.file_name() {
        Some(name) => name,
        None => {
            let message = format!("{} is not a file path", path.display());
            return Err(io_error(std::io::Error::new(std::io::ErrorKind::InvalidInput, message)));
        }
    };
    if let Err(e) = std::fs::create_dir_all(dir) {
        return Err(io_error(e));
    }
    let tmp = dir.join(format!(
        ".tmp-{}-{}-{}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed),
        name.to_string_lossy()
    ));
    let result = write(&tmp).and_then(|()| {
        (|| {
            std::fs::File::open(&tmp)?.sync_all()?;
            std::fs::rename(&tmp, path)?;
            std::fs::File::open(dir)?.sync_all()
        })()
        .map_err(io_error)
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_replaces_and_leaves_no_temporary_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/report.json");
        write_atomic(&path, b"first").unwrap();
        write_atomic(&path, b"second").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"second");
        let names: Vec<_> =
            std::fs::read_dir(path.parent().unwrap()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, vec![std::ffi::OsString::from("report.json")]);
    }

    #[test]
    fn a_failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keep.txt");
        write_atomic(&path, b"old").unwrap();
        // A writer that fails half-way (after writing part of the file), before the rename.
        let failing = |tmp: &Path| {
            std::fs::write(tmp, b"ne")?;
            Err(std::io::Error::other("disk full"))
        };
        assert!(write_atomic_with(&path, failing).is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, vec![std::ffi::OsString::from("keep.txt")], "the temporary file is removed");
    }
}
