//! Comparing two images, and two sets of depths: the figures behind `raybatch compare` and
//! `raybatch verify`.
//!
//! Pixel figures are in the images' own units (0–255 for 8-bit PPM, floats for PFM; a PPM
//! compared with a PFM is first scaled to [0, 1]). Depth figures treat a pixel as a miss
//! when all three channels equal the background, and give the relative error `|a − b| / |b|`
//! where both hit (`B` is the reference).

use serde_json::json;

use crate::image::Decoded;

/// How two images differ.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageComparison {
    pub width: u32,
    pub height: u32,
    /// Pixels where any channel differs.
    pub differing: u64,
    pub max_abs: f64,
    pub rmse: f64,
    /// `20 log10(peak / RMSE)`, infinite for identical images; the peak is the PPM maxval,
    /// or for PFM the largest absolute value in the reference (1 if that is 0).
    pub psnr: f64,
    pub depth: Option<DepthComparison>,
}

/// How two depth maps (or two sets of traced distances) differ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthComparison {
    pub samples: u64,
    /// Samples where exactly one side hit something.
    pub mask_disagreements: u64,
    pub mask_fraction: f64,
    /// Samples where both hit.
    pub both_hit: u64,
    /// Relative error `|a − b| / |b|` over samples where both hit.
    pub median: f64,
    pub p99: f64,
    pub p999: f64,
    pub max: f64,
}

impl DepthComparison {
    /// From pairs `(a, b)` of distances, `None` for a miss; `b` is the reference.
    pub fn from_pairs(
        pairs: impl IntoIterator<Item = (Option<f64>, Option<f64>)>,
    ) -> DepthComparison {
        let (mut samples, mut disagreements) = (0u64, 0u64);
        let mut errors = Vec::new();
        for (a, b) in pairs {
            samples += 1;
            match (a, b) {
                (Some(a), Some(b)) => {
                    errors.push(if a == b { 0.0 } else { (a - b).abs() / b.abs() })
                }
                (None, None) => {}
                _ => disagreements += 1,
            }
        }
        errors.sort_by(f64::total_cmp);
        let percentile = |p: f64| -> f64 {
            if errors.is_empty() {
                return 0.0;
            }
            // Nearest rank: the smallest value with at least p of the values at or below it.
            let rank = (p * errors.len() as f64).ceil() as usize;
            errors[rank.clamp(1, errors.len()) - 1]
        };
        DepthComparison {
            samples,
            mask_disagreements: disagreements,
            mask_fraction: if samples == 0 {
                0.0
            } else {
                disagreements as f64 / samples as f64
            },
            both_hit: errors.len() as u64,
            median: percentile(0.5),
            p99: percentile(0.99),
            p999: percentile(0.999),
            max: errors.last().copied().unwrap_or(0.0),
        }
    }

    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "samples": self.samples,
            "mask_disagreements": self.mask_disagreements,
            "mask_fraction": self.mask_fraction,
            "both_hit": self.both_hit,
            "median": self.median,
            "p99": self.p99,
            "p999": self.p999,
            "max": self.max,
        })
    }

    /// One line for people.
    pub fn summary(&self) -> String {
        format!(
            "hit-mask disagreements {} of {} ({:.4}%), relative depth error median {:.3e}, p99 {:.3e}, p99.9 {:.3e}, max {:.3e}",
            self.mask_disagreements,
            self.samples,
            100.0 * self.mask_fraction,
            self.median,
            self.p99,
            self.p999,
            self.max
        )
    }
}

