//! Where each sample of a pixel goes.
//!
//! ```json
//! {"type": "center"}
//! {"type": "independent", "spp": 64, "seed": 1}
//! {"type": "stratified", "spp": 16}
//! ```
//!
//! Every random number is a hash of `(seed, pixel, sample, dimension)`, so a pixel's
//! samples do not depend on which thread renders it or in what order.
//!
//! Through a lens ([`Sampler::with_lens`]), with at most [`MOST_LENS_CELLS`] samples per
//! pixel, the stratified sampler stratifies the lens too: sample `s` of every pixel takes a
//! point of the lens grid's cell `s`, and each pixel pairs its offset cells with the lens
//! cells by a shuffle of its own ([`Sampler::shuffles`]), as pbrt's stratified sampler
//! shuffles each pixel's cells. A pixel still meets every cell of both grids once, every
//! offset cell is as likely as another to meet a given lens cell (so a pixel's mean stays
//! unbiased), and an 8 × 8 group's rays of one sample leave from one part of the lens, so
//! they stay together.

use crate::manifest::{SamplerDesc, SamplerKind};

/// The middle of `[0, 1)²`: every offset and lens point of the `center` sampler.
pub const CENTER: (f64, f64) = (0.5, 0.5);

/// Random dimensions used per sample: 0–1 the pixel offset, 2–3 the lens.
const DIM_PIXEL: u64 = 0;
const DIM_LENS: u64 = 2;

/// Most samples per pixel for which the stratified sampler stratifies the lens: a pixel's
/// shuffle of cells ([`CellShuffle`]) then fits in bytes. With more, lens points are
/// random, as with the `independent` sampler.
pub const MOST_LENS_CELLS: u32 = 256;

/// A pixel's offset cell for each of its samples through a stratified lens
/// ([`Sampler::shuffles`]): entry `s` is sample `s`'s cell.
pub type CellShuffle = [u8; MOST_LENS_CELLS as usize];

#[derive(Debug, Clone, Copy)]
pub struct Sampler {
    kind: SamplerKind,
    spp: u32,
    /// The seed's hash: the first step of every random number, taken once.
    seed_hash: u64,
    /// Stratified grid: `columns × rows = spp`, as square as `spp`'s divisors allow.
    columns: u32,
    /// The widest build of the group loops this CPU runs, chosen once.
    loops: Loops,
    /// Whether the stratified sampler stratifies the lens as well ([`Sampler::with_lens`]).
    lens_strata: bool,
}

/// Which build of the group loops ([`Sampler::pixel_hashes`], [`Sampler::group`]) runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Loops {
    /// AVX-512 F, DQ and VL: 64-bit products eight pixels at a time.
    Avx512,
    /// AVX2: four at a time, from 32-bit products.
    Avx2,
    Plain,
}

impl Loops {
    fn for_this_cpu() -> Loops {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512dq")
                && std::is_x86_feature_detected!("avx512vl")
            {
                return Loops::Avx512;
            }
            if std::is_x86_feature_detected!("avx2") {
                return Loops::Avx2;
            }
        }
        Loops::Plain
    }
}

impl Sampler {
    pub fn new(desc: &SamplerDesc) -> Sampler {
        let spp = desc.spp.max(1);
        let columns = (1..=spp)
            .take_while(|c| c * c <= spp)
            .filter(|&c| spp.is_multiple_of(c))
            .last()
            .unwrap_or(1);
        Sampler {
            kind: desc.kind,
            spp,
            seed_hash: mix(desc.seed ^ 0x9e37_79b9_7f4a_7c15),
            columns,
            loops: Loops::for_this_cpu(),
            lens_strata: false,
        }
    }

    /// The sampler for a camera with a lens (`lens`) or a pinhole (the default). With a
    /// lens and at most [`MOST_LENS_CELLS`] samples, the stratified sampler puts sample
    /// `s`'s lens point in the lens grid's cell `s` and shuffles each pixel's offset cells
    /// (the module's doc); a pinhole ignores lens points, and its offsets stay those of
    /// [`Sampler::new`]. The other kinds are the same either way.
    pub fn with_lens(self, lens: bool) -> Sampler {
        Sampler {
            // One sample's single cell is the whole lens: its numbers are the same either way.
            lens_strata: lens
                && self.kind == SamplerKind::Stratified
                && (2..=MOST_LENS_CELLS).contains(&self.spp),
            ..self
        }
    }

    /// Whether the lens is stratified, so that [`Sampler::group`] needs each pixel's
    /// [`Sampler::shuffles`].
    pub fn stratifies_lens(&self) -> bool {
        self.lens_strata
    }

