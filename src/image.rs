//! Images as written: 8-bit PPM (`P3` text or `P6` bytes) or float32 PFM.
//!
//! A pixel's value (the mean of its samples) is stored in its final form at once: for PPM
//! each channel, after the transfer function, becomes `floor(clamp(c * 256, 0, 255))`; for
//! PFM it is the linear value as float32. Files are written to a temporary name beside the
//! target and then put in its place in one step, so a failed or interrupted job never
//! leaves a partial image.

use std::borrow::Cow;
use std::io::{self, IoSlice, Write};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::manifest::{Encoding, OutputFormat, PpmStyle, Rgb};

use rayon::prelude::*;

/// Pixels in their stored form, row-major from the top-left.
#[derive(Debug, Clone, PartialEq)]
pub enum Pixels {
    /// Three bytes per pixel.
    Rgb8(Vec<u8>),
    /// Three floats per pixel.
    RgbF32(Vec<f32>),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub format: OutputFormat,
    pub encoding: Encoding,
    pub pixels: Pixels,
}

impl Image {
    /// A black image.
    pub fn new(width: u32, height: u32, format: OutputFormat, encoding: Encoding) -> Image {
        let n = width as usize * height as usize * 3;
        let pixels = match format {
            OutputFormat::Ppm(_) => Pixels::Rgb8(zeroed(n)),
            OutputFormat::Pfm => Pixels::RgbF32(zeroed(n)),
        };
        Image {
            width,
            height,
            format,
            encoding,
            pixels,
        }
    }

    /// Stores the linear value of pixel `(x, y)`.
    pub fn set(&mut self, x: u32, y: u32, value: Rgb) {
        let height = self.height;
        let mut bands = self.bands_mut(height);
        bands[0].set(x, y, value);
    }

    /// The image cut into horizontal bands of `rows` rows (the last may be shorter), each
    /// writable on its own thread.
    pub fn bands_mut(&mut self, rows: u32) -> Vec<Band<'_>> {
        let stride = self.width as usize * 3 * rows.max(1) as usize;
        let (width, encoding) = (self.width, self.encoding);
        let band = |i: usize, data| Band {
            y0: i as u32 * rows,
            width,
            encoding,
            data,
        };
        match &mut self.pixels {
            Pixels::Rgb8(bytes) => bytes
                .chunks_mut(stride)
                .enumerate()
                .map(|(i, c)| band(i, BandData::Rgb8(c)))
                .collect(),
            Pixels::RgbF32(floats) => floats
                .chunks_mut(stride)
                .enumerate()
                .map(|(i, c)| band(i, BandData::RgbF32(c)))
                .collect(),
        }
    }

    /// The complete file contents.
    pub fn to_bytes(&self) -> Vec<u8> {
        self.file_parts().concat()
    }

    /// The file contents in consecutive parts: the header, then the pixels. Pixel data
    /// already in file form is borrowed, not copied: `P6` bytes whole, PFM rows one by one
    /// (bottom row first) on little-endian machines. `P3` text is formatted in parallel in
    /// bands of rows (a full-HD image is 25 MB of text).
    fn file_parts(&self) -> Vec<Cow<'_, [u8]>> {
        let (w, h) = (self.width as usize, self.height as usize);
        match (&self.pixels, self.format) {
            (Pixels::Rgb8(bytes), OutputFormat::Ppm(PpmStyle::Binary)) => vec![
                Cow::Owned(format!("P6\n{w} {h}\n255\n").into_bytes()),
                Cow::Borrowed(bytes.as_slice()),
            ],
            (Pixels::Rgb8(bytes), _) => {
                let mut parts = vec![Cow::Owned(plain_header(w, h))];
                parts.par_extend(bytes.par_chunks(plain_band_len(w)).map(|band| {
                    let mut text = Vec::new();
                    append_plain_text(band, &mut text);
                    Cow::Owned(text)
                }));
                parts
            }
            (Pixels::RgbF32(floats), _) => {
                // The scale -1.0 declares little-endian floats.
                let mut parts = vec![Cow::Owned(format!("PF\n{w} {h}\n-1.0\n").into_bytes())];
                // PFM stores the bottom row first.
                parts.extend(
                    floats
                        .chunks_exact(w.max(1) * 3)
                        .rev()
                        .map(little_endian_bytes),
                );
                parts
            }
        }
    }

    /// Writes the image to `path` atomically (see [`write_atomically`]). `P3` text is
    /// formatted a group of bands at a time as the file is written.
    pub fn write(&self, path: &Path) -> io::Result<()> {
        match (&self.pixels, self.format) {
            (Pixels::Rgb8(bytes), OutputFormat::Ppm(PpmStyle::Plain)) => {
                write_atomically_with(path, |file| {
                    write_plain_text(file, self.width as usize, self.height as usize, bytes)
                })
            }
            _ => write_parts_atomically(path, &self.file_parts()),
        }
    }
}

/// `n` zeros; a large image's on every worker thread. A full-HD PFM is 25 MB, zeroed and
/// first touched (each page a fault) on the thread that makes the image while the workers
/// waited; the pixels are written in parallel bands anyway.
fn zeroed<T: Copy + Default + Send + Sync>(n: usize) -> Vec<T> {
    /// Bytes below which the calling thread zeroes the image itself (a worker's wake-up
    /// costs more).
    const PARALLEL_FROM_BYTES: usize = 1 << 20;
    if n * std::mem::size_of::<T>() < PARALLEL_FROM_BYTES {
        return vec![T::default(); n];
    }
    let mut zeros = Vec::with_capacity(n);
    zeros.par_extend(rayon::iter::repeat_n(T::default(), n));
    zeros
}

