//! A parallel reader for the OBJ subset nearly every file uses. It gives exactly what the
//! `tobj` reader gives (same vertices in the same order, same triangles), and declines
//! (returns `None`) everything else, so that `tobj` reads it. The subset:
//!
//! - valid UTF-8, read line by line and word by word as `tobj` reads it;
//! - `v x y z` with exactly three numbers; `vt` and `vn` with at least two and three
//!   (counted and checked, not kept);
//! - `f` with three or more corners `v`, `v/vt`, `v//vn` or `v/vt/vn`, each index counted
//!   from 1 or, if negative, back from the last element read, and referring to an
//!   element already read;
//! - `o` and `g` (a new object once the current one has faces), `usemtl` with a name, and
//!   every other keyword and comment (ignored, as `tobj` ignores them).
//!
//! Declined: a `v` with a weight or colours, points and lines (`l`), faces of fewer than
//! three corners, references to elements not yet read, and every fault.
//!
//! Lines of the commonest forms (`v` and three plain decimals, `f` and plain indices,
//! separated by spaces) are read straight from the bytes (`Chunk::common_line`); every
//! other line word by word.
//!
//! The text is cut into chunks at line ends, read in parallel. A chunk does not know how
//! many elements come before it, so it keeps negative indices relative to its own start
//! and notes the furthest reference either way; once the chunks' counts are summed, the
//! references are checked and resolved. A last pass numbers each object's vertices in
//! order of first use, as `tobj` does: in parallel over the chunks when the file is one
//! object, else in one pass.

use std::ops::Range;

use rayon::prelude::*;

use crate::mesh::{Geometry, MeshFile};

/// Bytes per chunk, about (chunks end at line ends).
const CHUNK: usize = 1 << 20;

/// Positions, texture coordinates, normals: what faces refer to.
const KINDS: usize = 3;

/// What one chunk contributes.
#[derive(Debug)]
struct Chunk {
    /// Elements of each kind read.
    counts: [usize; KINDS],
    positions: Vec<[f32; 3]>,
    /// Corners per face, and every face's corners as position indices (from 0, over the
    /// whole file; a relative index holds a placeholder until it is resolved).
    arities: Vec<u32>,
    corners: Vec<u32>,
    /// Relative position indices: where in `corners`, and the index counted from the
    /// chunk's first position (negative for one in an earlier chunk).
    relative: Vec<(usize, i64)>,
    /// Per kind, the largest `index − elements read so far` over indices counted from 1
    /// (must stay below the elements before the chunk), and the smallest index counted
    /// from the chunk's start over negative ones (must not reach before the file's start).
    forward: [i64; KINDS],
    backward: [i64; KINDS],
    /// For each `o` or `g` line, the faces of the chunk read before it.
    breaks: Vec<usize>,
}

impl Chunk {
    fn new() -> Chunk {
        Chunk {
            counts: [0; KINDS],
            positions: Vec::new(),
            arities: Vec::new(),
            corners: Vec::new(),
            relative: Vec::new(),
            forward: [i64::MIN; KINDS],
            backward: [i64::MAX; KINDS],
            breaks: Vec::new(),
        }
    }
}

/// The file's mesh, or `None` if the file is outside the subset (see the module doc).
pub fn parse(bytes: &[u8]) -> Option<MeshFile> {
    parse_in_chunks(bytes, CHUNK)
}

/// [`parse`] with chunks of about `chunk` bytes (tests use tiny ones).
pub(super) fn parse_in_chunks(bytes: &[u8], chunk: usize) -> Option<MeshFile> {
    // Chunks end after a line feed, which is never part of a longer UTF-8 sequence, so
    // each chunk is valid UTF-8 exactly when the whole text is: they are checked in
    // parallel, with the rest of each chunk's reading.
    let mut chunks: Vec<Chunk> = chunks(bytes, chunk.max(1))
        .into_par_iter()
        .map(|r| read(std::str::from_utf8(&bytes[r]).ok()?))
        .collect::<Option<_>>()?;
    // What comes before each chunk is now known: check and resolve its references.
    let mut before = [0usize; KINDS];
    for chunk in &mut chunks {
        for (kind, seen) in before.iter_mut().enumerate() {
            let start = *seen as i64;
            if chunk.forward[kind] >= start || chunk.backward[kind].saturating_add(start) < 0 {
                return None;
            }
            *seen += chunk.counts[kind];
        }
        let start = (before[0] - chunk.counts[0]) as i64;
        for &(at, index) in &chunk.relative {
            chunk.corners[at] = u32::try_from(start + index).ok()?;
        }
    }
    if u32::try_from(before[0]).is_err() {
        return None;
    }
    Some(assemble(&chunks, before[0]))
}