    /// Each pixel's shuffle of offset cells, for the pixels whose
    /// [hashes](Sampler::pixel_hashes) are `pixel_hashes`, into `out[i]`: made once for all
    /// of a group's samples. Nothing unless the lens is stratified.
    ///
    /// # Panics
    /// If `out` is shorter than `pixel_hashes`.
    pub fn shuffles(&self, pixel_hashes: &[u64], out: &mut [CellShuffle]) {
        if !self.lens_strata {
            return;
        }
        let out = &mut out[..pixel_hashes.len()];
        match self.loops {
            // SAFETY: `loops` names only features the CPU has.
            #[cfg(target_arch = "x86_64")]
            Loops::Avx512 => unsafe { shuffles_avx512(pixel_hashes, self.spp, out) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            Loops::Avx2 => unsafe { shuffles_avx2(pixel_hashes, self.spp, out) },
            _ => shuffle_pixels(pixel_hashes, self.spp, out),
        }
    }

    pub fn spp(&self) -> u32 {
        self.spp
    }

    /// The offset every sample of every pixel takes, if it is fixed (`center`).
    pub fn fixed_offset(&self) -> Option<(f64, f64)> {
        match self.kind {
            SamplerKind::Center => Some(CENTER),
            SamplerKind::Independent | SamplerKind::Stratified => None,
        }
    }

    /// The offset of sample `s` within pixel `(x, y)`, in `[0, 1)²`.
    // Always inlined: a group's offsets are computed in a loop, whose hashes then overlap.
    #[inline(always)]
    pub fn pixel_offset(&self, x: u32, y: u32, s: u32) -> (f64, f64) {
        match self.kind {
            SamplerKind::Center => CENTER,
            _ => self.offset_from(self.pixel_hash(x, y), s),
        }
    }

    /// A point of `[0, 1)²` for the lens; the lens centre `(0.5, 0.5)` for `center`.
    #[inline(always)]
    pub fn lens(&self, x: u32, y: u32, s: u32) -> (f64, f64) {
        match self.kind {
            SamplerKind::Center => CENTER,
            _ => self.lens_from(self.pixel_hash(x, y), s),
        }
    }

    /// The hash of each pixel `(x, y0 + dy)` of `pixels`, into `out[i]`: where all of the
    /// pixel's numbers start, for [`Sampler::group`]. A group's pixels keep theirs through
    /// its samples, so the render loop hashes them once. Nothing for `center`.
    ///
    /// # Panics
    /// If `out` is shorter than `pixels`.
    pub fn pixel_hashes(&self, (pixels, y0): (&[(u32, u32)], u32), out: &mut [u64]) {
        if self.kind == SamplerKind::Center {
            return;
        }
        let out = &mut out[..pixels.len()];
        match self.loops {
            // SAFETY: `loops` names only features the CPU has.
            #[cfg(target_arch = "x86_64")]
            Loops::Avx512 => unsafe { hashes_avx512(self.seed_hash, (pixels, y0), out) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            Loops::Avx2 => unsafe { hashes_avx2(self.seed_hash, (pixels, y0), out) },
            _ => hash_pixels(self.seed_hash, (pixels, y0), out),
        }
    }

    /// [`Sampler::pixel_offset`] of sample `s` for each pixel whose
    /// [hash](Sampler::pixel_hashes) is `pixel_hashes[i]` (and, where the lens is
    /// stratified, whose [shuffle](Sampler::shuffles) is `shuffles[i]`; otherwise
    /// `shuffles` is not read), into `(u[i], v[i])`, and with `lens`, [`Sampler::lens`]
    /// into `lens[i]`: the same numbers, a group at a time. The stratum is found once for
    /// the group, and the loop is compiled for AVX-512 (whose 64-bit products hash eight
    /// pixels at once) or AVX2 (four, from 32-bit products) where the CPU has it.
    ///
    /// # Panics
    /// If the lens is stratified and `shuffles` is shorter than `pixel_hashes`.
    pub fn group(
        &self,
        (pixel_hashes, shuffles): (&[u64], &[CellShuffle]),
        s: u32,
        (u, v): (&mut [f64], &mut [f64]),
        lens: Option<&mut [(f64, f64)]>,
    ) {
        let n = pixel_hashes.len();
        let (u, v) = (&mut u[..n], &mut v[..n]);
        if self.kind == SamplerKind::Center {
            u.fill(CENTER.0);
            v.fill(CENTER.1);
            if let Some(lens) = lens {
                lens[..n].fill(CENTER);
            }
            return;
        }
        let shuffles = if self.lens_strata {
            &shuffles[..n]
        } else {
            &[]
        };
        let group = self.group_of((pixel_hashes, shuffles), s);
        match self.loops {
            // SAFETY: `loops` names only features the CPU has.
            #[cfg(target_arch = "x86_64")]
            Loops::Avx512 => unsafe { group_avx512(&group, u, v, lens) },
            // SAFETY: as above.
            #[cfg(target_arch = "x86_64")]
            Loops::Avx2 => unsafe { group_avx2(&group, u, v, lens) },
            _ => group_numbers(&group, u, v, lens),
        }
    }

    /// Sample `s` of the pixels whose hashes are `pixel_hashes`, for [`Sampler::group`].
    #[inline(always)]
    fn group_of<'a>(
        &self,
        (pixel_hashes, shuffles): (&'a [u64], &'a [CellShuffle]),
        s: u32,
    ) -> Group<'a> {
        Group {
            pixel_hashes,
            shuffles,
            s,
            stratum: self.stratum(s),
            lens_strata: self.lens_strata,
        }
    }