/// Compares image `a` with the reference `b`. Depth figures are added when `depth` is
/// `Some(background)`.
pub fn compare_images(
    a: &Decoded,
    b: &Decoded,
    depth: Option<[f64; 3]>,
) -> Result<ImageComparison, String> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(format!(
            "the images differ in size: {} x {} and {} x {}",
            a.width, a.height, b.width, b.height
        ));
    }
    // Same kind of file (and for PPMs the same maxval): native units. Otherwise PPMs
    // scaled to [0, 1], so that an 8-bit and a 16-bit image compare as the colours they
    // denote.
    let scale = |d: &Decoded| match (a.maxval, b.maxval) {
        (Some(ma), Some(mb)) if ma == mb => 1.0,
        (None, None) => 1.0,
        _ => d.maxval.map_or(1.0, |m| 1.0 / f64::from(m)),
    };
    let (scale_a, scale_b) = (scale(a), scale(b));
    let (mut differing, mut max_abs, mut sum_sq) = (0u64, 0.0f64, 0.0f64);
    for (pa, pb) in a.pixels.iter().zip(&b.pixels) {
        let mut differs = false;
        for c in 0..3 {
            let d = (pa[c] * scale_a - pb[c] * scale_b).abs();
            differs |= d != 0.0;
            max_abs = max_abs.max(d);
            sum_sq += d * d;
        }
        differing += u64::from(differs);
    }
    let rmse = (sum_sq / (3 * a.pixels.len()) as f64).sqrt();
    let peak = match (b.maxval, scale_b) {
        (Some(m), 1.0) => f64::from(m),
        (Some(_), _) => 1.0,
        (None, _) => {
            let largest = b
                .pixels
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            if largest > 0.0 { largest } else { 1.0 }
        }
    };
    let psnr = if rmse == 0.0 {
        f64::INFINITY
    } else {
        20.0 * (peak / rmse).log10()
    };
    let depth = depth.map(|background| {
        // The background as each file stores it; a PPM value v holds depth/scale ≈ v / 256.
        let stored = |d: &Decoded| match d.maxval {
            Some(_) => background.map(|c| f64::from(crate::image::quantize(c))),
            None => background.map(|c| f64::from(c as f32)),
        };
        let (background_a, background_b) = (stored(a), stored(b));
        let depth_of = |d: &Decoded, p: &[f64; 3], background: [f64; 3]| {
            (*p != background).then_some(if d.maxval.is_some() {
                p[0] / 256.0
            } else {
                p[0]
            })
        };
        DepthComparison::from_pairs(
            a.pixels
                .iter()
                .zip(&b.pixels)
                .map(|(pa, pb)| (depth_of(a, pa, background_a), depth_of(b, pb, background_b))),
        )
    });
    Ok(ImageComparison {
        width: a.width,
        height: a.height,
        differing,
        max_abs,
        rmse,
        psnr,
        depth,
    })
}

/// Thresholds; `None` means unchecked.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Limits {
    pub max_differing: Option<u64>,
    pub max_abs: Option<f64>,
    pub min_psnr: Option<f64>,
    pub max_mask_fraction: Option<f64>,
    pub max_depth_p99: Option<f64>,
    pub max_depth_p999: Option<f64>,
    pub max_depth_error: Option<f64>,
}

impl Limits {
    /// What exceeds the limits, one phrase each.
    pub fn check_image(&self, c: &ImageComparison) -> Vec<String> {
        let mut failures = Vec::new();
        if let Some(limit) = self.max_differing.filter(|&l| c.differing > l) {
            failures.push(format!("{} differing pixels > {limit}", c.differing));
        }
        if let Some(limit) = self.max_abs.filter(|&l| c.max_abs > l) {
            failures.push(format!("max abs difference {} > {limit}", c.max_abs));
        }
        if let Some(limit) = self.min_psnr.filter(|&l| c.psnr < l) {
            failures.push(format!("PSNR {:.2} dB < {limit}", c.psnr));
        }
        if let Some(depth) = &c.depth {
            failures.extend(self.check_depth(depth));
        }
        failures
    }

    pub fn check_depth(&self, d: &DepthComparison) -> Vec<String> {
        let mut failures = Vec::new();
        let checks = [
            (
                self.max_mask_fraction,
                d.mask_fraction,
                "hit-mask disagreement fraction",
            ),
            (self.max_depth_p99, d.p99, "p99 relative depth error"),
            (self.max_depth_p999, d.p999, "p99.9 relative depth error"),
            (self.max_depth_error, d.max, "max relative depth error"),
        ];
        for (limit, value, what) in checks {
            if let Some(limit) = limit.filter(|&l| value > l) {
                failures.push(format!("{what} {value:.3e} > {limit:e}"));
            }
        }
        failures
    }
}

impl ImageComparison {
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "width": self.width,
            "height": self.height,
            "differing": self.differing,
            "differing_fraction": self.differing as f64 / (f64::from(self.width) * f64::from(self.height)),
            "max_abs": self.max_abs,
            "rmse": self.rmse,
            // JSON has no infinity: identical images report a PSNR of null.
            "psnr": self.psnr.is_finite().then_some(self.psnr),
            "depth": self.depth.as_ref().map(DepthComparison::to_json),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(maxval: Option<u32>, pixels: Vec<[f64; 3]>) -> Decoded {
        Decoded {
            width: pixels.len() as u32,
            height: 1,
            maxval,
            pixels,
        }
    }

