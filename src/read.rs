//! Reading files that may be hostile (weights, images, deformations, ground truth, records)
//! within a size limit, so a file that is larger than it may be (or a device, or a pipe that
//! never ends) is an error instead of exhausted memory. Below every layer that reads files.

use std::fs;
use std::path::Path;

use crate::error::{Error, Result};

/// The bytes of a file of at most `limit` bytes; `what` names the kind of file for the
/// message. Reads at most `limit + 1` bytes whatever the file claims to be (a device, a
/// pipe, a file that grows), so an unexpected file cannot exhaust memory.
///
/// # Errors
///
/// [`Error::Io`] naming the file; [`Error::Format`] if it holds more than `limit` bytes.
pub fn read_bytes(path: &Path, limit: u64, what: &str) -> Result<Vec<u8>> {
    let too_large = |size: String| Error::Format {
        path: path.to_path_buf(),
        detail: format!("{size}, more than the {limit} bytes a {what} may hold"),
    };
    let (file, declared) = open_readable(path, what)?;
    // A regular file says its size: a larger one is refused before a byte is read.
    if let Some(len) = declared.filter(|&len| len > limit) {
        return Err(too_large(format!("{len} bytes")));
    }
    let bytes = read_from(path, file, limit.saturating_add(1))?;
    if bytes.len() as u64 > limit {
        return Err(too_large("more bytes".into()));
    }
    Ok(bytes)
}

/// The first `n` bytes of a file (fewer if it is shorter): a header that says how much
/// [`read_bytes`] may then read.
///
/// # Errors
///
/// [`Error::Io`] naming the file; [`Error::Format`] if it is a folder or a device.
pub fn read_prefix(path: &Path, n: u64, what: &str) -> Result<Vec<u8>> {
    let (file, _) = open_readable(path, what)?;
    read_from(path, file, n)
}

/// Whether `path` is a regular file (not a pipe, which can be read only once).
pub fn is_regular_file(path: &Path) -> bool {
    fs::metadata(path).is_ok_and(|m| m.is_file())
}

/// Opens `path` for reading if it is a regular file or a pipe (the size of a regular file
/// is returned with it). A folder, a device (`/dev/zero` would never end, a disk would be
/// read whole) or a socket is refused by its kind, before anything is read.
fn open_readable(path: &Path, what: &str) -> Result<(fs::File, Option<u64>)> {
    #[cfg(unix)]
    use std::os::unix::fs::FileTypeExt;
    let refuse = |kind: &str| Error::Format {
        path: path.to_path_buf(),
        detail: format!("is {kind}, not a regular file or a pipe (expected: {what})"),
    };
    let io_error = |cause| Error::Io {
        path: path.to_path_buf(),
        cause,
    };
    // The kind is checked before opening: opening a pipe waits for its writer.
    let kind = fs::metadata(path).map_err(io_error)?.file_type();
    if kind.is_dir() {
        return Err(refuse("a folder"));
    }
    #[cfg(unix)]
    if kind.is_char_device() || kind.is_block_device() {
        return Err(refuse("a device"));
    }
    #[cfg(unix)]
    if kind.is_socket() {
        return Err(refuse("a socket"));
    }
    let file = fs::File::open(path).map_err(io_error)?;
    // What was opened, which may not be what was looked at a moment ago.
    let meta = file.metadata().map_err(io_error)?;
    let kind = meta.file_type();
    if kind.is_file() {
        return Ok((file, Some(meta.len())));
    }
    #[cfg(unix)]
    if kind.is_fifo() {
        return Ok((file, None));
    }
    Err(refuse("something else"))
}

fn read_from(path: &Path, file: fs::File, n: u64) -> Result<Vec<u8>> {
    use std::io::Read;
    let mut bytes = Vec::new();
    file.take(n)
        .read_to_end(&mut bytes)
        .map_err(|cause| Error::Io {
            path: path.to_path_buf(),
            cause,
        })?;
    Ok(bytes)
}