    /// The pixel offset of sample `s` of a random sampler, from its pixel's hash.
    #[inline(always)]
    fn offset_from(&self, pixel: u64, s: u32) -> (f64, f64) {
        match self.stratum(s) {
            Some([.., columns, rows]) if self.lens_strata => {
                let mut cells = [0; MOST_LENS_CELLS as usize];
                shuffle(pixel, self.spp, &mut cells);
                let cell = cell(u32::from(cells[s as usize]), [columns, rows]);
                in_cell(cell, unit_offset(pixel, s))
            }
            Some(cell) => in_cell(cell, unit_offset(pixel, s)),
            None => unit_offset(pixel, s),
        }
    }

    /// The lens point of sample `s` of a random sampler, from its pixel's hash.
    #[inline(always)]
    fn lens_from(&self, pixel: u64, s: u32) -> (f64, f64) {
        match self.stratum(s) {
            Some(cell) if self.lens_strata => in_cell(cell, lens_from(pixel, s)),
            _ => lens_from(pixel, s),
        }
    }

    /// For the stratified sampler, sample `s`'s cell: its column and row, and the grid's
    /// columns and rows ([`in_cell`]); `None` for the others.
    #[inline(always)]
    fn stratum(&self, s: u32) -> Option<[f64; 4]> {
        let grid = [self.columns, self.spp / self.columns].map(f64::from);
        (self.kind == SamplerKind::Stratified).then(|| cell(s, grid))
    }

    /// A uniform number in `[0, 1)` determined by the seed, pixel, sample and dimension.
    #[inline]
    pub fn random(&self, x: u32, y: u32, s: u32, dimension: u64) -> f64 {
        uniform(self.pixel_hash(x, y), s, dimension)
    }

    /// The hash of the seed and pixel, which every number of the pixel starts from.
    #[inline(always)]
    fn pixel_hash(&self, x: u32, y: u32) -> u64 {
        hash_pixel(self.seed_hash, x, y)
    }
}

/// A group of pixels' sample, for [`Sampler::group`].
struct Group<'a> {
    /// Each pixel's hash ([`Sampler::pixel_hashes`]).
    pixel_hashes: &'a [u64],
    /// Each pixel's shuffle of offset cells where the lens is stratified; empty otherwise.
    shuffles: &'a [CellShuffle],
    s: u32,
    /// For the stratified sampler, the sample's cell: its column and row, and the grid's
    /// columns and rows.
    stratum: Option<[f64; 4]>,
    /// Whether the lens is stratified: the cell is then the lens point's, and each pixel's
    /// offset takes the cell its own shuffle gives the sample.
    lens_strata: bool,
}

/// [`Sampler::pixel_hashes`] compiled for AVX-512.
///
/// # Safety
/// The CPU must have AVX-512 F, DQ and VL.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
unsafe fn hashes_avx512(seed_hash: u64, pixels: (&[(u32, u32)], u32), out: &mut [u64]) {
    hash_pixels(seed_hash, pixels, out);
}

/// [`Sampler::pixel_hashes`] compiled for AVX2.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn hashes_avx2(seed_hash: u64, pixels: (&[(u32, u32)], u32), out: &mut [u64]) {
    hash_pixels(seed_hash, pixels, out);
}

/// [`Sampler::pixel_hashes`] for the random and stratified samplers, in a loop free of
/// branches.
#[inline(always)]
fn hash_pixels(seed_hash: u64, (pixels, y0): (&[(u32, u32)], u32), out: &mut [u64]) {
    for (&(x, dy), out) in pixels.iter().zip(out) {
        *out = hash_pixel(seed_hash, x, y0 + dy);
    }
}

/// [`Sampler::shuffles`] compiled for AVX-512.
///
/// # Safety
/// The CPU must have AVX-512 F, DQ and VL.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
unsafe fn shuffles_avx512(pixel_hashes: &[u64], n: u32, out: &mut [CellShuffle]) {
    shuffle_pixels(pixel_hashes, n, out);
}

/// [`Sampler::shuffles`] compiled for AVX2.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn shuffles_avx2(pixel_hashes: &[u64], n: u32, out: &mut [CellShuffle]) {
    shuffle_pixels(pixel_hashes, n, out);
}

