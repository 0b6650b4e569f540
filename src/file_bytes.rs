//! A file's bytes, mapped into memory when that is cheaper than reading them.
//!
//! Reading copies a file into freshly allocated memory, and most of that time goes to
//! page faults on the new buffer. A mapping lets the parser read the system's cached
//! copy of the file directly. A file that another process changes or truncates
//! while it is mapped may read garbled or end the process (SIGBUS), as with any tool that
//! maps its inputs (ripgrep maps large files the same way); mesh files are not edited in
//! the middle of a render.

use std::ops::Deref;
use std::path::Path;

/// Regular files at least this large are mapped (where the platform allows); smaller ones
/// are read, since a mapping costs system calls of its own.
pub const MAP_FROM: u64 = 1 << 20;

/// The bytes of a file, read or mapped.
pub struct FileBytes {
    inner: Inner,
}

enum Inner {
    Read(Vec<u8>),
    #[cfg(unix)]
    Mapped {
        start: *const u8,
        len: usize,
    },
}

// SAFETY: a mapping is private to this value, read-only, and unmapped only on drop.
unsafe impl Send for FileBytes {}
// SAFETY: as above; shared access only reads.
unsafe impl Sync for FileBytes {}

impl FileBytes {
    /// The bytes of the file at `path`.
    pub fn open(path: &Path) -> std::io::Result<FileBytes> {
        let file = std::fs::File::open(path)?;
        let metadata = file.metadata()?;
        #[cfg(unix)]
        if metadata.is_file()
            && metadata.len() >= MAP_FROM
            && let Ok(len) = usize::try_from(metadata.len())
            && let Some(mapped) = map(&file, len)
        {
            return Ok(mapped);
        }
        let mut bytes = Vec::with_capacity(usize::try_from(metadata.len()).unwrap_or(0));
        std::io::Read::read_to_end(&mut &file, &mut bytes)?;
        Ok(FileBytes {
            inner: Inner::Read(bytes),
        })
    }

    /// Whether the bytes are mapped rather than read.
    pub fn is_mapped(&self) -> bool {
        match self.inner {
            Inner::Read(_) => false,
            #[cfg(unix)]
            Inner::Mapped { .. } => true,
        }
    }
}

/// A read-only private mapping of the first `len` (> 0) bytes of `file`, or `None` if the
/// system refuses one (the caller then reads the file).
#[cfg(unix)]
fn map(file: &std::fs::File, len: usize) -> Option<FileBytes> {
    use std::os::unix::io::AsRawFd;
    // SAFETY: a fresh read-only mapping of an open file; nothing else refers to it.
    let start = unsafe {
        libc::mmap(
            std::ptr::null_mut(),
            len,
            libc::PROT_READ,
            libc::MAP_PRIVATE,
            file.as_raw_fd(),
            0,
        )
    };
    if start == libc::MAP_FAILED {
        return None;
    }
    // The file is read front to back: ask for read-ahead. Only advice, so a refusal is
    // harmless.
    // SAFETY: `start..start + len` is the mapping just made.
    unsafe { libc::madvise(start, len, libc::MADV_SEQUENTIAL) };
    Some(FileBytes {
        inner: Inner::Mapped {
            start: start.cast::<u8>().cast_const(),
            len,
        },
    })
}

impl Deref for FileBytes {
    type Target = [u8];

    fn deref(&self) -> &[u8] {
        match &self.inner {
            Inner::Read(bytes) => bytes,
            #[cfg(unix)]
            // SAFETY: the mapping covers `len` readable bytes until `self` is dropped.
            Inner::Mapped { start, len } => unsafe { std::slice::from_raw_parts(*start, *len) },
        }
    }
}

impl Drop for FileBytes {
    fn drop(&mut self) {
        #[cfg(unix)]
        if let Inner::Mapped { start, len } = self.inner {
            // SAFETY: the mapping made in `map`, unmapped once; no slice of it outlives
            // `self` (they borrow it).
            unsafe { libc::munmap(start.cast_mut().cast(), len) };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The same bytes whether read or mapped, at sizes around the mapping threshold and
    /// page boundaries.
    #[test]
    fn mapped_and_read_files_give_the_same_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let threshold = MAP_FROM as usize;
        for len in [
            0,
            1,
            4095,
            4096,
            4097,
            threshold - 1,
            threshold,
            threshold + 4097,
        ] {
            let bytes: Vec<u8> = (0..len).map(|i| (i * 7 + i / 251) as u8).collect();
            let path = dir.path().join(format!("{len}.bin"));
            std::fs::write(&path, &bytes).unwrap();
            let file = FileBytes::open(&path).unwrap();
            assert_eq!(&*file, &bytes[..], "{len} bytes");
            assert_eq!(
                file.is_mapped(),
                cfg!(unix) && len >= threshold,
                "{len} bytes"
            );
        }
        assert!(FileBytes::open(&dir.path().join("absent")).is_err());
    }
}
