//! Rendering an image: camera rays through every pixel sample, in parallel over bands of
//! rows (rayon), each band walked in square tiles so neighbouring rays stay together.
//! A pixel's value depends only on the scene and its samples, never on the thread that
//! computed it, so the bytes do not depend on the thread count.

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::ManifestError;
use crate::image::Image;
use crate::integrator::{DepthIntegrator, HitIntegrator, Integrator, NormalIntegrator};
use crate::manifest::{IntegratorDesc, Manifest};
use crate::ray::Ray;
use crate::sampler::{CellShuffle, MOST_LENS_CELLS, Sampler};
use crate::scene::{Extent, Tracer};

/// Side of the square tiles, in pixels; also the height of a parallel band.
pub const TILE: u32 = 16;

/// A group's pixels `(x, y0 + dy)`, their first row `y0`, their [`View::pixel_hashes`] and
/// their [`View::shuffles`] (empty where the view does not stratify the lens), for
/// [`View::rays_hashed`].
pub type HashedGroup<'a> = (&'a [(u32, u32)], u32, &'a [u64; GROUP], &'a [CellShuffle]);

/// Everything besides the scene that decides a pixel. Made from a manifest, and not
/// changed after: the tables below follow from the camera and sampler.
#[derive(Debug, Clone)]
pub struct View {
    camera: Camera,
    sampler: Sampler,
    tmin: f64,
    tmax: f64,
    /// With a fixed pixel offset (the `center` sampler), each column's `u` and each row's
    /// `v` (see [`Camera::screen_u`]), computed once instead of twice per pixel: the same
    /// values, and two divisions fewer per camera ray.
    screen: Option<(Vec<f64>, Vec<f64>)>,
}

impl View {
    pub fn new(manifest: &Manifest) -> View {
        let camera = Camera::new(&manifest.camera, manifest.width, manifest.height);
        let sampler = Sampler::new(&manifest.sampler).with_lens(camera.has_lens());
        let screen = sampler.fixed_offset().map(|(sx, sy)| {
            (
                (0..manifest.width)
                    .map(|x| camera.screen_u(x, sx))
                    .collect(),
                (0..manifest.height)
                    .map(|y| camera.screen_v(y, sy))
                    .collect(),
            )
        });
        View {
            camera,
            sampler,
            tmin: manifest.tmin,
            tmax: manifest.tmax,
            screen,
        }
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Whether every ray of `tile` (of the band starting at row `y0`), whatever its
    /// sample's offset in the pixel, provably hits nothing of `extent`: it passes outside
    /// the box and leaves every plane behind ([`crate::camera::ScreenRegion`]), from
    /// whatever point of the lens.
    pub fn tile_misses(&self, tile: &Tile, y0: u32, extent: &Extent) -> bool {
        let camera = &self.camera;
        let (x, y) = (tile.x0, y0 + tile.dy0);
        // The tile's pixel edges: offsets range over [0, 1).
        let u = [
            camera.screen_u(x, 0.0),
            camera.screen_u(x + tile.width, 0.0),
        ];
        let v = [
            camera.screen_v(y + tile.height, 0.0),
            camera.screen_v(y, 0.0),
        ];
        // The region's half-spaces hold the rays' points with `t ≥ 0` only.
        let Some(region) = camera.region(u, v).filter(|_| self.tmin >= 0.0) else {
            return false;
        };
        region.misses_box(extent.bounds) && extent.planes.iter().all(|p| region.misses_plane(p))
    }

    /// Samples per pixel.
    pub fn spp(&self) -> u32 {
        self.sampler.spp()
    }

    /// The camera ray of sample `s` of pixel `(x, y)`, with the manifest's `tmin`/`tmax`.
    // Always inlined: returned through memory, the ray was reread whole from fields
    // stored one by one, and every camera ray stalled on store forwarding.
    #[inline(always)]
    pub fn ray(&self, x: u32, y: u32, s: u32) -> crate::Ray {
        let (u, v) = match &self.screen {
            Some((columns, rows)) => (columns[x as usize], rows[y as usize]),
            None => {
                let (sx, sy) = self.sampler.pixel_offset(x, y, s);
                (self.camera.screen_u(x, sx), self.camera.screen_v(y, sy))
            }
        };
        let lens = if self.camera.has_lens() {
            self.sampler.lens(x, y, s)
        } else {
            crate::sampler::CENTER
        };
        let mut ray = self.camera.ray_at(u, v, lens);
        ray.tmin = self.tmin;
        ray.tmax = self.tmax;
        ray
    }

    /// [`View::ray`] for sample `s` of each pixel `(x, y0 + dy)` of `pixels`, into `out`:
    /// the same rays, computed several at a time (every pixel's `u` and `v` from the tables,
    /// or from its sample's offset, then the pinhole directions four at a time, then with a
    /// lens each through its lens point).
    pub fn rays(&self, pixels: &[(u32, u32)], y0: u32, s: u32, out: &mut [Ray]) {
        if pixels.len() > GROUP {
            for (ray, &(x, dy)) in out.iter_mut().zip(pixels) {
                *ray = self.ray(x, y0 + dy, s);
            }
            return;
        }
        if self.stratifies_lens() {
            let mut shuffles = [[0; MOST_LENS_CELLS as usize]; GROUP];
            let (hashes, shuffles) = self.group_numbers(pixels, y0, &mut shuffles);
            self.rays_hashed((pixels, y0, &hashes, shuffles), s, out);
        } else {
            let hashes = self.pixel_hashes(pixels, y0);
            self.rays_hashed((pixels, y0, &hashes, &[]), s, out);
        }
    }

    /// What all the samples of a group of pixels `(x, y0 + dy)` share, made once for them:
    /// the pixels' [`View::pixel_hashes`] and, where [`View::stratifies_lens`], their
    /// [`View::shuffles`], written into `shuffles`. Returns the hashes and the part of
    /// `shuffles` that [`View::rays_hashed`] reads (none without a stratified lens).
    ///
    /// # Panics
    /// If `pixels` holds more than [`GROUP`].
    pub fn group_numbers<'a>(
        &self,
        pixels: &[(u32, u32)],
        y0: u32,
        shuffles: &'a mut [CellShuffle; GROUP],
    ) -> ([u64; GROUP], &'a [CellShuffle]) {
        let hashes = self.pixel_hashes(pixels, y0);
        self.shuffles(&hashes[..pixels.len()], shuffles);
        let used = if self.stratifies_lens() {
            pixels.len()
        } else {
            0
        };
        (hashes, &shuffles[..used])
    }