/// [`shuffle`] of each pixel whose hash is `pixel_hashes[i]` into `out[i]`, the pixels in
/// step: each step's choices first, a loop over the pixels that takes several at once,
/// then its swaps.
#[inline(always)]
fn shuffle_pixels(pixel_hashes: &[u64], n: u32, out: &mut [CellShuffle]) {
    const CHUNK: usize = 64;
    for (hashes, out) in pixel_hashes.chunks(CHUNK).zip(out.chunks_mut(CHUNK)) {
        let (mut keys, mut picks) = ([0u64; CHUNK], [0u32; CHUNK]);
        let (keys, picks) = (&mut keys[..hashes.len()], &mut picks[..hashes.len()]);
        for ((&p, key), cells) in hashes.iter().zip(keys.iter_mut()).zip(out.iter_mut()) {
            *key = shuffle_key(p);
            unshuffled(n, cells);
        }
        for j in (1..n).rev() {
            for (&key, pick) in keys.iter().zip(picks.iter_mut()) {
                *pick = shuffle_pick(key, j);
            }
            for (cells, &k) in out.iter_mut().zip(&*picks) {
                cells.swap(j as usize, k as usize);
            }
        }
    }
}

/// [`Sampler::group`] for the random and stratified samplers, compiled for AVX-512.
///
/// # Safety
/// The CPU must have AVX-512 F, DQ and VL.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl")]
unsafe fn group_avx512(
    group: &Group,
    u: &mut [f64],
    v: &mut [f64],
    lens: Option<&mut [(f64, f64)]>,
) {
    group_numbers(group, u, v, lens);
}

/// [`Sampler::group`] for the random and stratified samplers, compiled for AVX2: the
/// hashes' 64-bit products four pixels at a time, where the baseline's SSE2 takes two.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn group_avx2(group: &Group, u: &mut [f64], v: &mut [f64], lens: Option<&mut [(f64, f64)]>) {
    group_numbers(group, u, v, lens);
}

/// [`Sampler::group`] for the random and stratified samplers: the offsets, then the lens
/// points, each loop free of branches so that the compiler can take several pixels at
/// once.
#[inline(always)]
fn group_numbers(group: &Group, u: &mut [f64], v: &mut [f64], lens: Option<&mut [(f64, f64)]>) {
    let &Group {
        pixel_hashes,
        shuffles,
        s,
        stratum,
        lens_strata,
    } = group;
    // The kind chosen once, outside the loops.
    match stratum {
        Some([.., columns, rows]) if lens_strata => {
            let offsets = pixel_hashes.iter().zip(shuffles).zip(u).zip(v);
            for (((&p, cells), u), v) in offsets {
                let cell = cell(u32::from(cells[s as usize]), [columns, rows]);
                (*u, *v) = in_cell(cell, unit_offset(p, s));
            }
        }
        Some(cell) => {
            for ((&p, u), v) in pixel_hashes.iter().zip(u).zip(v) {
                (*u, *v) = in_cell(cell, unit_offset(p, s));
            }
        }
        None => {
            for ((&p, u), v) in pixel_hashes.iter().zip(u).zip(v) {
                (*u, *v) = unit_offset(p, s);
            }
        }
    }
    if let Some(lens) = lens {
        let points = pixel_hashes.iter().zip(lens.iter_mut());
        match stratum {
            Some(cell) if lens_strata => {
                for (&p, lens) in points {
                    *lens = in_cell(cell, lens_from(p, s));
                }
            }
            _ => {
                for (&p, lens) in points {
                    *lens = lens_from(p, s);
                }
            }
        }
    }
}

/// The offset of sample `s` of a random pixel, from its pixel's hash: uniform in `[0, 1)²`.
#[inline(always)]
fn unit_offset(pixel: u64, s: u32) -> (f64, f64) {
    (
        uniform(pixel, s, DIM_PIXEL),
        uniform(pixel, s, DIM_PIXEL + 1),
    )
}

/// A point `(u, v)` of `[0, 1)²` placed in a grid's `cell` (column, row, columns, rows).
#[inline(always)]
fn in_cell([column, row, columns, rows]: [f64; 4], (u, v): (f64, f64)) -> (f64, f64) {
    ((column + u) / columns, (row + v) / rows)
}

/// The lens point of sample `s`, from its pixel's hash: uniform in `[0, 1)²`.
#[inline(always)]
fn lens_from(pixel: u64, s: u32) -> (f64, f64) {
    (uniform(pixel, s, DIM_LENS), uniform(pixel, s, DIM_LENS + 1))
}