/// Ranges of about `size` bytes, each ending just after a line end (or at the end).
fn chunks(bytes: &[u8], size: usize) -> Vec<Range<usize>> {
    let mut ranges = Vec::new();
    let mut start = 0;
    while start < bytes.len() {
        let mut end = (start + size).min(bytes.len());
        if let Some(newline) = bytes[end..].iter().position(|&b| b == b'\n') {
            end += newline + 1;
        } else {
            end = bytes.len();
        }
        ranges.push(start..end);
        start = end;
    }
    ranges
}

/// Reads one chunk.
fn read(text: &str) -> Option<Chunk> {
    let mut out = Chunk::new();
    for_each_line(text, |words, line| {
        if let Words::Ascii { text, at } = words
            && let Some(end) = out.common_line(text.as_bytes(), *at)
        {
            *at = end;
            return Some(());
        }
        match words.next() {
            Some("v") => {
                let mut p = [0f32; 3];
                for c in &mut p {
                    *c = words.number()?;
                }
                if words.next().is_some() {
                    return None;
                }
                out.positions.push(p);
                out.counts[0] += 1;
            }
            Some("vt") => {
                numbers(words, 2)?;
                out.counts[1] += 1;
            }
            Some("vn") => {
                numbers(words, 3)?;
                out.counts[2] += 1;
            }
            Some("f") => {
                let before = out.corners.len();
                while let Some(word) = words.integer() {
                    match word {
                        Ok(position) => out.position(position)?,
                        Err(corner) => out.corner(corner.as_bytes())?,
                    }
                }
                let arity = out.corners.len() - before;
                if arity < 3 {
                    return None;
                }
                out.arities.push(arity as u32);
            }
            Some("o" | "g") => out.breaks.push(out.arities.len()),
            // As tobj reads the name: after the first space.
            Some("usemtl")
                if line
                    .get()
                    .split_once(' ')
                    .unwrap_or_default()
                    .1
                    .trim()
                    .is_empty() =>
            {
                return None;
            }
            Some("l") => return None,
            _ => {}
        }
        Some(())
    })?;
    Some(out)
}

/// Calls `f` with the words of each line (as `str::split_whitespace`, and so `tobj`,
/// finds them) and the line; stops at the first `None`. ASCII text is scanned byte by
/// byte in one pass, which finds the same words much faster.
fn for_each_line<'a>(
    text: &'a str,
    mut f: impl FnMut(&mut Words<'a>, Line<'a>) -> Option<()>,
) -> Option<()> {
    if !text.is_ascii() {
        let mut start = 0;
        for line in text.split('\n') {
            f(
                &mut Words::Unicode(line.split_whitespace()),
                Line { text, start },
            )?;
            start += line.len() + 1;
        }
        return Some(());
    }
    let bytes = text.as_bytes();
    let mut at = 0;
    while at < bytes.len() {
        let mut words = Words::Ascii { text, at };
        f(&mut words, Line { text, start: at })?;
        // Past what the handler left unread, and the line end.
        if let Words::Ascii { at: stop, .. } = words {
            at = stop;
        }
        while at < bytes.len() && bytes[at] != b'\n' {
            at += 1;
        }
        at += 1;
    }
    Some(())
}

/// A line of the text, found only if asked for.
#[derive(Clone, Copy)]
struct Line<'a> {
    text: &'a str,
    start: usize,
}

impl<'a> Line<'a> {
    fn get(self) -> &'a str {
        let rest = &self.text[self.start..];
        rest.split('\n').next().unwrap_or_default()
    }
}

/// The words of one line: ASCII text scanned from `at` up to (not past) the line end,
/// or any text by `split_whitespace`.
enum Words<'a> {
    Ascii { text: &'a str, at: usize },
    Unicode(std::str::SplitWhitespace<'a>),
}

/// The ASCII characters that are Unicode white space, other than the line feed: tab,
/// vertical tab, form feed, carriage return and space.
#[inline(always)]
fn is_space(b: u8) -> bool {
    ends_word(b) && b != b'\n'
}

/// Whether `b` is white space or the line feed: one bit of a mask for bytes up to the
/// space, so the usual word byte (above it) costs one comparison.
#[inline(always)]
fn ends_word(b: u8) -> bool {
    const MASK: u64 = 1 << b'\t' | 1 << b'\n' | 1 << 0x0b | 1 << 0x0c | 1 << b'\r' | 1 << b' ';
    b <= b' ' && MASK >> b & 1 == 1
}

impl<'a> Iterator for Words<'a> {
    type Item = &'a str;

    #[inline]
    fn next(&mut self) -> Option<&'a str> {
        let (text, at) = match self {
            Words::Ascii { text, at } => (*text, at),
            Words::Unicode(words) => return words.next(),
        };
        let bytes = text.as_bytes();
        let start = word_start(bytes, at)?;
        while *at < bytes.len() && !ends_word(bytes[*at]) {
            *at += 1;
        }
        Some(&text[start..*at])
    }
}