    #[test]
    fn pixel_figures_by_hand() {
        let a = image(Some(255), vec![[10.0, 20.0, 30.0], [0.0, 0.0, 0.0]]);
        let b = image(Some(255), vec![[10.0, 20.0, 30.0], [3.0, 0.0, 4.0]]);
        let c = compare_images(&a, &b, None).unwrap();
        assert_eq!(c.differing, 1);
        assert_eq!(c.max_abs, 4.0);
        // sqrt((9 + 16) / 6)
        assert!((c.rmse - (25.0f64 / 6.0).sqrt()).abs() < 1e-15);
        assert!((c.psnr - 20.0 * (255.0 / c.rmse).log10()).abs() < 1e-12);
        let same = compare_images(&a, &a, None).unwrap();
        assert_eq!(
            (same.differing, same.max_abs, same.psnr),
            (0, 0.0, f64::INFINITY)
        );
    }

    #[test]
    fn ppms_of_other_maxvals_compare_as_fractions_of_their_maxval() {
        let a = image(Some(255), vec![[255.0, 0.0, 51.0]]);
        let b = image(Some(65535), vec![[65535.0, 0.0, 13107.0]]);
        let c = compare_images(&a, &b, None).unwrap();
        assert_eq!((c.differing, c.max_abs, c.psnr), (0, 0.0, f64::INFINITY));
        let d = image(Some(65535), vec![[0.0, 0.0, 13107.0]]);
        let c = compare_images(&a, &d, None).unwrap();
        assert_eq!((c.differing, c.max_abs), (1, 1.0));
        // Peak 1 in these units.
        assert!((c.psnr - 20.0 * (1.0 / c.rmse).log10()).abs() < 1e-12);
    }

    #[test]
    fn sizes_must_match() {
        let a = image(None, vec![[0.0; 3]; 2]);
        let b = image(None, vec![[0.0; 3]; 3]);
        assert!(
            compare_images(&a, &b, None)
                .unwrap_err()
                .contains("differ in size")
        );
    }

    #[test]
    fn depth_figures_use_nearest_rank_percentiles() {
        // 1000 pairs: 990 exact, 9 at 1e-6, 1 at 1e-3; 2 mask disagreements on top.
        let mut pairs: Vec<(Option<f64>, Option<f64>)> = vec![(Some(2.0), Some(2.0)); 990];
        pairs.extend(vec![(Some(2.0 + 2e-6), Some(2.0)); 9]);
        pairs.push((Some(2.002), Some(2.0)));
        pairs.extend([(None, Some(1.0)), (Some(1.0), None), (None, None)]);
        let d = DepthComparison::from_pairs(pairs);
        assert_eq!(
            (d.samples, d.mask_disagreements, d.both_hit),
            (1003, 2, 1000)
        );
        assert_eq!(d.median, 0.0);
        assert_eq!(d.p99, 0.0);
        assert!((d.p999 - 1e-6).abs() < 1e-12, "{}", d.p999);
        assert!((d.max - 1e-3).abs() < 1e-12);
        let limits = Limits {
            max_depth_p999: Some(1e-5),
            max_mask_fraction: Some(1e-3),
            ..Limits::default()
        };
        let failures = limits.check_depth(&d);
        assert_eq!(failures.len(), 1, "{failures:?}");
        assert!(failures[0].contains("hit-mask"));
    }

    #[test]
    fn misses_are_pixels_equal_to_the_background() {
        let a = image(None, vec![[0.5; 3], [0.0; 3], [0.25; 3]]);
        let b = image(None, vec![[0.5; 3], [0.75; 3], [0.2; 3]]);
        let c = compare_images(&a, &b, Some([0.0; 3])).unwrap();
        let d = c.depth.unwrap();
        assert_eq!((d.mask_disagreements, d.both_hit), (1, 2));
        assert!((d.max - 0.25).abs() < 1e-15);

        // A coloured background: a miss equals it in all three channels; a depth of 0.25
        // (grey) is a hit though it shares the background's first channel, and so is a
        // depth of 0.5, which shares its last.
        let background = [0.25, 0.375, 0.5];
        let a = image(None, vec![background, [0.25; 3], [0.5; 3], background]);
        let b = image(None, vec![background, [0.25; 3], [0.5; 3], [1.0; 3]]);
        let d = compare_images(&a, &b, Some(background))
            .unwrap()
            .depth
            .unwrap();
        assert_eq!((d.samples, d.mask_disagreements, d.both_hit), (4, 1, 2));
    }
}