/// Cell `i` of a grid of `[columns, rows]` (whole numbers), filled row by row: its column
/// and row, and the grid's columns and rows. By float arithmetic, which the group loops
/// take several pixels at a time, and exact: a grid has at most 2^16 columns (their
/// square is at most its cells), so a quotient `i / columns` short of an integer is short
/// by at least 2^-16, far more than its rounding (below 2^32 · 2^-53).
#[inline(always)]
fn cell(i: u32, [columns, rows]: [f64; 2]) -> [f64; 4] {
    let i = small_integer(i);
    let row = (i / columns).floor();
    [i - row * columns, row, columns, rows]
}

/// `k as f64`, exactly, as `2^52 + k` in a float's mantissa less `2^52`: a conversion the
/// group loops take several pixels at a time (x86 converts unsigned integers to floats
/// only one at a time before AVX-512).
#[inline(always)]
fn small_integer(k: u32) -> f64 {
    const TWO_52: u64 = 0x4330_0000_0000_0000;
    f64::from_bits(TWO_52 | u64::from(k)) - f64::from_bits(TWO_52)
}

/// The pixel's shuffle of the cells `0..n` (`n` at most [`MOST_LENS_CELLS`]), into
/// `out[..n]`: a Fisher–Yates shuffle, each step's choice from a hash of the pixel and the
/// step, so that every order is as likely as another (to within `n / 2^32`).
#[inline(always)]
fn shuffle(pixel: u64, n: u32, out: &mut CellShuffle) {
    let key = shuffle_key(pixel);
    unshuffled(n, out);
    for j in (1..n).rev() {
        out.swap(j as usize, shuffle_pick(key, j) as usize);
    }
}

/// The key of a pixel's [`shuffle`].
#[inline(always)]
fn shuffle_key(pixel: u64) -> u64 {
    // Bit 63 set: `(s << 16) | dimension` of a sample's number never has it.
    mix(pixel ^ (1 << 63))
}

/// `0..n` in order, into `out[..n]`.
#[inline(always)]
fn unshuffled(n: u32, out: &mut CellShuffle) {
    for (i, cell) in out.iter_mut().take(n as usize).enumerate() {
        *cell = i as u8;
    }
}

/// Step `j` of a [`shuffle`] under `key`: the place in `0..=j` that place `j` swaps with.
#[inline(always)]
fn shuffle_pick(key: u64, j: u32) -> u32 {
    let h = mix(key.wrapping_add(u64::from(j).wrapping_mul(0x9e37_79b9_7f4a_7c15)));
    // A 32-bit fraction times `j + 1`, its top 32 bits.
    (((h & 0xffff_ffff) * u64::from(j + 1)) >> 32) as u32
}

/// The number of dimension `dimension` of sample `s`, from its pixel's hash.
#[inline(always)]
fn uniform(pixel_hash: u64, s: u32, dimension: u64) -> f64 {
    let h = mix(pixel_hash ^ ((u64::from(s) << 16) | dimension));
    unit(h >> 11)
}

/// `bits as f64 / 2^53` for `bits < 2^53`, exactly, by the two halves of `bits` placed in
/// float mantissas: the same value as the conversion, but without a 64-bit integer
/// conversion, which x86 has only for single values (before AVX-512), so the group loops
/// stay in vector registers.
#[inline(always)]
fn unit(bits: u64) -> f64 {
    const TWO_84: u64 = 0x4530_0000_0000_0000;
    // 2^84 + high · 2^32 and 2^52 + low, each exact; less the powers, both halves are
    // exact, and so is their sum (below 2^53).
    let high = f64::from_bits(TWO_84 | (bits >> 32)) - f64::from_bits(TWO_84);
    let low = small_integer(bits as u32);
    (high + low) * (1.0 / (1u64 << 53) as f64)
}

/// The hash of pixel `(x, y)` under the seed's hash: where its numbers start.
#[inline(always)]
fn hash_pixel(seed_hash: u64, x: u32, y: u32) -> u64 {
    mix(seed_hash ^ ((u64::from(x) << 32) | u64::from(y)))
}