impl<'a> Words<'a> {
    /// The next word read as [`number`] reads it; `None` at the line's end or if the word
    /// is not a number. In ASCII text a plain decimal is read as the word is scanned,
    /// rather than found first and read after.
    #[inline]
    fn number(&mut self) -> Option<f32> {
        if let Words::Ascii { text, at } = self {
            let bytes = text.as_bytes();
            let start = word_start(bytes, at)?;
            if let Some((value, end)) = whole_word(bytes, start, plain_decimal_prefix) {
                *at = end;
                return Some(value);
            }
        }
        number(self.next()?)
    }

    /// The next word: `Ok` with its value if it is an integer, read as the word is scanned
    /// (ASCII text only), else `Err` with the word; `None` at the line's end.
    #[inline]
    fn integer(&mut self) -> Option<Result<isize, &'a str>> {
        if let Words::Ascii { text, at } = self {
            let bytes = text.as_bytes();
            let start = word_start(bytes, at)?;
            if let Some((value, end)) = whole_word(bytes, start, integer_prefix) {
                *at = end;
                return Some(Ok(value));
            }
        }
        self.next().map(Err)
    }
}

/// Moves `at` past spaces to the start of the next word of its line, if there is one.
#[inline(always)]
fn word_start(bytes: &[u8], at: &mut usize) -> Option<usize> {
    while *at < bytes.len() && is_space(bytes[*at]) {
        *at += 1;
    }
    (*at < bytes.len() && bytes[*at] != b'\n').then_some(*at)
}

/// What `prefix` reads of `word`, if it reads all of it.
#[inline(always)]
fn whole<T>(word: &[u8], prefix: impl Fn(&[u8]) -> Option<(T, usize)>) -> Option<T> {
    prefix(word)
        .filter(|&(_, length)| length == word.len())
        .map(|(value, _)| value)
}

/// What `prefix` reads at `start`, and where it stops, if it stops at the end of the word.
#[inline(always)]
fn whole_word<T>(
    bytes: &[u8],
    start: usize,
    prefix: impl Fn(&[u8]) -> Option<(T, usize)>,
) -> Option<(T, usize)> {
    let (value, length) = prefix(&bytes[start..])?;
    let end = start + length;
    (end == bytes.len() || ends_word(bytes[end])).then_some((value, end))
}

/// A number as `f32::from_str` reads it (`None` where it fails). Plain decimals take a
/// shorter way to the same value (see [`plain_decimal`]); anything else goes to the
/// standard library.
fn number(word: &str) -> Option<f32> {
    plain_decimal(word.as_bytes()).or_else(|| word.parse().ok())
}

/// Powers of ten exact in `f64`: `10^k` for `k <= 22` (`5^22 < 2^53`).
const POWERS_OF_TEN: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// The value of `[+|-]digits[.digits]` (at least one digit) whose digits, read as one
/// integer `m`, make at most `2^53`, with `k <= 22` of them after the point; `None` for
/// anything else, and for the rare values it cannot settle (below).
///
/// `m` and `10^k` are exact in `f64`, so one division gives `d`, the `f64` nearest to
/// `m / 10^k` (Clinger's fast path). Rounding `d` to `f32` gives the `f32` nearest to
/// `m / 10^k`, as `f32::from_str` does, unless `d` is exactly halfway between two
/// `f32`s: any other `f32` rounding boundary between `d` and the true value would be an
/// `f64` nearer to it than `d`. Halfway cases are left to the standard library.
fn plain_decimal(word: &[u8]) -> Option<f32> {
    whole(word, plain_decimal_prefix)
}

/// [`plain_decimal`] of the longest start of `text` made of a sign, digits and a point, and
/// that start's length.
#[inline(always)]
fn plain_decimal_prefix(text: &[u8]) -> Option<(f32, usize)> {
    let (negative, sign) = sign(text);
    let (mut m, whole) = append_digits(&text[sign..], 0, 1 << 53)?;
    let mut length = sign + whole;
    // Digits in all, and after the point.
    let (mut count, mut k) = (whole, 0);
    if text.get(length) == Some(&b'.') {
        (m, k) = append_digits(&text[length + 1..], m, 1 << 53)?;
        (count, length) = (count + k, length + 1 + k);
        if text.get(length) == Some(&b'.') {
            return None;
        }
    }
    if count == 0 || k >= POWERS_OF_TEN.len() {
        return None;
    }
    // `m / 10^k` lies in [1e-22, 2^53] (or is 0), well inside the normal `f32` range,
    // so rounding to `f32` drops exactly the low 29 of the 52 fraction bits.
    let d = m as f64 / POWERS_OF_TEN[k];
    const DROPPED: u64 = (1 << 29) - 1;
    if d.to_bits() & DROPPED == 1 << 28 {
        return None;
    }
    let value = d as f32;
    Some((if negative { -value } else { value }, length))
}