/// Rows of `P3` text formatted by one task.
const PLAIN_BAND_ROWS: usize = 8;

/// Bands of `P3` text formatted together, as one group; a group is written while the next
/// is formatted. Its text is still in the cache when the kernel copies it, and the two
/// groups' buffers are reused, instead of the whole text (14 MB for a full-HD image)
/// going first to memory never touched before.
const PLAIN_BANDS_AT_ONCE: usize = 8;

/// The `P3` header of a `width` x `height` image.
fn plain_header(width: usize, height: usize) -> Vec<u8> {
    format!("P3\n{width} {height}\n255\n").into_bytes()
}

/// The bytes of [`PLAIN_BAND_ROWS`] rows of pixels `width` wide.
fn plain_band_len(width: usize) -> usize {
    3 * width.max(1) * PLAIN_BAND_ROWS
}

/// Writes the `P3` file of `width` x `height` pixels `bytes` to `file`, formatted in
/// parallel a few bands at a time ([`PLAIN_BANDS_AT_ONCE`]).
fn write_plain_text(
    file: &mut (impl Write + Send),
    width: usize,
    height: usize,
    bytes: &[u8],
) -> io::Result<()> {
    file.write_all(&plain_header(width, height))?;
    let band_len = plain_band_len(width);
    let format = |group: &[u8], texts: &mut Vec<Vec<u8>>| {
        texts.resize(group.len().div_ceil(band_len), Vec::new());
        let bands = group.par_chunks(band_len);
        bands.zip(texts.par_iter_mut()).for_each(|(band, text)| {
            text.clear();
            append_plain_text(band, text);
        });
    };
    let mut groups = bytes.chunks(band_len * PLAIN_BANDS_AT_ONCE);
    let (mut ready, mut next) = (Vec::new(), Vec::new());
    if let Some(group) = groups.next() {
        format(group, &mut ready);
    }
    while !ready.is_empty() {
        let group = groups.next();
        let (written, ()) = rayon::join(
            || write_all_vectored(file, &ready),
            || match group {
                Some(group) => format(group, &mut next),
                None => next.clear(),
            },
        );
        written?;
        std::mem::swap(&mut ready, &mut next);
    }
    Ok(())
}

/// The bytes of `floats` in little-endian order: the floats' own memory where that is
/// their order.
fn little_endian_bytes(floats: &[f32]) -> Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        // SAFETY: f32 has no padding and every byte of it is initialized; u8 needs no
        // alignment; the length covers exactly the floats' memory.
        Cow::Borrowed(unsafe {
            std::slice::from_raw_parts(floats.as_ptr().cast::<u8>(), std::mem::size_of_val(floats))
        })
    } else {
        Cow::Owned(floats.iter().flat_map(|v| v.to_le_bytes()).collect())
    }
}

/// Appends the `P3` text of `pixels` to `text`: "r g b" and a newline per pixel.
fn append_plain_text(pixels: &[u8], text: &mut Vec<u8>) {
    // Each pixel's text ("255 255 255\n" at most) is put together in registers and stored
    // in two unaligned writes, "r g " (8 bytes stored) and "b\n" (4), the position then
    // advanced by its length: no byte-by-byte copies, and no zeroing of the buffer first.
    const MAX_PIXEL_TEXT: usize = 12;
    let count = pixels.len() / 3;
    text.reserve(count * MAX_PIXEL_TEXT);
    let start = text.len();
    let mut at = start;
    let out = text.as_mut_ptr();
    for pixel in pixels.chunks_exact(3) {
        let [r, g, b] = [0, 1, 2].map(|k| DECIMAL_WORDS[usize::from(pixel[k])]);
        let (r_len, g_len, b_len) = (r >> 32, g >> 32, b >> 32);
        let head = u64::from(r as u32) | u64::from(g as u32) << (8 * r_len);
        // b's trailing space turned into the line feed.
        let tail = b as u32 ^ u32::from(b' ' ^ b'\n') << (8 * (b_len - 1));
        // SAFETY: `reserve` made room for `MAX_PIXEL_TEXT` bytes per pixel after `start`,
        // and each pixel advances `at` by at most that; the stores reach `at + 8` and
        // `at + r_len + g_len + 4 <= at + 12`. Unaligned writes of plain integers.
        unsafe {
            out.add(at).cast::<u64>().write_unaligned(head.to_le());
            let b_at = at + (r_len + g_len) as usize;
            out.add(b_at).cast::<u32>().write_unaligned(tail.to_le());
        }
        at += (r_len + g_len + b_len) as usize;
    }
    // SAFETY: every byte in `start..at` was written above, within the reserved capacity.
    unsafe { text.set_len(at) };
}

/// An image read back from a PPM (`P3`/`P6`, any maxval) or PFM (`PF`/`Pf`) file, in the
/// file's own units (PPM: `0..=maxval`; PFM: floats), rows from the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    pub width: u32,
    pub height: u32,
    /// `Some(maxval)` for PPM, `None` for PFM.
    pub maxval: Option<u32>,
    pub pixels: Vec<[f64; 3]>,
}

/// Why an image file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: std::path::PathBuf,
        #[source]
        source: io::Error,
    },
    #[error("{path}: {message}")]
    Format {
        path: std::path::PathBuf,
        message: String,
    },
}