/// SplitMix64's finalizer: a bijective mix of 64 bits.
#[inline(always)]
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sampler(kind: SamplerKind, spp: u32) -> Sampler {
        Sampler::new(&SamplerDesc { kind, spp, seed: 3 })
    }

    /// The cell of a grid of `spp` cells in `columns` columns, row by row, that `(u, v)`
    /// lies in, worked out apart from the sampler.
    fn cell_of((u, v): (f64, f64), spp: u32, columns: u32) -> u32 {
        assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
        let rows = spp / columns;
        (v * f64::from(rows)) as u32 * columns + (u * f64::from(columns)) as u32
    }

    #[test]
    fn stratified_samples_fill_every_cell_once() {
        // With a pinhole sample i takes offset cell i; through a lens, lens cell i in
        // every pixel and an offset cell that changes from pixel to pixel.
        for lens in [false, true] {
            for spp in [1, 2, 6, 7, 16, 20] {
                let s = sampler(SamplerKind::Stratified, spp).with_lens(lens);
                let mut moved = 0;
                for (x, y) in [(4, 9), (0, 0), (1919, 1079), (77, 3)] {
                    let (mut offsets, mut points) = (vec![0; spp as usize], vec![0; spp as usize]);
                    for i in 0..spp {
                        let cell = cell_of(s.pixel_offset(x, y, i), spp, s.columns);
                        offsets[cell as usize] += 1;
                        moved += usize::from(cell != i);
                        let point = cell_of(s.lens(x, y, i), spp, s.columns);
                        points[point as usize] += 1;
                        if lens {
                            assert_eq!(point, i, "spp {spp}: lens point of sample {i}");
                        }
                    }
                    assert!(offsets.iter().all(|&n| n == 1), "spp {spp}: {offsets:?}");
                    if lens {
                        assert!(points.iter().all(|&n| n == 1), "spp {spp}: {points:?}");
                    }
                }
                assert_eq!(
                    moved > 0,
                    lens && spp > 1,
                    "spp {spp}, lens {lens}: {moved}"
                );
            }
        }
    }

    #[test]
    fn through_a_lens_every_pairing_of_offset_and_lens_cells_is_as_likely() {
        // Over many pixels, the offset cell that meets lens cell 0 must be uniform over
        // the cells (else a pixel's mean is biased), and the pair that meets lens cells 0
        // and 1 uniform over the ordered pairs of distinct cells: a pairing shifted
        // around the grid by a pixel's amount would pass the first, not the second (its
        // images were noisier at 256 spp than with lens points not stratified at all).
        for spp in [2, 4, 6, 7, 16] {
            let s = sampler(SamplerKind::Stratified, spp).with_lens(true);
            let n = spp as usize;
            let pixels = 3000 * n * (n - 1);
            let (mut single, mut pairs) = (vec![0usize; n], vec![0usize; n * n]);
            for p in 0..pixels as u32 {
                let (x, y) = (p % 1024, p / 1024);
                let a = cell_of(s.pixel_offset(x, y, 0), spp, s.columns) as usize;
                let b = cell_of(s.pixel_offset(x, y, 1), spp, s.columns) as usize;
                single[a] += 1;
                pairs[a * n + b] += 1;
            }
            let expected = (pixels / n) as f64;
            for (cell, &count) in single.iter().enumerate() {
                let ratio = count as f64 / expected;
                assert!(
                    (0.95..1.05).contains(&ratio),
                    "spp {spp}: cell {cell}: {ratio}"
                );
            }
            let expected = (pixels / (n * (n - 1))) as f64;
            for a in 0..n {
                for b in 0..n {
                    let count = pairs[a * n + b];
                    if a == b {
                        assert_eq!(count, 0, "spp {spp}: cell {a} twice");
                        continue;
                    }
                    let ratio = count as f64 / expected;
                    assert!(
                        (0.85..1.15).contains(&ratio),
                        "spp {spp}: ({a}, {b}): {ratio}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_pixel_s_shuffle_holds_every_cell_once() {
        let mut random = crate::test_random::XorShift::new(5);
        for n in (1..=70).chain([127, 128, 255, 256]) {
            for _ in 0..20 {
                let pixel = random.next_u64();
                let mut cells = [7; MOST_LENS_CELLS as usize];
                shuffle(pixel, n, &mut cells);
                let mut seen = vec![false; n as usize];
                for &c in &cells[..n as usize] {
                    assert!(u32::from(c) < n && !seen[c as usize], "{n}: {c} again");
                    seen[c as usize] = true;
                }
                // Nothing past the cells is written.
                assert!(cells[n as usize..].iter().all(|&c| c == 7));
            }
        }
    }

    #[test]
    fn the_lens_is_stratified_from_two_samples_to_the_most_cells() {
        // One sample's numbers are the same either way; past the most cells, a shuffle
        // would not fit in bytes, and lens points are random.
        for (spp, stratified) in [(1, false), (2, true), (256, true), (257, false)] {
            let s = sampler(SamplerKind::Stratified, spp).with_lens(true);
            assert_eq!(s.stratifies_lens(), stratified, "{spp}");
            let pinhole = sampler(SamplerKind::Stratified, spp);
            if spp == 1 {
                assert_eq!(s.pixel_offset(3, 4, 0), pinhole.pixel_offset(3, 4, 0));
                assert_eq!(s.lens(3, 4, 0), pinhole.lens(3, 4, 0));
            }
        }
        assert!(
            !sampler(SamplerKind::Independent, 4)
                .with_lens(true)
                .stratifies_lens()
        );
    }

    #[test]
    fn cells_by_float_arithmetic_are_the_cells_by_integers() {
        let mut random = crate::test_random::XorShift::new(9);
        let max = crate::manifest::MAX_SPP;
        let grids = (1..=300).chain([4096, 65_535, max - 1, max]);
        for spp in grids {
            let columns = sampler(SamplerKind::Stratified, spp).columns;
            let grid = [columns, spp / columns].map(f64::from);
            let ends = [0, 1, spp / 2, spp - 1];
            let randoms = (0..50).map(|_| (random.next_u64() % u64::from(spp)) as u32);
            for i in ends.into_iter().chain(randoms) {
                let integers = [i % columns, i / columns, columns, spp / columns];
                assert_eq!(cell(i, grid), integers.map(f64::from), "{spp}: {i}");
            }
        }
    }

    #[test]
    fn stratified_samples_are_jittered_independently_within_their_cells() {
        // Each sample's place inside its cell, over many pixels: uniform on [0, 1) along
        // each axis, the two axes uncorrelated (a sample at the cell's centre, or on its
        // diagonal, fails), and the very numbers the independent sampler draws for the same
        // seed, pixel and sample, which the pinned hashes below fix. Through a lens, the
        // lens points' too, and the offsets' in the cells the pixel's pairing gives them.
        for (spp, lens, points) in [
            (4, false, false),
            (6, false, false),
            (16, false, false),
            (4, true, false),
            (6, true, false),
            (4, true, true),
            (6, true, true),
            (16, true, true),
        ] {
            let s = sampler(SamplerKind::Stratified, spp).with_lens(lens);
            let independent = sampler(SamplerKind::Independent, spp);
            let (columns, rows) = (f64::from(s.columns), f64::from(spp / s.columns));
            let (mut n, mut sum_u, mut sum_v, mut sum_uv) = (0.0, 0.0, 0.0, 0.0);
            let (mut low, mut high) = (0, 0);
            for pixel in 0..2000 {
                let (x, y) = (pixel % 53, pixel / 53);
                for i in 0..spp {
                    let ((u, v), (ju, jv), cell) = if points {
                        let point = s.lens(x, y, i);
                        (point, independent.lens(x, y, i), i)
                    } else {
                        let offset = s.pixel_offset(x, y, i);
                        let cell = if lens {
                            cell_of(offset, spp, s.columns)
                        } else {
                            i
                        };
                        (offset, independent.pixel_offset(x, y, i), cell)
                    };
                    let (column, row) = (f64::from(cell % s.columns), f64::from(cell / s.columns));
                    let (du, dv) = (u * columns - column, v * rows - row);
                    assert!((0.0..1.0).contains(&du) && (0.0..1.0).contains(&dv));
                    assert!((du - ju).abs() < 1e-12 && (dv - jv).abs() < 1e-12);
                    (n, sum_u, sum_v, sum_uv) = (n + 1.0, sum_u + du, sum_v + dv, sum_uv + du * dv);
                    low += usize::from(du < 0.05);
                    high += usize::from(du > 0.95);
                }
            }
            let (mean_u, mean_v) = (sum_u / n, sum_v / n);
            assert!((mean_u - 0.5).abs() < 0.01 && (mean_v - 0.5).abs() < 0.01);
            // Uniform offsets have variance 1/12; a covariance near it means one axis
            // follows the other.
            let covariance = sum_uv / n - mean_u * mean_v;
            let case = format!("spp {spp}, lens {lens}, lens points {points}");
            assert!(covariance.abs() < 0.005, "{case}: covariance {covariance}");
            assert!(low > 0 && high > 0, "{case}: {low} low, {high} high");
        }
    }

    #[test]
    fn a_group_s_numbers_are_the_numbers_one_by_one() {
        // Every kind, the stratified one also through a lens (with grids of 4 and 6
        // cells), with and without lens points, through the dispatch (AVX-512 where the CPU has it) and
        // through the plain loop, for groups of every size.
        let pixels: Vec<(u32, u32)> = (0..64).map(|i| ((i * 5) % 41, (i * 3) % 16)).collect();
        for (kind, spp, lens) in [
            (SamplerKind::Center, 1, false),
            (SamplerKind::Independent, 6, false),
            (SamplerKind::Stratified, 6, false),
            (SamplerKind::Stratified, 4, true),
            (SamplerKind::Stratified, 6, true),
        ] {
            let sampler = sampler(kind, spp).with_lens(lens);
            for n in 0..=pixels.len() {
                for s in 0..sampler.spp() {
                    let (mut u, mut v, mut lens) = ([9.0; 64], [9.0; 64], [(9.0, 9.0); 64]);
                    let (mut plain_u, mut plain_v) = ([9.0; 64], [9.0; 64]);
                    let mut plain_lens = [(9.0, 9.0); 64];
                    let mut hashes = [0u64; 64];
                    sampler.pixel_hashes((&pixels[..n], 7), &mut hashes);
                    let hashes = &hashes[..n];
                    let mut shuffles = [[0; MOST_LENS_CELLS as usize]; 64];
                    sampler.shuffles(hashes, &mut shuffles);
                    let numbers = (hashes, &shuffles[..n]);
                    sampler.group(numbers, s, (&mut u, &mut v), Some(&mut lens));
                    let (mut u2, mut v2) = ([9.0; 64], [9.0; 64]);
                    sampler.group(numbers, s, (&mut u2, &mut v2), None);
                    if kind != SamplerKind::Center {
                        let mut plain_hashes = [0u64; 64];
                        hash_pixels(sampler.seed_hash, (&pixels[..n], 7), &mut plain_hashes);
                        assert_eq!(hashes, &plain_hashes[..n], "{kind:?}, {n} pixels");
                        let shuffles: &[CellShuffle] = if sampler.stratifies_lens() {
                            &shuffles[..n]
                        } else {
                            &[]
                        };
                        let group = sampler.group_of((&plain_hashes[..n], shuffles), s);
                        group_numbers(
                            &group,
                            &mut plain_u[..n],
                            &mut plain_v[..n],
                            Some(&mut plain_lens[..n]),
                        );
                    }
                    for (i, &(x, dy)) in pixels[..n].iter().enumerate() {
                        let offset = sampler.pixel_offset(x, 7 + dy, s);
                        let point = sampler.lens(x, 7 + dy, s);
                        let bits = |(a, b): (f64, f64)| (a.to_bits(), b.to_bits());
                        assert_eq!(bits((u[i], v[i])), bits(offset), "{kind:?} {n} {s} {i}");
                        assert_eq!(bits((u2[i], v2[i])), bits(offset));
                        assert_eq!(bits(lens[i]), bits(point));
                        if kind != SamplerKind::Center {
                            assert_eq!(bits((plain_u[i], plain_v[i])), bits(offset));
                            assert_eq!(bits(plain_lens[i]), bits(point));
                        }
                    }
                    // Nothing past the group is written.
                    assert!(u[n..].iter().chain(&v2[n..]).all(|&x| x == 9.0));
                    assert!(lens[n..].iter().all(|&p| p == (9.0, 9.0)));
                }
            }
        }
    }

    #[test]
    fn numbers_are_splitmix_hashes_of_seed_pixel_sample_and_dimension() {
        // Computed apart (Python, arbitrary-precision integers): the top 53 bits of
        // mix(mix(mix(seed ^ 0x9e3779b97f4a7c15) ^ (x << 32 | y)) ^ (s << 16 | dimension)).
        // Pinned so that a user's sampled images stay the same from version to version.
        let units = |v: f64| v * (1u64 << 53) as f64;
        let s = sampler(SamplerKind::Independent, 8);
        let (u, v) = s.pixel_offset(5, 6, 7);
        assert_eq!(
            (units(u), units(v)),
            (2459685303689427.0, 1915105744436346.0)
        );
        assert_eq!(units(s.lens(5, 6, 7).0), 3755447657861202.0);
        let unseeded = Sampler::new(&SamplerDesc {
            kind: SamplerKind::Independent,
            spp: 64,
            seed: 0,
        });
        assert_eq!(
            units(unseeded.random(1919, 1079, 63, 3)),
            2019775988978328.0
        );
    }

    #[test]
    fn unit_is_the_conversion_of_every_kind_of_53_bit_number() {
        let mut random = crate::test_random::XorShift::new(11);
        let edges = [
            0,
            1,
            (1 << 32) - 1,
            1 << 32,
            (1 << 32) + 1,
            (1 << 52) + 1,
            (1 << 53) - 1,
        ];
        let randoms = (0..10_000).map(|_| random.next_u64() >> 11);
        for bits in edges.into_iter().chain(randoms) {
            let expected = bits as f64 / (1u64 << 53) as f64;
            assert_eq!(unit(bits).to_bits(), expected.to_bits(), "{bits}");
        }
    }

    #[test]
    fn independent_samples_are_uniform_and_reproducible() {
        let s = sampler(SamplerKind::Independent, 1);
        let n = 20_000;
        let mean: f64 = (0..n)
            .map(|i| s.pixel_offset(i % 97, i / 97, 0).0)
            .sum::<f64>()
            / f64::from(n);
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        assert_eq!(s.pixel_offset(5, 6, 7), s.pixel_offset(5, 6, 7));
        assert_ne!(s.pixel_offset(5, 6, 7), s.pixel_offset(5, 6, 8));
        let other_seed = Sampler::new(&SamplerDesc {
            kind: SamplerKind::Independent,
            spp: 1,
            seed: 4,
        });
        assert_ne!(s.pixel_offset(5, 6, 7), other_seed.pixel_offset(5, 6, 7));
    }
}