/// Checks that the next `n` words are numbers.
fn numbers(words: &mut Words<'_>, n: usize) -> Option<()> {
    for _ in 0..n {
        words.number()?;
    }
    Some(())
}

impl Chunk {
    /// Reads the line at `at` if it has the most common form: `v` and three plain
    /// decimals, or `f` and three or more positive position indices, each word after one
    /// or more spaces, the line ending in a line feed (perhaps after a carriage return)
    /// or the text's end. Returns where the line ends, having added what the general
    /// reader would add; `None`, having added nothing, for any other line. Most lines of
    /// large files have this form; found word by word first, as the general reader finds
    /// them, they took a quarter more instructions.
    #[inline(always)]
    fn common_line(&mut self, bytes: &[u8], at: usize) -> Option<usize> {
        match bytes.get(at..)?.first_chunk::<2>()? {
            [b'v', b' '] => {
                let mut p = [0f32; 3];
                let mut word = at + 1;
                for (i, c) in p.iter_mut().enumerate() {
                    word = next_word(bytes, word)?;
                    let (value, length) = plain_decimal_prefix(&bytes[word..])?;
                    (*c, word) = (value, word + length);
                    if i < 2 && bytes.get(word) != Some(&b' ') {
                        return None;
                    }
                }
                let end = line_end(bytes, word)?;
                self.positions.push(p);
                self.counts[0] += 1;
                Some(end)
            }
            [b'f', b' '] => {
                let (corners, forward) = (self.corners.len(), self.forward[0]);
                let Some(end) = self.common_face(bytes, at + 1) else {
                    // Undone, for the general reader to read the line again.
                    self.corners.truncate(corners);
                    self.forward[0] = forward;
                    return None;
                };
                self.arities.push((self.corners.len() - corners) as u32);
                Some(end)
            }
            _ => None,
        }
    }

    /// The corners of a face line in [`Chunk::common_line`]'s form, from `at` (past the
    /// `f`), each added as it is read; where the line ends, or `None` if it has another
    /// form (the caller undoes what was added). An index of up to seven digits is read,
    /// with the byte after it, from one 8-byte load: an eighth fewer instructions in
    /// reading the scans and the torus than through [`append_digits`].
    #[inline(always)]
    fn common_face(&mut self, bytes: &[u8], mut at: usize) -> Option<usize> {
        let (first, read) = (self.corners.len(), self.counts[0] as i64);
        loop {
            at = next_word(bytes, at)?;
            // An index of up to seven digits, and the byte after it, in one load.
            if let Some(&eight) = bytes.get(at..).and_then(<[u8]>::first_chunk::<8>) {
                let word = u64::from_le_bytes(eight);
                let digits = leading_digits(word);
                if (1..8).contains(&digits) {
                    let position = digits_value(word, digits).checked_sub(1)?;
                    self.forward[0] = self.forward[0].max(position as i64 - read);
                    self.corners.push(position as u32);
                    at += digits;
                    if (word >> (8 * digits)) as u8 == b' ' {
                        continue;
                    }
                    return if self.corners.len() - first >= 3 {
                        line_end(bytes, at)
                    } else {
                        None
                    };
                }
            }
            if bytes.get(at).is_some_and(u8::is_ascii_digit) {
                let (index, length) = append_digits(&bytes[at..], 0, u32::MAX.into())?;
                let position = index.checked_sub(1)?;
                self.forward[0] = self.forward[0].max(position as i64 - read);
                self.corners.push(position as u32);
                at += length;
                if bytes.get(at) == Some(&b' ') {
                    continue;
                }
            }
            // Not a corner, or no space after one: the line must end here.
            return if self.corners.len() - first >= 3 {
                line_end(bytes, at)
            } else {
                None
            };
        }
    }

    /// Adds a face corner `v`, `v/vt`, `v//vn` or `v/vt/vn` (empty parts skipped, as
    /// `tobj` skips them), noting how far its indices reach.
    fn corner(&mut self, corner: &[u8]) -> Option<()> {
        let mut parts = corner.split(|&b| b == b'/');
        self.position(integer(parts.next()?)?)?;
        for kind in 1..KINDS {
            match parts.next() {
                Some([]) | None => {}
                Some(part) => {
                    let _checked = self.reference(integer(part)?, kind)?;
                }
            }
        }
        if parts.any(|p| !p.is_empty()) {
            return None;
        }
        Some(())
    }

    /// Adds a face corner given by its position index alone.
    #[inline]
    fn position(&mut self, index: isize) -> Option<()> {
        match self.reference(index, 0)? {
            Ok(index) => self.corners.push(index),
            Err(relative) => {
                self.relative.push((self.corners.len(), relative));
                self.corners.push(0);
            }
        }
        Some(())
    }