/// Reads a PPM or PFM file.
pub fn read(path: &Path) -> Result<Decoded, DecodeError> {
    let bytes = std::fs::read(path).map_err(|source| DecodeError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    decode(&bytes).map_err(|message| DecodeError::Format {
        path: path.to_path_buf(),
        message,
    })
}

/// Decodes PPM or PFM bytes.
pub fn decode(bytes: &[u8]) -> Result<Decoded, String> {
    let mut header = Header { bytes, at: 0 };
    let magic = header.token()?;
    let width: u32 = header.number("width")?;
    let height: u32 = header.number("height")?;
    if width == 0 || height == 0 {
        return Err(format!("empty image ({width} x {height})"));
    }
    let n = width as usize * height as usize;
    match magic.as_str() {
        "P3" | "P6" => {
            let maxval: u32 = header.number("maxval")?;
            if !(1..=65535).contains(&maxval) {
                return Err(format!("maxval {maxval} is outside 1..=65535"));
            }
            // Sized by what the file can hold, never by its header alone: a header may
            // claim more pixels than memory holds (a P3 value takes two bytes or more).
            let mut pixels = Vec::with_capacity(n.min(bytes.len() / 6 + 1));
            if magic == "P3" {
                for _ in 0..n {
                    let mut p = [0.0; 3];
                    for c in &mut p {
                        let v: u32 = header.number("pixel value")?;
                        if v > maxval {
                            return Err(format!("pixel value {v} exceeds maxval {maxval}"));
                        }
                        *c = f64::from(v);
                    }
                    pixels.push(p);
                }
            } else {
                let data = header.data()?;
                let size = if maxval < 256 { 1 } else { 2 };
                if data.len() < n * 3 * size {
                    return Err(format!(
                        "{} bytes of pixel data, {} expected",
                        data.len(),
                        n * 3 * size
                    ));
                }
                let sample = |i: usize| match size {
                    1 => f64::from(data[i]),
                    _ => f64::from(u16::from_be_bytes([data[2 * i], data[2 * i + 1]])),
                };
                pixels
                    .extend((0..n).map(|p| [sample(3 * p), sample(3 * p + 1), sample(3 * p + 2)]));
            }
            Ok(Decoded {
                width,
                height,
                maxval: Some(maxval),
                pixels,
            })
        }
        "PF" | "Pf" => {
            let scale: f64 = header
                .token()?
                .parse()
                .map_err(|_| "the PFM scale is not a number".to_string())?;
            let data = header.data()?;
            let channels = if magic == "PF" { 3 } else { 1 };
            if data.len() < n * channels * 4 {
                return Err(format!(
                    "{} bytes of pixel data, {} expected",
                    data.len(),
                    n * channels * 4
                ));
            }
            let float = |i: usize| {
                let b = [
                    data[4 * i],
                    data[4 * i + 1],
                    data[4 * i + 2],
                    data[4 * i + 3],
                ];
                f64::from(if scale < 0.0 {
                    f32::from_le_bytes(b)
                } else {
                    f32::from_be_bytes(b)
                })
            };
            let (w, h) = (width as usize, height as usize);
            let mut pixels = vec![[0.0; 3]; n];
            for row in 0..h {
                // The file's first row is the image's bottom row.
                let y = h - 1 - row;
                for x in 0..w {
                    let i = (row * w + x) * channels;
                    pixels[y * w + x] = if channels == 3 {
                        [float(i), float(i + 1), float(i + 2)]
                    } else {
                        [float(i); 3]
                    };
                }
            }
            Ok(Decoded {
                width,
                height,
                maxval: None,
                pixels,
            })
        }
        other => Err(format!("not a PPM or PFM file (magic {other:?})")),
    }
}

/// A cursor over a Netpbm-style header: whitespace-separated tokens, `#` comments.
struct Header<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Header<'_> {
    fn token(&mut self) -> Result<String, String> {
        loop {
            while self.at < self.bytes.len() && self.bytes[self.at].is_ascii_whitespace() {
                self.at += 1;
            }
            if self.bytes.get(self.at) != Some(&b'#') {
                break;
            }
            while self.at < self.bytes.len() && self.bytes[self.at] != b'\n' {
                self.at += 1;
            }
        }
        let start = self.at;
        while self.at < self.bytes.len() && !self.bytes[self.at].is_ascii_whitespace() {
            self.at += 1;
        }
        if start == self.at {
            return Err("the file ends early".to_string());
        }
        Ok(String::from_utf8_lossy(&self.bytes[start..self.at]).into_owned())
    }

    fn number<T: std::str::FromStr>(&mut self, what: &str) -> Result<T, String> {
        let token = self.token()?;
        token.parse().map_err(|_| format!("bad {what} {token:?}"))
    }

    /// The binary data after the single whitespace byte that ends the header.
    fn data(&self) -> Result<&[u8], String> {
        self.bytes
            .get(self.at + 1..)
            .ok_or_else(|| "the file ends early".to_string())
    }
}

/// Rows `y0..y0 + rows()` of an [`Image`].
#[derive(Debug)]
pub struct Band<'a> {
    pub y0: u32,
    width: u32,
    encoding: Encoding,
    data: BandData<'a>,
}