    /// The sampler's hashes of a group's pixels `(x, y0 + dy)`, which stay the same
    /// through the pixels' samples ([`View::rays_hashed`]).
    ///
    /// # Panics
    /// If `pixels` holds more than [`GROUP`].
    #[inline]
    pub fn pixel_hashes(&self, pixels: &[(u32, u32)], y0: u32) -> [u64; GROUP] {
        let mut hashes = [0; GROUP];
        if self.screen.is_none() {
            self.sampler.pixel_hashes((pixels, y0), &mut hashes);
        }
        hashes
    }

    /// Each pixel's shuffle of offset cells through a stratified lens, from its
    /// [`View::pixel_hashes`], into `out[i]`: made once for all of a group's samples, and
    /// only where [`View::stratifies_lens`].
    pub fn shuffles(&self, hashes: &[u64], out: &mut [CellShuffle; GROUP]) {
        self.sampler.shuffles(hashes, out);
    }

    /// Whether [`View::rays_hashed`] needs the pixels' [`View::shuffles`].
    pub fn stratifies_lens(&self) -> bool {
        self.sampler.stratifies_lens()
    }

    /// [`View::rays`] of a group of pixels, given their [`View::pixel_hashes`] and, where
    /// [`View::stratifies_lens`], their [`View::shuffles`] (otherwise not read).
    ///
    /// # Panics
    /// If `pixels` holds more than [`GROUP`], or if the lens is stratified and `shuffles`
    /// holds fewer than `pixels`.
    pub fn rays_hashed(
        &self,
        (pixels, y0, hashes, shuffles): HashedGroup,
        s: u32,
        out: &mut [Ray],
    ) {
        let n = pixels.len();
        let (mut u, mut v) = ([0.0; GROUP], [0.0; GROUP]);
        // Lens points: the centre for the `center` sampler, whose coordinates are tabled.
        let mut lens = [crate::sampler::CENTER; GROUP];
        let has_lens = self.camera.has_lens();
        match &self.screen {
            Some((columns, rows)) => {
                for (i, &(x, dy)) in pixels.iter().enumerate() {
                    u[i] = columns[x as usize];
                    v[i] = rows[(y0 + dy) as usize];
                }
            }
            None => {
                // Offsets first, then coordinates: the divisions of one pixel no longer
                // wait for its hashes, and overlap with other pixels'.
                let lens = has_lens.then_some(&mut lens[..]);
                let hashes = &hashes[..n];
                self.sampler
                    .group((hashes, shuffles), s, (&mut u[..], &mut v[..]), lens);
                self.camera
                    .screen_coordinates(pixels, y0, &mut u[..n], &mut v[..n]);
            }
        }
        if has_lens {
            self.camera
                .lens_rays(&u[..n], &v[..n], &lens[..n], &mut out[..n]);
        } else {
            self.camera.pinhole_rays(&u[..n], &v[..n], out);
        }
        for ray in out.iter_mut() {
            ray.tmin = self.tmin;
            ray.tmax = self.tmax;
        }
    }
}