    /// An index of `kind` counted from 1 (`Ok`, from 0) or back from the last element
    /// read (`Err`, from the chunk's first element), its reach noted.
    #[inline]
    fn reference(&mut self, index: isize, kind: usize) -> Option<Result<u32, i64>> {
        let index = i64::try_from(index).ok()?;
        let read = self.counts[kind] as i64;
        if index > 0 {
            self.forward[kind] = self.forward[kind].max(index - 1 - read);
            Some(Ok(u32::try_from(index - 1).ok()?))
        } else if index < 0 {
            self.backward[kind] = self.backward[kind].min(read + index);
            Some(Err(read + index))
        } else {
            None
        }
    }
}

/// The start of the next word after one or more spaces at `at`; `None` if there is no
/// space at `at`.
#[inline(always)]
fn next_word(bytes: &[u8], mut at: usize) -> Option<usize> {
    if bytes.get(at) != Some(&b' ') {
        return None;
    }
    while bytes.get(at) == Some(&b' ') {
        at += 1;
    }
    Some(at)
}

/// Where the line ends if it ends at `at`: at a line feed, at one after a carriage return,
/// or at the text's end.
#[inline(always)]
fn line_end(bytes: &[u8], at: usize) -> Option<usize> {
    match bytes.get(at) {
        None | Some(b'\n') => Some(at),
        Some(b'\r') if matches!(bytes.get(at + 1), None | Some(b'\n')) => Some(at + 1),
        _ => None,
    }
}

/// An integer as `isize::from_str` reads it: an optional sign and at least one digit.
fn integer(word: &[u8]) -> Option<isize> {
    whole(word, integer_prefix)
}

/// [`integer`] of the longest start of `text` made of a sign and digits, and that start's
/// length.
#[inline(always)]
fn integer_prefix(text: &[u8]) -> Option<(isize, usize)> {
    let (negative, sign) = sign(text);
    let (magnitude, count) = append_digits(&text[sign..], 0, u64::MAX)?;
    let length = sign + count;
    let value = if negative {
        isize::try_from(-i128::from(magnitude)).ok()?
    } else {
        isize::try_from(magnitude).ok()?
    };
    (length > sign).then_some((value, length))
}

/// Whether `text` starts with a minus sign, and the length of its sign (`-` or `+`) if any.
#[inline(always)]
fn sign(text: &[u8]) -> (bool, usize) {
    match text.first() {
        Some(b'-') => (true, 1),
        Some(b'+') => (false, 1),
        _ => (false, 0),
    }
}

/// `value` followed by the decimal digits at the start of `text` (`value · 10^n + digits`),
/// and their count `n`; `None` if that would pass `limit`.
///
/// Digits are taken eight bytes at a time while eight remain ([`leading_digits`],
/// [`digits_value`]), a byte at a time at a text's end. Appending digits never lowers the
/// value, so checking `limit` once per eight digits rejects exactly what checking it after
/// each digit rejects.
#[inline(always)]
fn append_digits(text: &[u8], mut value: u64, limit: u64) -> Option<(u64, usize)> {
    let mut count = 0;
    while let Some(&eight) = text.get(count..).and_then(<[u8]>::first_chunk::<8>) {
        let bytes = u64::from_le_bytes(eight);
        let digits = leading_digits(bytes);
        if digits == 0 {
            return Some((value, count));
        }
        value = value
            .checked_mul(POWERS_OF_TEN_U64[digits])?
            .checked_add(digits_value(bytes, digits))?;
        if value > limit {
            return None;
        }
        count += digits;
        if digits < 8 {
            return Some((value, count));
        }
    }
    let (value, rest) = append_digits_one_by_one(&text[count..], value, limit)?;
    Some((value, count + rest))
}

/// [`append_digits`] a digit at a time: for the last bytes of a text (and so of a word
/// read on its own).
#[inline(never)]
fn append_digits_one_by_one(text: &[u8], mut value: u64, limit: u64) -> Option<(u64, usize)> {
    let mut count = 0;
    while let Some(&c @ b'0'..=b'9') = text.get(count) {
        value = value.checked_mul(10)?.checked_add(u64::from(c - b'0'))?;
        if value > limit {
            return None;
        }
        count += 1;
    }
    Some((value, count))
}

/// `10^k` for `k <= 8`.
const POWERS_OF_TEN_U64: [u64; 9] = [
    1,
    10,
    100,
    1_000,
    10_000,
    100_000,
    1_000_000,
    10_000_000,
    100_000_000,
];