#[derive(Debug)]
enum BandData<'a> {
    Rgb8(&'a mut [u8]),
    RgbF32(&'a mut [f32]),
}

impl Band<'_> {
    /// Rows in this band.
    pub fn rows(&self) -> u32 {
        let len = match &self.data {
            BandData::Rgb8(d) => d.len(),
            BandData::RgbF32(d) => d.len(),
        };
        (len / (self.width as usize * 3)) as u32
    }

    /// Stores the linear values of `tile`'s pixels, row by row (as
    /// [`Tile::pixels`](crate::render::Tile::pixels) lists them): the format and encoding
    /// are looked at once, and each row is one slice of the band.
    pub fn set_tile(&mut self, tile: &crate::render::Tile, values: &[Rgb]) {
        // Each row's channels as one flat run, in the file's order: loops over channels,
        // not pixels, which the compiler turns into vector operations.
        let w = tile.width as usize;
        let row_start = |dy: u32| (dy as usize * self.width as usize + tile.x0 as usize) * 3;
        let rows = (tile.dy0..).zip(values.chunks_exact(w).map(|row| row.as_flattened()));
        match (&mut self.data, self.encoding) {
            (BandData::Rgb8(bytes), Encoding::Linear) => {
                for (dy, row) in rows {
                    let start = row_start(dy);
                    quantize_run(&mut bytes[start..start + 3 * w], row);
                }
            }
            (BandData::Rgb8(bytes), Encoding::Srgb) => {
                for (dy, row) in rows {
                    let start = row_start(dy);
                    for (out, &c) in bytes[start..start + 3 * w].iter_mut().zip(row) {
                        *out = quantize(encode(c, Encoding::Srgb));
                    }
                }
            }
            (BandData::RgbF32(floats), _) => {
                for (dy, row) in rows {
                    let start = row_start(dy);
                    for (out, &c) in floats[start..start + 3 * w].iter_mut().zip(row) {
                        *out = c as f32;
                    }
                }
            }
        }
    }

    /// Stores the linear value of pixel `(x, y0 + dy)`.
    #[inline]
    pub fn set(&mut self, x: u32, dy: u32, value: Rgb) {
        let at = (dy as usize * self.width as usize + x as usize) * 3;
        match &mut self.data {
            BandData::Rgb8(bytes) => {
                let encoded = match self.encoding {
                    Encoding::Linear => value,
                    Encoding::Srgb => value.map(|c| encode(c, Encoding::Srgb)),
                };
                bytes[at..at + 3].copy_from_slice(&encoded.map(quantize));
            }
            BandData::RgbF32(floats) => {
                floats[at..at + 3].copy_from_slice(&value.map(|c| c as f32));
            }
        }
    }
}

/// The transfer function: identity, or the sRGB curve.
#[inline]
pub fn encode(c: f64, encoding: Encoding) -> f64 {
    match encoding {
        Encoding::Linear => c,
        Encoding::Srgb => {
            if c <= 0.0031308 {
                12.92 * c
            } else {
                1.055 * c.powf(1.0 / 2.4) - 0.055
            }
        }
    }
}

/// [`quantize`] of each of `values` into `out`, eight at a time where the CPU has AVX2.
#[inline]
fn quantize_run(out: &mut [u8], values: &[f64]) {
    #[inline(always)]
    fn run(out: &mut [u8], values: &[f64]) {
        for (out, &c) in out.iter_mut().zip(values) {
            *out = quantize(c);
        }
    }
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn run_avx2(out: &mut [u8], values: &[f64]) {
        run(out, values);
    }
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        unsafe { run_avx2(out, values) };
        return;
    }
    run(out, values);
}

/// `floor(clamp(c * 256, 0, 255))`; NaN becomes 0.
#[inline]
pub fn quantize(c: f64) -> u8 {
    // Clamped first (`max` takes 0 over a NaN), so that the cast that truncates toward
    // zero (floor, for what is left) needs none of the saturating cast's range checks.
    #[allow(
        clippy::manual_clamp,
        reason = "`clamp` keeps a NaN, which must become 0"
    )]
    let clamped = (c * 256.0).max(0.0).min(255.0);
    // SAFETY: `clamped` is a number in [0, 255], which fits a `u8`.
    unsafe { clamped.to_int_unchecked::<u8>() }
}

/// Every byte value's decimal digits followed by a space, as the low bytes of a
/// little-endian word (bits 0..32), and how many bytes that is (bits 32 and up).
const DECIMAL_WORDS: [u64; 256] = {
    let mut table = [0u64; 256];
    let mut v = 0;
    while v < 256 {
        let space = b' ' as u64;
        let zero = b'0' as u64;
        let (hundreds, tens, ones) = (
            zero + v as u64 / 100,
            zero + v as u64 / 10 % 10,
            zero + v as u64 % 10,
        );
        table[v] = if v >= 100 {
            hundreds | tens << 8 | ones << 16 | space << 24 | 4 << 32
        } else if v >= 10 {
            tens | ones << 8 | space << 16 | 3 << 32
        } else {
            ones | space << 8 | 2 << 32
        };
        v += 1;
    }
    table
};

/// Writes `bytes` to a hidden temporary file beside `path`, then puts it in `path`'s place
/// in one step (on Linux, over an existing file, by exchanging the two and removing the
/// old one): readers see the old file or the whole new one, never a part.
/// Creates missing parent folders. On failure the temporary file is removed.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_parts_atomically(path, &[bytes])
}

/// [`write_atomically`] for contents given as consecutive parts.
pub fn write_parts_atomically(path: &Path, parts: &[impl AsRef<[u8]>]) -> io::Result<()> {
    write_atomically_with(path, |file| write_all_vectored(file, parts))
}