/// Refuses manifests whose integrator this version cannot render yet.
pub fn check_supported(manifest: &Manifest) -> Result<(), ManifestError> {
    match manifest.integrator {
        IntegratorDesc::Hit | IntegratorDesc::Depth { .. } | IntegratorDesc::Normal => Ok(()),
        other => Err(ManifestError::invalid(
            "integrator.type",
            format!(
                "`{}` is part of the format but not implemented in this version (hit, depth and normal are)",
                other.name()
            ),
        )),
    }
}

/// Renders the manifest's image of `scene` with any tracer. `progress` is called with the number of pixels
/// finished, band by band, from any thread.
pub fn render<T: Tracer>(
    scene: &T,
    manifest: &Manifest,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Image, ManifestError> {
    check_supported(manifest)?;
    let view = View::new(manifest);
    let mut image = Image::new(
        manifest.width,
        manifest.height,
        manifest.format,
        manifest.encoding,
    );
    let background = manifest.background;
    match manifest.integrator {
        IntegratorDesc::Hit => render_with(
            scene,
            &HitIntegrator { background },
            &view,
            &mut image,
            progress,
        ),
        IntegratorDesc::Depth { scale } => render_with(
            scene,
            &DepthIntegrator { scale, background },
            &view,
            &mut image,
            progress,
        ),
        IntegratorDesc::Normal => render_with(
            scene,
            &NormalIntegrator { background },
            &view,
            &mut image,
            progress,
        ),
        _ => unreachable!("checked by check_supported"),
    }
    Ok(image)
}

/// Side of the square groups of pixels whose rays are traced together (one packet).
pub const PACKET_SIDE: u32 = 8;

/// Pixels of a group: at most [`PACKET_SIDE`]².
pub const GROUP: usize = (PACKET_SIDE * PACKET_SIDE) as usize;

/// A group's pixels: columns `x0..x0 + width` of band rows `dy0..dy0 + height`, at most
/// [`PACKET_SIDE`] each way.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tile {
    pub x0: u32,
    pub dy0: u32,
    pub width: u32,
    pub height: u32,
}

impl Tile {
    /// The tile's pixels `(x, row in the band)` row by row into `out`, and how many.
    #[inline]
    pub fn pixels(&self, out: &mut [(u32, u32); GROUP]) -> usize {
        let mut n = 0;
        for dy in self.dy0..self.dy0 + self.height {
            for x in self.x0..self.x0 + self.width {
                out[n] = (x, dy);
                n += 1;
            }
        }
        n
    }
}

/// The groups of a band `width` pixels wide and `rows` rows high, in render order: square
/// tiles of [`PACKET_SIDE`] (smaller at the right and bottom edges), left to right, each
/// top to bottom.
pub fn groups(width: u32, rows: u32) -> impl Iterator<Item = Tile> {
    (0..width)
        .step_by(PACKET_SIDE as usize)
        .flat_map(move |x0| {
            (0..rows)
                .step_by(PACKET_SIDE as usize)
                .map(move |dy0| Tile {
                    x0,
                    dy0,
                    width: PACKET_SIDE.min(width - x0),
                    height: PACKET_SIDE.min(rows - dy0),
                })
        })
}