/// How many of the eight bytes of `bytes` (the first in its lowest byte) are ASCII digits
/// before the first that is not (8 if all are). A byte `b` is a digit when neither
/// `b − '0'` nor `b + 0x46` sets its top bit; the first byte that is not a digit sets
/// one of them, and the borrows and carries it may pass on reach only bytes after it.
#[inline(always)]
fn leading_digits(bytes: u64) -> usize {
    const ZEROS: u64 = 0x3030_3030_3030_3030;
    const PAST_NINE: u64 = 0x4646_4646_4646_4646;
    const TOP_BITS: u64 = 0x8080_8080_8080_8080;
    let not_digits = (bytes.wrapping_sub(ZEROS) | bytes.wrapping_add(PAST_NINE)) & TOP_BITS;
    (not_digits.trailing_zeros() / 8) as usize
}

/// The value of the first `digits` bytes of `bytes` (1 to 8 ASCII digits, the first in
/// the lowest byte, most significant first). The digits are moved to the top bytes, so
/// the bytes below them count as leading zeros, and combined in pairs, fours and eights
/// by three multiplications.
#[inline(always)]
fn digits_value(bytes: u64, digits: usize) -> u64 {
    let eight = (bytes & 0x0f0f_0f0f_0f0f_0f0f) << (8 * (8 - digits));
    let pairs = (eight.wrapping_mul(10 << 8 | 1) >> 8) & 0x00ff_00ff_00ff_00ff;
    let fours = (pairs.wrapping_mul(100 << 16 | 1) >> 16) & 0x0000_ffff_0000_ffff;
    fours.wrapping_mul(10_000 << 32 | 1) >> 32
}

/// One geometry: objects in file order, each object's vertices numbered in order of first
/// use, polygons as fans from their first corner. A file of one object (every `o` or `g`
/// before the first face, as in most large files) is numbered in parallel.
fn assemble(chunks: &[Chunk], vertices: usize) -> MeshFile {
    let first_face_chunk = chunks.iter().position(|c| !c.arities.is_empty());
    let one_object = first_face_chunk.is_none_or(|first| {
        chunks[first].breaks.iter().all(|&b| b == 0)
            && chunks[first + 1..].iter().all(|c| c.breaks.is_empty())
    });
    if one_object {
        assemble_one_object(chunks, vertices)
    } else {
        assemble_in_order(chunks, vertices)
    }
}

/// Not yet assigned: no chunk owns the vertex, or its owner has not numbered it.
const UNSET: u32 = u32::MAX;

/// [`assemble`] for a file of one object, in parallel over the chunks. A vertex's index is
/// the number of distinct vertices first used before it. Each vertex belongs to the first
/// chunk that uses it; each chunk numbers its own vertices in order of first use; the
/// counts of the chunks before it then give each chunk's first index.
fn assemble_one_object(chunks: &[Chunk], vertices: usize) -> MeshFile {
    use std::sync::atomic::{AtomicU32, Ordering::Relaxed};
    let all = all_positions(chunks);
    let owner: Vec<AtomicU32> = (0..vertices).map(|_| AtomicU32::new(UNSET)).collect();
    chunks.par_iter().enumerate().for_each(|(c, chunk)| {
        let c = c as u32;
        for &v in &chunk.corners {
            // Loaded first: most corners repeat a vertex this chunk has already claimed.
            if owner[v as usize].load(Relaxed) > c {
                owner[v as usize].fetch_min(c, Relaxed);
            }
        }
    });
    // Each chunk's own vertices, in order of first use: their index within the chunk is
    // kept in `local` (written only by the owner).
    let local: Vec<AtomicU32> = (0..vertices).map(|_| AtomicU32::new(UNSET)).collect();
    let owned: Vec<Vec<u32>> = chunks
        .par_iter()
        .enumerate()
        .map(|(c, chunk)| {
            let mut own = Vec::new();
            for &v in &chunk.corners {
                let v = v as usize;
                if owner[v].load(Relaxed) == c as u32 && local[v].load(Relaxed) == UNSET {
                    local[v].store(own.len() as u32, Relaxed);
                    own.push(v as u32);
                }
            }
            own
        })
        .collect();
    let mut first_index = Vec::with_capacity(chunks.len());
    let mut total = 0u32;
    for own in &owned {
        first_index.push(total);
        total += own.len() as u32;
    }
    let mut positions = vec![[0f32; 3]; total as usize];
    split_by_lengths(&mut positions, owned.iter().map(Vec::len))
        .into_par_iter()
        .zip(&owned)
        .for_each(|(part, own)| {
            for (p, &v) in part.iter_mut().zip(own) {
                *p = all[v as usize];
            }
        });
    let fans = |chunk: &Chunk| chunk.arities.iter().map(|&a| a as usize - 2).sum::<usize>();
    let mut triangles = vec![[0u32; 3]; chunks.iter().map(fans).sum()];
    split_by_lengths(&mut triangles, chunks.iter().map(fans))
        .into_par_iter()
        .zip(chunks)
        .for_each(|(part, chunk)| {
            let index = |v: u32| {
                let v = v as usize;
                first_index[owner[v].load(Relaxed) as usize] + local[v].load(Relaxed)
            };
            let mut out = part.iter_mut();
            let mut corners = chunk.corners.as_slice();
            for &arity in &chunk.arities {
                let (face, tail) = corners.split_at(arity as usize);
                corners = tail;
                let first = index(face[0]);
                for pair in face[1..].windows(2) {
                    *out.next().expect("counted above") = [first, index(pair[0]), index(pair[1])];
                }
            }
        });
    MeshFile::one_geometry(Geometry {
        positions,
        triangles,
    })
}

