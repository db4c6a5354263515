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
    let bytes = read_at_most(path, limit.saturating_add(1), what)?;
    if bytes.len() as u64 > limit {
        return Err(Error::Format {
            path: path.to_path_buf(),
            detail: format!("more than {limit} bytes, the most a {what} may hold"),
        });
    }
    Ok(bytes)
}

/// The first `n` bytes of a file (fewer if it is shorter): a header that says how much
/// [`read_bytes`] may then read.
///
/// # Errors
///
/// [`Error::Io`] naming the file; [`Error::Format`] if it is a folder.
pub fn read_prefix(path: &Path, n: u64, what: &str) -> Result<Vec<u8>> {
    read_at_most(path, n, what)
}

fn read_at_most(path: &Path, n: u64, what: &str) -> Result<Vec<u8>> {
    use std::io::Read;
    let io_error = |cause| Error::Io {
        path: path.to_path_buf(),
        cause,
    };
    let file = fs::File::open(path).map_err(io_error)?;
    if file.metadata().is_ok_and(|m| m.is_dir()) {
        return Err(Error::Format {
            path: path.to_path_buf(),
            detail: format!("is a folder, not a {what}"),
        });
    }
    let mut bytes = Vec::new();
    file.take(n).read_to_end(&mut bytes).map_err(io_error)?;
    Ok(bytes)
}
