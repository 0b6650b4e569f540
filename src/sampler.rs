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

use crate::manifest::{SamplerDesc, SamplerKind};

/// The middle of `[0, 1)²`: every offset and lens point of the `center` sampler.
pub const CENTER: (f64, f64) = (0.5, 0.5);

/// Random dimensions used per sample: 0–1 the pixel offset, 2–3 the lens.
const DIM_PIXEL: u64 = 0;
const DIM_LENS: u64 = 2;

#[derive(Debug, Clone, Copy)]
pub struct Sampler {
    kind: SamplerKind,
    spp: u32,
    /// The seed's hash: the first step of every random number, taken once.
    seed_hash: u64,
    /// Stratified grid: `columns × rows = spp`, as square as `spp`'s divisors allow.
    columns: u32,
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
            _ => lens_from(self.pixel_hash(x, y), s),
        }
    }

    /// [`Sampler::pixel_offset`] and [`Sampler::lens`] together, the pixel hashed once.
    #[inline(always)]
    pub fn offset_and_lens(&self, x: u32, y: u32, s: u32) -> ((f64, f64), (f64, f64)) {
        match self.kind {
            SamplerKind::Center => (CENTER, CENTER),
            _ => {
                let pixel = self.pixel_hash(x, y);
                (self.offset_from(pixel, s), lens_from(pixel, s))
            }
        }
    }

    /// The pixel offset of sample `s` of a random sampler, from its pixel's hash.
    #[inline(always)]
    fn offset_from(&self, pixel: u64, s: u32) -> (f64, f64) {
        let (u, v) = (
            uniform(pixel, s, DIM_PIXEL),
            uniform(pixel, s, DIM_PIXEL + 1),
        );
        match self.kind {
            SamplerKind::Stratified => {
                let (column, row) = (s % self.columns, s / self.columns);
                let rows = self.spp / self.columns;
                (
                    (f64::from(column) + u) / f64::from(self.columns),
                    (f64::from(row) + v) / f64::from(rows),
                )
            }
            _ => (u, v),
        }
    }

    /// A uniform number in `[0, 1)` determined by the seed, pixel, sample and dimension.
    #[inline]
    pub fn random(&self, x: u32, y: u32, s: u32, dimension: u64) -> f64 {
        uniform(self.pixel_hash(x, y), s, dimension)
    }

    /// The hash of the seed and pixel, which every number of the pixel starts from.
    #[inline(always)]
    fn pixel_hash(&self, x: u32, y: u32) -> u64 {
        mix(self.seed_hash ^ ((u64::from(x) << 32) | u64::from(y)))
    }
}

/// The lens point of sample `s`, from its pixel's hash.
#[inline(always)]
fn lens_from(pixel: u64, s: u32) -> (f64, f64) {
    (uniform(pixel, s, DIM_LENS), uniform(pixel, s, DIM_LENS + 1))
}

/// The number of dimension `dimension` of sample `s`, from its pixel's hash.
#[inline(always)]
fn uniform(pixel_hash: u64, s: u32, dimension: u64) -> f64 {
    let h = mix(pixel_hash ^ ((u64::from(s) << 16) | dimension));
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
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

    #[test]
    fn stratified_samples_fill_every_cell_once() {
        for spp in [1, 2, 6, 7, 16, 20] {
            let s = sampler(SamplerKind::Stratified, spp);
            let rows = spp / s.columns;
            let mut seen = vec![false; spp as usize];
            for i in 0..spp {
                let (u, v) = s.pixel_offset(4, 9, i);
                assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
                let cell =
                    (v * f64::from(rows)) as u32 * s.columns + (u * f64::from(s.columns)) as u32;
                assert!(!seen[cell as usize], "spp {spp}: cell {cell} twice");
                seen[cell as usize] = true;
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