/// Renders every pixel of `image` with one integrator, specialized at compile time. Rays
/// go to the integrator one packet at a time: the same sample of an 8 × 8 group of
/// pixels, so that they are coherent. A group whose rays all miss everything the tracer
/// holds ([`Tracer::extent`], [`View::tile_misses`]) is not traced: each of its rays takes
/// the integrator's value for a miss ([`Integrator::miss`]), the same bits a trace gives.
pub fn render_with<T: Tracer, I: Integrator>(
    scene: &T,
    integrator: &I,
    view: &View,
    image: &mut Image,
    progress: &(dyn Fn(u64) + Sync),
) {
    let width = image.width;
    let spp = view.spp();
    // The value of a miss and everything a ray can hit, when both are known.
    let misses = integrator.miss().zip(scene.extent());
    image.bands_mut(TILE).into_par_iter().for_each(|mut band| {
        let rows = band.rows();
        // One group's buffers, reused by every group (each ray is written before use):
        // nothing is allocated per group.
        let unused = Ray {
            origin: DVec3::ZERO,
            direction: DVec3::Z,
            tmin: 0.0,
            tmax: 0.0,
        };
        let mut rays = [unused; GROUP];
        let mut values = [[0.0f64; 3]; GROUP];
        let mut pixels = [(0u32, 0u32); GROUP];
        let mut shuffles = [[0; MOST_LENS_CELLS as usize]; GROUP];
        for tile in groups(width, rows) {
            let n = tile.pixels(&mut pixels);
            // Where every ray of the tile passes outside everything it could hit, each
            // takes the integrator's value for a miss, untraced.
            let missed = misses
                .filter(|(_, extent)| view.tile_misses(&tile, band.y0, extent))
                .map(|(value, _)| value);
            if spp == 1 {
                match missed {
                    Some(value) => values[..n].fill(value),
                    None => {
                        view.rays(&pixels[..n], band.y0, 0, &mut rays[..n]);
                        integrator.values(scene, &rays[..n], &mut values[..n]);
                    }
                }
                band.set_tile(&tile, &values[..n]);
                continue;
            }
            let mut sums = [[0.0f64; 3]; GROUP];
            // Untraced values are summed as traced ones are, so the mean has the same bits.
            if let Some(value) = missed {
                values[..n].fill(value);
            }
            let numbers = missed
                .is_none()
                .then(|| view.group_numbers(&pixels[..n], band.y0, &mut shuffles));
            for s in 0..spp {
                if let Some((hashes, shuffles)) = &numbers {
                    let numbers = (&pixels[..n], band.y0, hashes, *shuffles);
                    view.rays_hashed(numbers, s, &mut rays[..n]);
                    integrator.values(scene, &rays[..n], &mut values[..n]);
                }
                for (sum, value) in sums.iter_mut().zip(&values[..n]) {
                    for c in 0..3 {
                        sum[c] += value[c];
                    }
                }
            }
            for (value, sum) in values.iter_mut().zip(&sums[..n]) {
                *value = sum.map(|c| c / f64::from(spp));
            }
            band.set_tile(&tile, &values[..n]);
        }
        progress(u64::from(rows) * u64::from(width));
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_cover_every_pixel_of_a_band_once_in_squares() {
        for (width, rows) in [(1, 1), (8, 8), (37, 16), (16, 5), (9, 17)] {
            let mut seen = vec![0; (width * rows) as usize];
            for tile in groups(width, rows) {
                let mut pixels = [(0, 0); GROUP];
                let n = tile.pixels(&mut pixels);
                assert!(n > 0);
                let (x0, y0) = pixels[0];
                for &(x, y) in &pixels[..n] {
                    assert!(x < width && y < rows, "{width}x{rows}: ({x}, {y})");
                    // Within one aligned square of the packet's side.
                    assert_eq!(
                        (x / PACKET_SIDE, y / PACKET_SIDE),
                        (x0 / PACKET_SIDE, y0 / PACKET_SIDE)
                    );
                    seen[(y * width + x) as usize] += 1;
                }
            }
            assert!(seen.iter().all(|&c| c == 1), "{width}x{rows}: {seen:?}");
        }
    }

    /// With several samples, the render loop hashes a group's pixels once for all of
    /// them: each pixel must still be the mean of its own samples' values, each from
    /// [`View::ray`] and [`Integrator::value`] alone, summed in sample order, for random
    /// and stratified samplers, with and without a lens, at sizes that leave partial
    /// groups.
    #[test]
    fn a_sampled_pixel_is_the_mean_of_its_rays_one_by_one() {
        use crate::sphere::Sphere;
        use crate::{Scene, SceneGeometry};
        let scene = Scene::build(&SceneGeometry {
            spheres: vec![Sphere {
                center: DVec3::new(0.0, 0.5, 0.0),
                radius: 1.4,
            }],
            ..SceneGeometry::default()
        });
        let camera = r#""camera": {"look_from": [1, 2, 3], "look_at": [0, 0.5, 0], "vfov": 50"#;
        for (sampler, lens) in [
            (r#"{"type": "independent", "spp": 3, "seed": 5}"#, ""),
            (r#"{"type": "stratified", "spp": 6, "seed": 2}"#, ""),
            (
                r#"{"type": "independent", "spp": 4, "seed": 9}"#,
                r#", "aperture": 0.2, "focus_distance": 3"#,
            ),
            (
                r#"{"type": "stratified", "spp": 6, "seed": 2}"#,
                r#", "aperture": 0.2, "focus_distance": 3"#,
            ),
        ] {
            let text = format!(
                r#"{{"image": {{"width": 19, "height": 11}}, "output": "o.pfm", {camera}{lens}}},
                    "sampler": {sampler}, "integrator": {{"type": "depth", "scale": 7}}}}"#
            );
            let manifest =
                Manifest::parse(text.as_bytes(), std::path::Path::new("t.json")).unwrap();
            let image = render(&scene, &manifest, &|_| {}).unwrap();
            let crate::image::Pixels::RgbF32(floats) = &image.pixels else {
                panic!("a PFM holds floats")
            };
            let view = View::new(&manifest);
            let depth = DepthIntegrator {
                scale: 7.0,
                background: manifest.background,
            };
            let mut hits = 0;
            for y in 0..11 {
                for x in 0..19 {
                    let mut sum = [0.0; 3];
                    for s in 0..view.spp() {
                        let value = depth.value(&scene, &view.ray(x, y, s));
                        hits += usize::from(value != manifest.background);
                        for c in 0..3 {
                            sum[c] += value[c];
                        }
                    }
                    let mean = sum.map(|c| (c / f64::from(view.spp())) as f32);
                    let at = (y as usize * 19 + x as usize) * 3;
                    assert_eq!(floats[at..at + 3], mean, "{sampler}{lens}: ({x}, {y})");
                }
            }
            assert!(hits > 100, "{sampler}{lens}: {hits} hits");
        }
    }

    #[test]
    fn rays_of_a_group_are_the_rays_one_by_one() {
        // Fixed offsets from the tables, random and stratified offsets, and a lens with
        // the centre sample, with random samples and with stratified ones, for groups of
        // every size up to a packet's.
        let camera = r#""camera": {"look_from": [1, 2, 3], "look_at": [0, 0.5, 0], "vfov": 50"#;
        let manifests = [
            format!(r#"{{"image": {{"width": 37, "height": 23}}, {camera}}}}}"#),
            format!(
                r#"{{"image": {{"width": 37, "height": 23}}, {camera}}},
                    "sampler": {{"type": "independent", "spp": 3, "seed": 5}}}}"#
            ),
            format!(
                r#"{{"image": {{"width": 37, "height": 23}}, {camera}}},
                    "sampler": {{"type": "stratified", "spp": 6, "seed": 2}}}}"#
            ),
            format!(
                r#"{{"image": {{"width": 37, "height": 23}}, {camera}, "aperture": 0.2, "focus_distance": 3}}}}"#
            ),
            format!(
                r#"{{"image": {{"width": 37, "height": 23}}, {camera}, "aperture": 0.2, "focus_distance": 3}},
                    "sampler": {{"type": "independent", "spp": 3, "seed": 5}}}}"#
            ),
            format!(
                r#"{{"image": {{"width": 37, "height": 23}}, {camera}, "aperture": 0.2, "focus_distance": 3}},
                    "sampler": {{"type": "stratified", "spp": 6, "seed": 2}}}}"#
            ),
        ];
        for text in &manifests {
            let manifest =
                Manifest::parse(text.as_bytes(), std::path::Path::new("t.json")).unwrap();
            let view = View::new(&manifest);
            let pixels: Vec<(u32, u32)> = (0..64).map(|i| ((i * 7) % 37, (i * 3) % 16)).collect();
            for n in 0..=pixels.len() {
                for s in 0..view.spp() {
                    let mut rays = vec![view.ray(0, 0, 0); n];
                    view.rays(&pixels[..n], 7, s, &mut rays);
                    for (ray, &(x, dy)) in rays.iter().zip(&pixels) {
                        let one = view.ray(x, 7 + dy, s);
                        let bits = |r: &Ray| {
                            [r.origin, r.direction]
                                .map(|v| v.to_array().map(f64::to_bits))
                                .concat()
                        };
                        assert_eq!(bits(ray), bits(&one), "{text}: pixel ({x}, {dy}) of {n}");
                        assert_eq!((ray.tmin, ray.tmax), (one.tmin, one.tmax));
                    }
                }
            }
        }
    }
}