/// `items` cut into consecutive parts of the given lengths (which must not sum past it).
fn split_by_lengths<T>(mut items: &mut [T], lengths: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    lengths
        .map(|len| {
            let (part, rest) = std::mem::take(&mut items).split_at_mut(len);
            items = rest;
            part
        })
        .collect()
}

/// [`assemble`] in one pass over the faces, for any number of objects.
fn assemble_in_order(chunks: &[Chunk], vertices: usize) -> MeshFile {
    let all = all_positions(chunks);
    let mut geometry = Geometry {
        positions: Vec::new(),
        triangles: Vec::with_capacity(chunks.iter().map(|c| c.corners.len()).sum::<usize>() / 3),
    };
    // `object_of[v]` is the object that last used vertex `v`, `index_of[v]` its index.
    let mut object_of = vec![u32::MAX; vertices];
    let mut index_of = vec![0u32; vertices];
    let mut object = 0u32;
    let mut faces_in_object = 0usize;
    let mut face = Vec::new();
    for chunk in chunks {
        let mut breaks = chunk.breaks.iter().peekable();
        let mut corner = 0;
        for (f, &arity) in chunk.arities.iter().enumerate() {
            while breaks.next_if(|&&b| b <= f).is_some() {
                if faces_in_object > 0 {
                    object += 1;
                    faces_in_object = 0;
                }
            }
            face.clear();
            for &v in &chunk.corners[corner..corner + arity as usize] {
                let v = v as usize;
                if object_of[v] != object {
                    object_of[v] = object;
                    index_of[v] = geometry.positions.len() as u32;
                    geometry.positions.push(all[v]);
                }
                face.push(index_of[v]);
            }
            corner += arity as usize;
            for k in 1..face.len() - 1 {
                geometry.triangles.push([face[0], face[k], face[k + 1]]);
            }
            faces_in_object += 1;
        }
        if breaks.next().is_some() && faces_in_object > 0 {
            object += 1;
            faces_in_object = 0;
        }
    }
    MeshFile::one_geometry(geometry)
}