/// [`write_atomically`] for contents that `write` writes to the (new, empty) file.
pub fn write_atomically_with(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> io::Result<()>,
) -> io::Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "not a file name"))?;
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(folder)?;
    let mut temporary_name = std::ffi::OsString::from(".");
    temporary_name.push(name);
    temporary_name.push(format!(
        ".{}-{}.tmp",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let temporary = folder.join(temporary_name);
    let create_and_write = || -> io::Result<()> {
        let mut file = std::fs::File::create(&temporary)?;
        write(&mut file)
    };
    let result = create_and_write().and_then(|()| put_in_place(&temporary, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    result
}

/// Puts the finished file `temporary` (in `path`'s folder) at `path`, replacing what is
/// there as `rename` does, in one step that readers cannot see half done.
///
/// Over an existing file on Linux, the two names are exchanged (`RENAME_EXCHANGE`) and the
/// old file, now under the temporary name, is unlinked. A plain rename over a file makes
/// ext4 start writing the new file to disk before the call returns (its `auto_da_alloc`
/// guard for programs that never `fsync`): rendering a full-HD `depth` job again, its
/// write (25 MB of PFM) took 18–19 ms that way and takes 7 ms now (BENCHMARKS.md). That
/// guard is what is given up; neither way calls `fsync`, so an image written just before
/// a power loss may be lost either way.
fn put_in_place(temporary: &Path, path: &Path) -> io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        // Only files and links are exchanged: a folder at `path` gets rename's error.
        let replaces_a_file = std::fs::symlink_metadata(path).is_ok_and(|m| !m.is_dir());
        if replaces_a_file && exchange(temporary, path).is_ok() {
            return remove_exchanged(temporary, path);
        }
    }
    std::fs::rename(temporary, path)
}

/// Unlinks the old file that [`exchange`] moved to `temporary`. Should that fail (a folder
/// took the file's place between the check and the exchange), the two are exchanged back
/// and renamed as they would have been.
#[cfg(target_os = "linux")]
fn remove_exchanged(temporary: &Path, path: &Path) -> io::Result<()> {
    if std::fs::remove_file(temporary).is_ok() {
        return Ok(());
    }
    exchange(temporary, path)?;
    std::fs::rename(temporary, path)
}

/// Swaps the entries at `a` and `b` atomically (`renameat2` with `RENAME_EXCHANGE`, by
/// system call: older C libraries lack the wrapper). Fails if either is missing or the
/// file system cannot exchange.
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> io::Result<()> {
    use std::os::unix::ffi::OsStrExt;
    let c_path = |p: &Path| {
        std::ffi::CString::new(p.as_os_str().as_bytes())
            .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "NUL in a path"))
    };
    let (a, b) = (c_path(a)?, c_path(b)?);
    // SAFETY: both paths are NUL-terminated strings that outlive the call.
    let status = unsafe {
        libc::syscall(
            libc::SYS_renameat2,
            libc::AT_FDCWD,
            a.as_ptr(),
            libc::AT_FDCWD,
            b.as_ptr(),
            libc::RENAME_EXCHANGE,
        )
    };
    if status == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// Bytes offered to the kernel per call. Linux 6.x caches one large write to ext4 in
/// folios of up to 2 MB, and on a virtual machine whose free memory goes back to its host
/// (free page reporting) such blocks are the ones the host must supply again on first
/// touch: 25 MB written to a new file in calls of 4 MB took 26–83 ms on the development
/// machine, in calls of 256 KB 6–8 ms (DEVELOPERS.md, "Images are written a quarter
/// megabyte at a time", gives the commands). Elsewhere, 100 calls for a full-HD PFM cost
/// nothing to speak of.
const BYTES_PER_CALL: usize = 256 * 1024;

/// Slices per call at most (Linux takes up to 1024; std passes at most the system's limit).
const SLICES_PER_CALL: usize = 512;

