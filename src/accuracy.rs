//! Run time against error (placeholder).
use std::path::{Path, PathBuf};
pub fn write(dir: &Path, _quick: bool) -> std::io::Result<PathBuf> {
    Ok(dir.join("accuracy.md"))
}