/// Every position read, in file order.
fn all_positions(chunks: &[Chunk]) -> Vec<[f32; 3]> {
    chunks
        .iter()
        .flat_map(|c| c.positions.iter().copied())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_white_space_is_what_unicode_calls_white_space() {
        for b in 0u8..128 {
            let space = is_space(b) || b == b'\n';
            assert_eq!(space, char::from(b).is_whitespace(), "byte {b}");
        }
    }

    #[test]
    fn integers_are_read_as_the_standard_library_reads_them() {
        let words = [
            "0",
            "1",
            "+1",
            "-1",
            "-",
            "+",
            "",
            "12a",
            "007",
            "-0",
            "+-1",
            "1 ",
            "9223372036854775807",
            "9223372036854775808",
            "-9223372036854775808",
            "-9223372036854775809",
            "١",
        ];
        for word in words {
            assert_eq!(
                integer(word.as_bytes()),
                word.parse::<isize>().ok(),
                "{word:?}"
            );
        }
    }

    #[test]
    fn digits_are_appended_as_their_value_in_128_bits_or_refused_past_the_limit() {
        // A run of up to 30 digits, then a byte that ends it (every byte value that is not
        // a digit, including UTF-8 lead bytes) and more digits, or nothing; appended to
        // values near the limits.
        let mut random = crate::test_random::XorShift::new(0x2545_f491_4f6c_dd1d);
        let enders: Vec<u8> = (0..=255u8).filter(|b| !b.is_ascii_digit()).collect();
        let limits = [1u64 << 53, u64::from(u32::MAX), u64::MAX];
        let starts = [0, 1, 9, 1 << 40, (1 << 53) / 1000, u64::MAX / 10, u64::MAX];
        for case in 0..100_000 {
            let run: String = (0..random.below(31))
                .map(|_| char::from(b'0' + random.below(10) as u8))
                .collect();
            let mut text = run.clone().into_bytes();
            if case % 4 != 0 {
                text.push(enders[random.below(enders.len() as u64) as usize]);
                text.extend((0..random.below(12)).map(|_| b'0' + random.below(10) as u8));
            }
            let start = starts[random.below(starts.len() as u64) as usize];
            let limit = limits[random.below(limits.len() as u64) as usize];
            let expected = if run.is_empty() {
                Some((start, 0))
            } else {
                // The run's value, below 10^30 < 2^100, appended in 128 bits.
                let digits: u128 = run.parse().unwrap();
                10u128
                    .checked_pow(run.len() as u32)
                    .and_then(|scale| u128::from(start).checked_mul(scale))
                    .and_then(|v| v.checked_add(digits))
                    .filter(|&v| v <= u128::from(limit))
                    .map(|v| (v as u64, run.len()))
            };
            assert_eq!(
                append_digits(&text, start, limit),
                expected,
                "{start} then {:?}, limit {limit}",
                String::from_utf8_lossy(&text)
            );
        }
    }

    #[test]
    fn words_read_in_one_pass_are_the_words_found_and_then_read() {
        // Words that start as a number or an integer and may go on as something else,
        // each followed by every way a word can end (or not end: `/`).
        let words = [
            "0",
            "-0",
            "+7",
            "12",
            "1.5",
            "-.5",
            "1.",
            ".",
            "-",
            "+",
            "1.5e3",
            "1e3",
            "12a",
            "1..2",
            "1.2.3",
            "0x10",
            "7/8",
            "7//9",
            "9223372036854775807",
            "9223372036854775808",
            "00000000000000000000001",
            "123456789012345678901",
            "9007199254740993",
            "16777217",
        ];
        let endings = ["", " ", "\t", "\r\n", "\n", "\x0bx", "/2", " 5"];
        for word in words {
            for ending in endings {
                let text = format!("{word}{ending}");
                let found = || Words::Ascii { text: &text, at: 0 };
                let first = found().next();
                let mut words = found();
                assert_eq!(words.number(), first.and_then(number), "{text:?}");
                assert_eq!(words.next(), found().nth(1), "after a number: {text:?}");
                let mut words = found();
                let expected = first.map(|w| integer(w.as_bytes()).ok_or(w));
                assert_eq!(words.integer(), expected, "{text:?}");
                assert_eq!(words.next(), found().nth(1), "after an integer: {text:?}");
            }
        }
    }

    #[test]
    fn numbers_are_read_as_the_standard_library_reads_them() {
        let same = |word: &str| {
            let ours = number(word).map(f32::to_bits);
            let standard = word.parse::<f32>().ok().map(f32::to_bits);
            assert_eq!(ours, standard, "{word:?}");
        };
        let edges = [
            "0",
            "-0",
            "+0",
            "0.",
            ".0",
            ".",
            "-.",
            "-",
            "+",
            "",
            "1.",
            ".5",
            "-.5",
            "1..2",
            "1.2.3",
            "16777216",
            "16777217",
            "16777218",
            "-16777217",
            "1677721.7",
            "0.0000000001",
            "0.00000000001",
            "1e3",
            "1E-3",
            "inf",
            "-inf",
            "NaN",
            "0x10",
            "00000000000000000000001",
            "1_000",
            " 1",
            "1 ",
            "3.4028235e38",
            "3.5e38",
        ];
        for word in edges {
            same(word);
        }
        // Random plain decimals of up to twelve digits each side of the point, with a
        // seeded xorshift; and values exactly halfway between two `f32`s (an odd multiple
        // of half an `f32` step, written out in full).
        let mut random = crate::test_random::XorShift::new(0x9e37_79b9_7f4a_7c15);
        let mut next = |n: u64| random.below(n);
        for _ in 0..200_000 {
            let mut word = String::new();
            match next(3) {
                0 => word.push('-'),
                1 if next(4) == 0 => word.push('+'),
                _ => {}
            }
            for _ in 0..next(13) {
                word.push(char::from(b'0' + next(10) as u8));
            }
            if next(4) != 0 {
                word.push('.');
                for _ in 0..next(13) {
                    word.push(char::from(b'0' + next(10) as u8));
                }
            }
            same(&word);
        }
        for _ in 0..20_000 {
            // `(2a + 1) · 2^s` or `(2a + 1) / 2^j` with a 24-bit `a`: halfway between two
            // `f32`s.
            let odd = 2 * ((1 << 23) + next(1 << 23)) + 1;
            let j = next(13) as u32;
            let word = if next(2) == 0 {
                (odd << next(29)).to_string()
            } else {
                let digits = format!("{:0>width$}", odd * 5u64.pow(j), width = j as usize + 1);
                let point = digits.len() - j as usize;
                format!("{}.{}", &digits[..point], &digits[point..])
            };
            same(&word);
        }
    }
}