/// Writes every part, in order, in calls of at most [`BYTES_PER_CALL`] bytes and
/// [`SLICES_PER_CALL`] slices (a PFM image is one part per row; a part longer than a call
/// is split).
fn write_all_vectored(file: &mut impl Write, parts: &[impl AsRef<[u8]>]) -> io::Result<()> {
    let mut parts = parts.iter().map(AsRef::as_ref);
    // What is left of the part being written.
    let mut rest: &[u8] = &[];
    let mut slices: Vec<IoSlice<'_>> = Vec::with_capacity(SLICES_PER_CALL);
    loop {
        slices.clear();
        let mut room = BYTES_PER_CALL;
        while room > 0 && slices.len() < SLICES_PER_CALL {
            if rest.is_empty() {
                match parts.next() {
                    Some(part) => rest = part,
                    None => break,
                }
                // A call given only empty parts would write nothing.
                if rest.is_empty() {
                    continue;
                }
            }
            let (now, later) = rest.split_at(rest.len().min(room));
            slices.push(IoSlice::new(now));
            room -= now.len();
            rest = later;
        }
        if slices.is_empty() {
            return Ok(());
        }
        let mut remaining = &mut slices[..];
        while !remaining.is_empty() {
            match file.write_vectored(remaining) {
                Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
                Ok(n) => IoSlice::advance_slices(&mut remaining, n),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantization_is_floor_of_256c_clamped() {
        let cases = [
            (0.0, 0),
            (-1.0, 0),
            (f64::NAN, 0),
            (1.0 / 256.0, 1),
            (1.0 / 256.0 - 1e-12, 0),
            (0.5, 128),
            (254.999 / 256.0, 254),
            (255.0 / 256.0, 255),
            (1.0, 255),
            (7.0, 255),
            (f64::INFINITY, 255),
            (f64::NEG_INFINITY, 0),
            (-0.0, 0),
            (-1e-300, 0),
        ];
        for (c, expected) in cases {
            assert_eq!(quantize(c), expected, "{c}");
        }
    }

    #[test]
    fn a_tile_is_stored_as_its_pixels_one_by_one() {
        // Every format and encoding; whole and edge tiles, in a band below the first.
        let formats = [OutputFormat::Ppm(PpmStyle::Plain), OutputFormat::Pfm];
        let tiles = [(0, 0, 8, 8), (8, 3, 5, 2), (16, 7, 3, 1)];
        for (format, encoding) in formats
            .into_iter()
            .flat_map(|f| [Encoding::Linear, Encoding::Srgb].map(|e| (f, e)))
        {
            for (x0, dy0, width, height) in tiles {
                let tile = crate::render::Tile {
                    x0,
                    dy0,
                    width,
                    height,
                };
                let mut pixels = [(0, 0); crate::render::GROUP];
                let n = tile.pixels(&mut pixels);
                let values: Vec<Rgb> = (0..n)
                    .map(|i| [i as f64 / 70.0, 0.3 - i as f64 / 50.0, 1.5 * (i % 3) as f64])
                    .collect();
                let (mut whole, mut one_by_one) =
                    [0, 1].map(|_| Image::new(19, 16, format, encoding)).into();
                whole.bands_mut(8)[1].set_tile(&tile, &values);
                for (&(x, dy), &value) in pixels[..n].iter().zip(&values) {
                    one_by_one.set(x, 8 + dy, value);
                }
                assert_eq!(
                    whole.to_bytes(),
                    one_by_one.to_bytes(),
                    "{format:?} {encoding:?} {tile:?}"
                );
                assert_ne!(
                    whole.to_bytes(),
                    Image::new(19, 16, format, encoding).to_bytes()
                );
            }
        }
    }

    #[test]
    fn srgb_follows_the_standard_curve() {
        // Reference values of the sRGB curve (IEC 61966-2-1), worked out apart from this
        // code: linear 0.5 is 0.7353570 (the 8-bit mid grey 188 by the contract's
        // `floor(c · 256)`), 18% grey 0.4613561 (118); 0.0035 lies past the branch point,
        // where the straight part would give 0.04522.
        let cases = [
            (0.5, 0.7353569830524495, 188),
            (0.18, 0.46135612950044164, 118),
            (0.0035, 0.04498790711983986, 11),
            (0.002, 0.02584, 6),
            (1.0, 1.0, 255),
            (0.0, 0.0, 0),
        ];
        for (c, encoded, byte) in cases {
            let e = encode(c, Encoding::Srgb);
            assert!((e - encoded).abs() < 1e-12, "{c}: {e} against {encoded}");
            assert_eq!(quantize(e), byte, "{c}");
        }
        // The branch point belongs to the straight part (`c ≤ 0.0031308`), where the curve
        // gives 0.04044991 instead.
        assert_eq!(encode(0.0031308, Encoding::Srgb), 12.92 * 0.0031308);
        assert_eq!(encode(0.3, Encoding::Linear), 0.3);
    }

    /// An image with every byte value in every channel, over more rows than two groups of
    /// `P3` bands written at once hold, and its `P3` file as `format!` writes it.
    fn plain_image_and_text() -> (Image, String) {
        let (w, h) = (97, (2 * PLAIN_BANDS_AT_ONCE * PLAIN_BAND_ROWS + 11) as u32);
        let mut image = Image::new(w, h, OutputFormat::Ppm(PpmStyle::Plain), Encoding::Linear);
        let value = |x: u32, y: u32, k: u32| (x * 7 + y * 13 + k * 101) % 256;
        for y in 0..h {
            for x in 0..w {
                let c = [0, 1, 2].map(|k| (f64::from(value(x, y, k)) + 0.5) / 256.0);
                image.set(x, y, c);
            }
        }
        let mut expected = format!("P3\n{w} {h}\n255\n");
        for y in 0..h {
            for x in 0..w {
                let [r, g, b] = [0, 1, 2].map(|k| value(x, y, k));
                expected.push_str(&format!("{r} {g} {b}\n"));
            }
        }
        (image, expected)
    }

    #[test]
    fn plain_ppm_text_is_each_pixel_formatted_on_its_line() {
        let (image, expected) = plain_image_and_text();
        assert_eq!(String::from_utf8(image.to_bytes()).unwrap(), expected);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.ppm");
        image.write(&path).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), expected);
    }

    #[test]
    fn plain_ppm_text_is_written_whole_however_the_writer_splits_it_and_stops_at_an_error() {
        let (image, expected) = plain_image_and_text();
        let Pixels::Rgb8(bytes) = &image.pixels else {
            unreachable!("a PPM image holds bytes")
        };
        let (w, h) = (image.width as usize, image.height as usize);
        for limit in [1, 7, 4096, usize::MAX] {
            let mut writer = Trickle {
                written: Vec::new(),
                limit,
                calls: 0,
            };
            write_plain_text(&mut writer, w, h, bytes).unwrap();
            assert!(
                writer.written == expected.as_bytes(),
                "at most {limit} bytes a call"
            );
        }
        // A writer that fails after `room` bytes: in the header, in the first group of
        // bands, in the last.
        struct Full {
            room: usize,
        }
        impl Write for Full {
            fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
                if self.room == 0 {
                    return Err(io::Error::other("no room"));
                }
                let n = bytes.len().min(self.room);
                self.room -= n;
                Ok(n)
            }
            fn flush(&mut self) -> io::Result<()> {
                Ok(())
            }
        }
        for room in [3, 1000, expected.len() - 1] {
            let error = write_plain_text(&mut Full { room }, w, h, bytes).unwrap_err();
            assert_eq!(error.to_string(), "no room", "room for {room} bytes");
        }
    }

    #[test]
    fn what_is_written_reads_back() {
        for format in [
            OutputFormat::Ppm(PpmStyle::Plain),
            OutputFormat::Ppm(PpmStyle::Binary),
            OutputFormat::Pfm,
        ] {
            let mut image = Image::new(3, 2, format, Encoding::Linear);
            image.set(2, 0, [0.5, 0.25, 1.0]);
            image.set(0, 1, [0.125, 0.0, 0.75]);
            let decoded = decode(&image.to_bytes()).unwrap();
            assert_eq!((decoded.width, decoded.height), (3, 2));
            let expected = |v: [f64; 3]| match format {
                OutputFormat::Pfm => v,
                _ => v.map(|c| f64::from(quantize(c))),
            };
            assert_eq!(decoded.pixels[2], expected([0.5, 0.25, 1.0]), "{format:?}");
            assert_eq!(
                decoded.pixels[3],
                expected([0.125, 0.0, 0.75]),
                "{format:?}"
            );
            assert_eq!(decoded.pixels[0], [0.0; 3]);
        }
    }

    /// The names in `folder`, sorted.
    fn names_in(folder: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(folder)
            .unwrap()
            .map(|entry| entry.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        names
    }

    #[cfg(unix)]
    #[test]
    fn a_new_image_replaces_the_entry_at_its_path_and_nothing_else() {
        // As `rename` does: the name gets the new file; other names of the old file, and
        // a link's target, keep the old contents.
        for before in ["nothing", "a file", "a file with a second name", "a link"] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("out.ppm");
            let mut expected = vec!["out.ppm"];
            match before {
                "nothing" => {}
                "a file" => std::fs::write(&path, "old").unwrap(),
                "a file with a second name" => {
                    std::fs::write(&path, "old").unwrap();
                    std::fs::hard_link(&path, dir.path().join("keep")).unwrap();
                    expected.push("keep");
                }
                _ => {
                    std::fs::write(dir.path().join("target"), "old").unwrap();
                    std::os::unix::fs::symlink("target", &path).unwrap();
                    expected.push("target");
                }
            }
            write_atomically(&path, b"new").unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), b"new", "{before}");
            assert!(
                std::fs::symlink_metadata(&path).unwrap().is_file(),
                "{before}"
            );
            expected.sort();
            assert_eq!(
                names_in(dir.path()),
                expected,
                "{before}: no temporary left"
            );
            for other in ["keep", "target"].map(|name| dir.path().join(name)) {
                if other.exists() {
                    assert_eq!(std::fs::read(&other).unwrap(), b"old", "{before}");
                }
            }
        }
    }

    #[test]
    fn a_folder_at_the_path_is_left_whole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.ppm");
        std::fs::create_dir(&path).unwrap();
        std::fs::write(path.join("inside"), "kept").unwrap();
        assert!(write_atomically(&path, b"new").is_err());
        assert_eq!(std::fs::read(path.join("inside")).unwrap(), b"kept");
        assert_eq!(names_in(dir.path()), ["out.ppm"], "no temporary left");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_folder_exchanged_in_by_a_race_is_exchanged_back() {
        // A folder that takes the old file's place after the check is moved to the
        // temporary name by the exchange; it must go back, and the write fail as a rename
        // onto a folder does.
        let dir = tempfile::tempdir().unwrap();
        let (temporary, path) = (dir.path().join(".new.tmp"), dir.path().join("out.ppm"));
        std::fs::write(&temporary, "new").unwrap();
        std::fs::create_dir(&path).unwrap();
        std::fs::write(path.join("inside"), "kept").unwrap();
        exchange(&temporary, &path).unwrap();
        assert!(remove_exchanged(&temporary, &path).is_err());
        assert_eq!(std::fs::read(path.join("inside")).unwrap(), b"kept");
        assert_eq!(std::fs::read(&temporary).unwrap(), b"new");
    }

    /// A writer that takes at most `limit` bytes a call and is interrupted every third
    /// call, as a pipe or a signal may do.
    struct Trickle {
        written: Vec<u8>,
        limit: usize,
        calls: usize,
    }

    impl Write for Trickle {
        fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
            self.calls += 1;
            if self.calls.is_multiple_of(3) {
                return Err(io::ErrorKind::Interrupted.into());
            }
            let n = bytes.len().min(self.limit);
            self.written.extend_from_slice(&bytes[..n]);
            Ok(n)
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn every_part_is_written_whole_and_in_order_however_the_writer_splits_it() {
        // More parts than one call takes, some empty, of uneven lengths.
        let parts: Vec<Vec<u8>> = (0..1500u32)
            .map(|i| (0..i % 11).map(|j| (i * 7 + j) as u8).collect())
            .collect();
        for limit in [1, 5, 64, usize::MAX] {
            let mut writer = Trickle {
                written: Vec::new(),
                limit,
                calls: 0,
            };
            write_all_vectored(&mut writer, &parts).unwrap();
            assert_eq!(
                writer.written,
                parts.concat(),
                "at most {limit} bytes a call"
            );
        }
    }

    #[test]
    fn no_call_is_offered_more_than_a_quarter_megabyte_or_512_slices() {
        // Takes whatever it is offered, and notes how much that was.
        struct Greedy {
            written: Vec<u8>,
            offered: Vec<(usize, usize)>,
        }
        impl Write for Greedy {
            fn write(&mut self, bytes: &[u8]) -> io::Result<usize> {
                self.write_vectored(&[IoSlice::new(bytes)])
            }
            fn write_vectored(&mut self, slices: &[IoSlice<'_>]) -> io::Result<usize> {
                let bytes: usize = slices.iter().map(|s| s.len()).sum();
                self.offered.push((bytes, slices.len()));
                for slice in slices {
                    self.written.extend_from_slice(slice);
                }
                Ok(bytes)
            }
            fn flush(&mut self) -> io::Result<()> {
                Ok(())
            }
        }
        // A part longer than two calls, many small ones, an empty one, a long one last.
        let part = |len: usize, seed: usize| -> Vec<u8> {
            (0..len).map(|i| (i * 31 + seed) as u8).collect()
        };
        let mut parts = vec![part(18, 1), part(600_000, 2)];
        parts.extend((0..1200).map(|i| part(100, i)));
        parts.push(Vec::new());
        parts.push(part(300_000, 3));
        let mut writer = Greedy {
            written: Vec::new(),
            offered: Vec::new(),
        };
        write_all_vectored(&mut writer, &parts).unwrap();
        assert!(writer.written == parts.concat());
        for &(bytes, slices) in &writer.offered {
            assert!(bytes <= 256 * 1024, "{bytes} bytes offered in one call");
            assert!(slices <= 512, "{slices} slices offered in one call");
            assert!(bytes > 0, "an empty call");
        }
    }

    #[test]
    fn images_of_every_size_start_black_on_either_side_of_the_parallel_threshold() {
        // Float32 pixels cross 1 MB at 262,144 values, bytes at 1,048,576.
        for n in [0, 1, 262_143, 262_144, 262_145, 1_048_577, 3_000_001] {
            let floats: Vec<f32> = zeroed(n);
            assert_eq!(floats.len(), n);
            assert!(floats.iter().all(|&x| x.to_bits() == 0), "{n} floats");
            let bytes: Vec<u8> = zeroed(n);
            assert_eq!(bytes.len(), n);
            assert!(bytes.iter().all(|&x| x == 0), "{n} bytes");
        }
    }

    #[test]
    fn a_tall_pfm_file_holds_every_row_bottom_first() {
        // 1100 rows: more rows than one system call is given.
        let (width, height) = (3, 1100);
        let mut image = Image::new(width, height, OutputFormat::Pfm, Encoding::Linear);
        for y in 0..height {
            for x in 0..width {
                image.set(x, y, [y as f64, x as f64, 0.5]);
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tall.pfm");
        image.write(&path).unwrap();
        let decoded = read(&path).unwrap();
        assert_eq!((decoded.width, decoded.height), (width, height));
        for y in 0..height {
            for x in 0..width {
                let pixel = decoded.pixels[(y * width + x) as usize];
                assert_eq!(pixel, [f64::from(y), f64::from(x), 0.5], "({x}, {y})");
            }
        }
        assert_eq!(std::fs::read(&path).unwrap(), image.to_bytes());
    }

    #[test]
    fn bad_images_are_refused_with_a_reason() {
        for (bytes, fragment) in [
            (&b"P5\n1 1\n255\n\0"[..], "not a PPM"),
            (b"P3\n2 1\n255\n1 2 3\n", "ends early"),
            (b"P3\n1 1\n255\n1 2 300\n", "exceeds maxval"),
            (b"P6\n2 2\n255\n\0\0\0", "bytes of pixel data"),
            (b"PF\n1 1\nabc\n", "scale"),
            (b"P3\nx 1\n255\n", "bad width"),
            // Headers claiming 10^10 pixels: refused for their data, not by exhausting memory.
            (b"P6\n100000 100000\n255\n\0\0\0", "bytes of pixel data"),
            (b"P3\n100000 100000\n255\n1 2 3\n", "ends early"),
            (b"PF\n100000 100000\n-1.0\n\0\0\0\0", "bytes of pixel data"),
        ] {
            let error = decode(bytes).unwrap_err();
            assert!(error.contains(fragment), "{error}");
        }
    }

    #[test]
    fn pfm_rows_are_stored_bottom_first() {
        let mut image = Image::new(2, 2, OutputFormat::Pfm, Encoding::Srgb);
        image.set(0, 0, [1.0, 2.0, 3.0]);
        image.set(1, 1, [4.0, 5.0, 6.0]);
        let bytes = image.to_bytes();
        let header = b"PF\n2 2\n-1.0\n";
        assert_eq!(&bytes[..header.len()], header);
        let floats: Vec<f32> = bytes[header.len()..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        // Bottom row first: (0,1), (1,1), then (0,0), (1,0). PFM is never sRGB-encoded.
        assert_eq!(&floats[3..6], &[4.0, 5.0, 6.0]);
        assert_eq!(&floats[6..9], &[1.0, 2.0, 3.0]);
    }
}
