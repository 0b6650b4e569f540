//! The camera: the contract's exact mapping from pixel samples to rays, in float64.
//!
//! ```json
//! {"origin": [0, 0, 0], "right": [1, 0, 0], "up": [0, 1, 0], "forward": [0, 0, 1]}
//! {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "vfov": 90}
//! {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "aperture": 0.1, "focus_distance": 5}
//! ```
//!
//! Both forms reduce to a [`CameraFrame`]. For pixel `(x, y)` of a `W × H` image and an
//! offset `(sx, sy)` in `[0, 1)²`:
//!
//! ```text
//! u = (W / H) * (2 * (x + sx) / W - 1)
//! v = 1 - 2 * (y + sy) / H
//! direction = normalize(u * right + v * up + forward)
//! ```

use glam::DVec3;

use crate::manifest::CameraDesc;
use crate::plane::Plane;
use crate::ray::Ray;

/// The basis camera: vectors used as given (their lengths zoom the film).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraFrame {
    pub origin: DVec3,
    pub right: DVec3,
    pub up: DVec3,
    pub forward: DVec3,
}

/// A thin lens: a uniform disk of `radius` (the manifest's `aperture`) focused at
/// `focus_distance` along the view direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThinLens {
    pub radius: f64,
    pub focus_distance: f64,
}

/// The frame of a look-at camera, or `None` when `up` is parallel to the view direction.
/// `vfov` is the vertical field of view in degrees; the image's right is
/// `cross(forward, up)` (OpenGL's `gluLookAt` handedness).
pub fn look_at_frame(from: DVec3, at: DVec3, up: DVec3, vfov: f64) -> Option<CameraFrame> {
    let forward = (at - from).normalize();
    let side = forward.cross(up);
    if side.length() == 0.0 || !side.is_finite() {
        return None;
    }
    let half_height = (vfov.to_radians() / 2.0).tan();
    let right = side.normalize() * half_height;
    // `right` is zero when `vfov` is too small for its tangent; `side` is its direction.
    let true_up =
        unit(if right == DVec3::ZERO { side } else { right }).cross(forward) * half_height;
    Some(CameraFrame {
        origin: from,
        right,
        up: true_up,
        forward,
    })
}

/// `v.normalize()`, bit for bit, where `v`'s squared length is a normal float; a shorter
/// (or longer) `v` is first divided by its largest component, where `normalize` would
/// give NaN (a `vfov` of 1e-200 degrees makes `right` that short).
fn unit(v: DVec3) -> DVec3 {
    let squared = v.length_squared();
    if squared >= f64::MIN_POSITIVE && squared.is_finite() {
        v.normalize()
    } else {
        (v / v.abs().max_element()).normalize()
    }
}

/// How far outside a box [`ScreenRegion::misses_box`] must see the rays pass, relative to
/// the largest coordinate of the box's corners and of the camera's origin (plus, through
/// a lens, how far the lens reaches from it along an axis). The rays the triangles meet
/// are rounded to float32 (about 1e-7 of those coordinates, and the watertight test's own
/// rounding about as much); the margin covers that a thousand times over and grows the
/// box by a ten-thousandth. Also how far from a plane, and how steeply away from it,
/// [`ScreenRegion::misses_plane`] asks the rays to start and go.
pub const MISS_MARGIN: f64 = 1e-4;

/// The rays through a rectangle of the screen ([`Camera::region`]), for showing that none
/// of them can hit something.
///
/// Without a lens each ray starts at the origin and lies in the cone spanned by the four
/// corners' directions `u · right + v · up + forward` (a direction is affine in `u` and
/// `v`): inside each half-space bounded by the plane through two neighbouring corners
/// that holds the other two, and in front of the origin along the corners' sum.
///
/// Through a lens each ray starts at a point `l` of the lens and passes through the
/// point `q` of the focus plane that the pinhole ray of its screen point meets; the
/// lens disk lies in the square of its four corners, and the focus points of the
/// rectangle in the quadrilateral of its corners' focus points. The rays' points
/// `l + t (q − l)`, `t ≥ 0`, make an hourglass of two convex parts: from the lens to
/// the focus plane (`t ≤ 1`), the hull of the eight corners; beyond it, `q + s (q − l)`
/// for `s ≥ 0`. Something is missed when a plane separates it from each part.
#[derive(Debug, Clone, Copy)]
pub struct ScreenRegion {
    origin: DVec3,
    shape: RegionShape,
}

#[derive(Debug, Clone, Copy)]
enum RegionShape {
    /// The corners' directions, in order round the rectangle.
    Pinhole { corners: [DVec3; 4] },
    /// Relative to the camera's origin, in order round each: the lens square's corners and
    /// the rectangle's corners' focus points; the unit view direction, and the least
    /// progress along it of any `q − l` (positive).
    Lens {
        lens: [DVec3; 4],
        focus: [DVec3; 4],
        axis: DVec3,
        rise: f64,
    },
}

impl ScreenRegion {
    /// Whether every ray of the region passes outside the box from `min` to `max` grown
    /// by [`MISS_MARGIN`]: the box lies wholly outside one of the cone's half-spaces, or
    /// through a lens, a plane separates it from each part of the hourglass. `true` for
    /// an empty box (`min > max` on an axis); `false` where it cannot be shown.
    #[inline]
    pub fn misses_box(&self, [min, max]: [DVec3; 2]) -> bool {
        if (0..3).any(|axis| min[axis] > max[axis]) {
            return true;
        }
        let scale = self
            .start_reach()
            .max(min.abs().max_element())
            .max(max.abs().max_element());
        let grow = DVec3::splat(MISS_MARGIN * scale);
        let (low, high) = (min - grow, max + grow);
        // The grown box's centre seen from the origin, and its half extent.
        let centre = (low + high) * 0.5 - self.origin;
        let half = (high - low) * 0.5;
        if !(centre.is_finite() && half.is_finite()) {
            return false;
        }
        match &self.shape {
            RegionShape::Pinhole { corners } => cone_misses_box(corners, centre, half),
            RegionShape::Lens {
                lens,
                focus,
                axis,
                rise,
            } => hourglass_misses_box(lens, focus, *axis, *rise, centre, half),
        }
    }

    /// Whether every ray of the region leaves the plane behind: every ray's start lies off
    /// the plane, on one side, and every ray's direction points away from it, by
    /// [`MISS_MARGIN`] of the coordinates and of the direction's length. Such a ray meets
    /// the plane only at a negative `t`, never with `0 ≤ tmin < t`.
    pub fn misses_plane(&self, plane: &Plane) -> bool {
        let Plane { point, normal } = *plane;
        let scale = self.start_reach().max(point.abs().max_element());
        let margin = MISS_MARGIN * normal.length();
        let to_plane = point - self.origin;
        // The plane's normal turned toward the plane, seen from the origin.
        let side = to_plane.dot(normal).signum() * normal;
        let off = |start: &DVec3| {
            let height = (to_plane - *start).dot(side);
            height.is_finite() && height > margin * scale
        };
        let away = |direction: DVec3| direction.dot(side) < -margin * direction.length();
        match &self.shape {
            RegionShape::Pinhole { corners } => {
                off(&DVec3::ZERO) && corners.iter().all(|&c| away(c))
            }
            // The disk lies between the lens's corners, and every direction `q − l` is a
            // weighted sum of those from the lens's corners to the focus corners.
            RegionShape::Lens { lens, focus, .. } => {
                lens.iter().all(off) && focus.iter().all(|&q| lens.iter().all(|&l| away(q - l)))
            }
        }
    }

    /// The largest coordinate a ray's start can have: the origin's, plus through a lens
    /// how far its corners lie from the origin along any axis.
    fn start_reach(&self) -> f64 {
        let lens = match &self.shape {
            RegionShape::Pinhole { .. } => 0.0,
            RegionShape::Lens { lens, .. } => lens
                .iter()
                .map(|l| l.abs().max_element())
                .fold(0.0, f64::max),
        };
        self.origin.abs().max_element() + lens
    }
}

/// Whether the box of `centre` (seen from the origin) and `half` extent lies wholly on
/// the negative side of the plane through the origin with `normal`.
#[inline(always)]
fn beyond(normal: DVec3, centre: DVec3, half: DVec3) -> bool {
    normal.dot(centre) + normal.abs().dot(half) < 0.0
}

/// [`ScreenRegion::misses_box`] for a pinhole's cone of `corners`.
fn cone_misses_box(corners: &[DVec3; 4], centre: DVec3, half: DVec3) -> bool {
    // Behind the origin: the corners' sum points into the cone when every corner is on
    // its positive side.
    let axis = corners.iter().sum::<DVec3>();
    if corners.iter().all(|c| c.dot(axis) > 0.0) && beyond(axis, centre, half) {
        return true;
    }
    (0..4).any(|i| {
        let mut normal = corners[i].cross(corners[(i + 1) % 4]);
        // Turned into the cone: the other two corners on its positive side (the corners
        // go round one way or the other as the frame is left- or right-handed).
        let [a, b] = [2, 3].map(|k| normal.dot(corners[(i + k) % 4]));
        if a < 0.0 && b < 0.0 {
            normal = -normal;
        }
        let inward = (a > 0.0 && b > 0.0) || (a < 0.0 && b < 0.0);
        inward && beyond(normal, centre, half)
    })
}

/// Whether the ray from the origin along `direction` (`t ≥ 0`) meets the box of `centre`
/// (seen from the origin) and `half` extent, in float64 slabs.
fn ray_meets_box(direction: DVec3, centre: DVec3, half: DVec3) -> bool {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for axis in 0..3 {
        let (d, low, high) = (
            direction[axis],
            centre[axis] - half[axis],
            centre[axis] + half[axis],
        );
        if d == 0.0 {
            if low > 0.0 || high < 0.0 {
                return false;
            }
            continue;
        }
        let (a, b) = (low / d, high / d);
        near = near.max(a.min(b));
        far = far.min(a.max(b));
    }
    near <= far
}

/// [`ScreenRegion::misses_box`] through a lens (see [`ScreenRegion`]): whether some
/// plane separates the box from the hull of the `lens` and `focus` corners, and some
/// plane from the part beyond the focus plane. The planes tried are those through an edge
/// of either quadrilateral and a corner of the other (the hourglass's sides), the plane
/// of the focus points, and the box's faces.
fn hourglass_misses_box(
    lens: &[DVec3; 4],
    focus: &[DVec3; 4],
    axis: DVec3,
    rise: f64,
    centre: DVec3,
    half: DVec3,
) -> bool {
    // The ray from the lens's centre through the focus points' centre is one of the
    // region's: where it meets the box (the tiles in view), no plane is tried.
    if ray_meets_box(focus.iter().sum::<DVec3>(), centre, half) {
        return false;
    }
    // Beyond the focus plane a ray's point `q + s (q − l)` gains at least `rise` along the
    // axis per unit of `s`, so only `s ≤ reach` can come as far along it as the box.
    let nearest_focus = focus
        .iter()
        .map(|q| q.dot(axis))
        .fold(f64::INFINITY, f64::min);
    let reach = ((axis.dot(centre) + axis.abs().dot(half) - nearest_focus) / rise).max(0.0);
    let (mut before, mut after) = (false, false);
    let mut separates = |normal: DVec3| {
        let (box_low, box_high) = {
            let (c, r) = (normal.dot(centre), normal.abs().dot(half));
            (c - r, c + r)
        };
        let extremes = |points: &[DVec3; 4]| {
            let d = points.map(|p| normal.dot(p));
            (
                d.iter().copied().fold(f64::INFINITY, f64::min),
                d.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            )
        };
        let ((l_low, l_high), (q_low, q_high)) = (extremes(lens), extremes(focus));
        before |= box_high < l_low.min(q_low) || box_low > l_high.max(q_high);
        // Along `normal`, `q + s (q − l)` reaches at most `q_high + s (q_high − l_low)`.
        let top = q_high + reach * (q_high - l_low).max(0.0);
        let bottom = q_low - reach * (l_high - q_low).max(0.0);
        after |= box_high < bottom || box_low > top;
        before && after
    };
    let focus_plane = (focus[2] - focus[0]).cross(focus[3] - focus[1]);
    if [focus_plane, DVec3::X, DVec3::Y, DVec3::Z]
        .into_iter()
        .any(&mut separates)
    {
        return true;
    }
    for (points, others) in [(focus, lens), (lens, focus)] {
        for i in 0..4 {
            let (start, edge) = (points[i], points[(i + 1) % 4] - points[i]);
            if others.iter().any(|&o| separates(edge.cross(o - start))) {
                return true;
            }
        }
    }
    false
}

/// A camera bound to an image size.
#[derive(Debug, Clone, Copy)]
pub struct Camera {
    frame: CameraFrame,
    width: f64,
    height: f64,
    lens: Option<Lens>,
    /// The vector instructions its group loops use, chosen once for this CPU.
    lanes: Lanes,
}

/// The widest vector instructions the camera's group loops ([`Camera::screen_coordinates`],
/// [`Camera::pinhole_rays`], [`Camera::lens_rays`]) run on this CPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
enum Lanes {
    Plain,
    /// Four float64 lanes.
    Avx,
    /// Four, and eight for the lens points.
    Avx512,
}

impl Lanes {
    fn for_this_cpu() -> Lanes {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx") {
                return if std::is_x86_feature_detected!("avx512f") {
                    Lanes::Avx512
                } else {
                    Lanes::Avx
                };
            }
        }
        Lanes::Plain
    }
}

#[derive(Debug, Clone, Copy)]
struct Lens {
    radius: f64,
    focus_distance: f64,
    /// Unit vectors spanning the lens disk, and the unit view direction.
    lens_x: DVec3,
    lens_y: DVec3,
    axis: DVec3,
}

impl Camera {
    pub fn new(desc: &CameraDesc, width: u32, height: u32) -> Camera {
        let frame = desc.frame;
        let lens = desc.lens.map(|lens| {
            let axis = unit(frame.forward);
            // A look-at camera's `right` and `up` are zero where `vfov` is too small for
            // its tangent; the disk is then laid out around the axis.
            let (lens_x, lens_y) = if frame.right != DVec3::ZERO && frame.up != DVec3::ZERO {
                (unit(frame.right), unit(frame.up))
            } else {
                axis.any_orthonormal_pair()
            };
            Lens {
                radius: lens.radius,
                focus_distance: lens.focus_distance,
                lens_x,
                lens_y,
                axis,
            }
        });
        Camera {
            frame,
            width: f64::from(width),
            height: f64::from(height),
            lens,
            lanes: Lanes::for_this_cpu(),
        }
    }

    /// Whether rays depend on a lens sample (see [`Camera::ray`]).
    pub fn has_lens(&self) -> bool {
        self.lens.is_some()
    }

    /// The ray through offset `(sx, sy)` of pixel `(x, y)`. `lens` is a point of `[0, 1)²`
    /// mapped onto the lens disk; a pinhole camera ignores it, and `(0.5, 0.5)` is the
    /// lens centre.
    #[inline]
    pub fn ray(&self, x: u32, y: u32, sx: f64, sy: f64, lens: (f64, f64)) -> Ray {
        self.ray_at(self.screen_u(x, sx), self.screen_v(y, sy), lens)
    }

    /// The horizontal screen coordinate `u` of offset `sx` in column `x`.
    #[inline]
    pub fn screen_u(&self, x: u32, sx: f64) -> f64 {
        let (w, h) = (self.width, self.height);
        (w / h) * (2.0 * (f64::from(x) + sx) / w - 1.0)
    }

    /// The vertical screen coordinate `v` of offset `sy` in row `y`.
    #[inline]
    pub fn screen_v(&self, y: u32, sy: f64) -> f64 {
        1.0 - 2.0 * (f64::from(y) + sy) / self.height
    }

    /// [`Camera::screen_u`] of `(x, u[i])` and [`Camera::screen_v`] of `(y0 + dy, v[i])`
    /// for each pixel `(x, dy)` of `pixels`, in place: the same bits, four pixels at a
    /// time with AVX where the CPU has it. Each pixel takes two divisions, which one by one
    /// (or two by two) were most of the time a group's rays took before the camera.
    pub fn screen_coordinates(&self, pixels: &[(u32, u32)], y0: u32, u: &mut [f64], v: &mut [f64]) {
        assert!(u.len() == pixels.len() && v.len() == pixels.len());
        #[cfg(target_arch = "x86_64")]
        if self.lanes != Lanes::Plain {
            // SAFETY: the CPU has AVX.
            unsafe { self.screen_coordinates_avx(pixels, y0, u, v) };
            return;
        }
        self.screen_coordinates_in_order(pixels, y0, u, v);
    }

    /// [`Camera::screen_coordinates`] compiled for AVX.
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn screen_coordinates_avx(
        &self,
        pixels: &[(u32, u32)],
        y0: u32,
        u: &mut [f64],
        v: &mut [f64],
    ) {
        self.screen_coordinates_in_order(pixels, y0, u, v);
    }

    /// [`Camera::screen_coordinates`]'s body.
    #[inline(always)]
    fn screen_coordinates_in_order(
        &self,
        pixels: &[(u32, u32)],
        y0: u32,
        u: &mut [f64],
        v: &mut [f64],
    ) {
        for ((&(x, dy), u), v) in pixels.iter().zip(u.iter_mut()).zip(v.iter_mut()) {
            *u = self.screen_u(x, *u);
            *v = self.screen_v(y0 + dy, *v);
        }
    }

    /// The ray through screen coordinates `(u, v)` ([`Camera::screen_u`],
    /// [`Camera::screen_v`]); `lens` as for [`Camera::ray`].
    #[inline]
    pub fn ray_at(&self, u: f64, v: f64, lens: (f64, f64)) -> Ray {
        let ray = self.screen_ray(u, v);
        match &self.lens {
            Some(l) => self.through_lens(l, ray.direction, lens),
            None => ray,
        }
    }

    /// The pinhole ray through screen coordinates `(u, v)`, whatever the lens.
    #[inline(always)]
    fn screen_ray(&self, u: f64, v: f64) -> Ray {
        let f = &self.frame;
        Ray {
            origin: f.origin,
            direction: (u * f.right + v * f.up + f.forward).normalize(),
            tmin: 0.0,
            tmax: f64::INFINITY,
        }
    }

    /// The rays through screen coordinates `u0 ≤ u ≤ u1`, `v0 ≤ v ≤ v1` (see
    /// [`Camera::screen_u`]), whatever their offsets in their pixels and, through a lens,
    /// their points of the lens. `None` for coordinates that are not finite, and through a
    /// lens for corners whose pinhole rays do not go ahead along the view direction, or
    /// focus points not clear of the lens along it.
    #[inline]
    pub fn region(&self, [u0, u1]: [f64; 2], [v0, v1]: [f64; 2]) -> Option<ScreenRegion> {
        let f = &self.frame;
        let corner = |u: f64, v: f64| u * f.right + v * f.up + f.forward;
        let corners = [
            corner(u0, v0),
            corner(u1, v0),
            corner(u1, v1),
            corner(u0, v1),
        ];
        let finite = |points: &[DVec3]| points.iter().all(|p| p.is_finite());
        if !(f.origin.is_finite() && finite(&corners)) {
            return None;
        }
        let shape = match &self.lens {
            None => RegionShape::Pinhole { corners },
            Some(l) => {
                // A corner's focus point is where its pinhole ray meets the focus plane;
                // with every corner ahead along the axis, so is every pixel's, and the
                // rectangle's focus points fill the quadrilateral of the corners'.
                if !corners.iter().all(|c| c.dot(l.axis) > 0.0) {
                    return None;
                }
                let focus = corners.map(|c| c * (l.focus_distance / c.dot(l.axis)));
                let lens = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                    .map(|(x, y)| l.radius * (x * l.lens_x + y * l.lens_y));
                let rise = (focus.iter())
                    .flat_map(|q| lens.iter().map(move |l| *q - *l))
                    .map(|d| d.dot(l.axis))
                    .fold(f64::INFINITY, f64::min);
                if !(finite(&focus) && finite(&lens) && rise > 0.0 && rise.is_finite()) {
                    return None;
                }
                RegionShape::Lens {
                    lens,
                    focus,
                    axis: l.axis,
                    rise,
                }
            }
        };
        Some(ScreenRegion {
            origin: f.origin,
            shape,
        })
    }

    /// The ray from lens point `lens` (of `[0, 1)²`) through the point of the focus plane
    /// that the pinhole ray of unit `direction` meets.
    #[inline(always)]
    fn through_lens(&self, l: &Lens, direction: DVec3, lens: (f64, f64)) -> Ray {
        let f = &self.frame;
        let (dx, dy) = concentric_disk(lens.0, lens.1);
        let focus = f.origin + direction * (l.focus_distance / direction.dot(l.axis));
        let origin = f.origin + l.radius * (dx * l.lens_x + dy * l.lens_y);
        Ray {
            origin,
            direction: (focus - origin).normalize(),
            tmin: 0.0,
            tmax: f64::INFINITY,
        }
    }

    /// The rays of a pinhole camera (one without a lens: see [`Camera::lens_rays`])
    /// through screen coordinates `(u[i], v[i])`, into `out[i]`: bit for bit the rays of
    /// [`Camera::ray_at`], computed four at a time with AVX where the CPU has it, so that
    /// four rays share each square root and division.
    pub fn pinhole_rays(&self, u: &[f64], v: &[f64], out: &mut [Ray]) {
        assert!(
            self.lens.is_none(),
            "a camera with a lens takes lens points"
        );
        self.rays_at(u, v, &[], out);
    }

    /// [`Camera::ray_at`] of `(u[i], v[i], lens[i])` for each ray, into `out[i]`: the same
    /// rays, the pinhole directions four at a time (as [`Camera::pinhole_rays`]), then each
    /// taken through its lens point.
    pub fn lens_rays(&self, u: &[f64], v: &[f64], lens: &[(f64, f64)], out: &mut [Ray]) {
        assert!(lens.len() == out.len() || self.lens.is_none());
        self.rays_at(u, v, lens, out);
    }

    /// The rays through `(u[i], v[i])`, and with a lens through `lens[i]` (unread without).
    fn rays_at(&self, u: &[f64], v: &[f64], lens: &[(f64, f64)], out: &mut [Ray]) {
        assert!(u.len() == out.len() && v.len() == out.len());
        #[cfg(target_arch = "x86_64")]
        let done = if self.lanes != Lanes::Plain {
            let lens = self.lens.as_ref().map(|l| (l, lens));
            // SAFETY: the CPU has AVX.
            unsafe { self.rays_avx(u, v, lens, out) }
        } else {
            0
        };
        #[cfg(not(target_arch = "x86_64"))]
        let done = 0;
        for (i, ray) in out.iter_mut().enumerate().skip(done) {
            *ray = self.screen_ray(u[i], v[i]);
            if let Some(l) = &self.lens {
                *ray = self.through_lens(l, ray.direction, lens[i]);
            }
        }
    }

    /// The rays of [`Camera::rays_at`] for the whole groups of four, and how many that is:
    /// the pinhole rays, and with `lens` each taken through its lens point, glam's
    /// operations in glam's order, none fused, so the same bits as [`Camera::screen_ray`]
    /// and [`Camera::through_lens`]. Each vector is stored straight from the registers
    /// (reading the lanes back from memory stalled every ray on store forwarding).
    ///
    /// Through a lens, the work goes in phases over [`RAYS_PER_PHASE`] rays at a time
    /// (pinhole directions, then lens points, then the rays through them), each a short
    /// loop whose groups do not depend on each other, so that the processor overlaps
    /// several: a lens ray is a chain of two square roots and four divisions, and as one
    /// loop it made a full-HD lens job's render 5% slower (DEVELOPERS.md, "Performance
    /// notes").
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn rays_avx(
        &self,
        u: &[f64],
        v: &[f64],
        lens: Option<(&Lens, &[(f64, f64)])>,
        out: &mut [Ray],
    ) -> usize {
        use std::arch::x86_64::*;
        const GROUPS: usize = RAYS_PER_PHASE / 4;
        let f = &self.frame;
        let splat = |v: DVec3| v.to_array().map(|c| _mm256_set1_pd(c));
        let (right, up, forward, eye) = (
            splat(f.right),
            splat(f.up),
            splat(f.forward),
            splat(f.origin),
        );
        let mul = |a, b| _mm256_mul_pd(a, b);
        let add = |a, b| _mm256_add_pd(a, b);
        // glam's `normalize`: `v * (1 / sqrt((x·x + y·y) + z·z))`.
        let normalize = |[x, y, z]: [__m256d; 3]| {
            let squared = add(add(mul(x, x), mul(y, y)), mul(z, z));
            let scale = _mm256_div_pd(_mm256_set1_pd(1.0), _mm256_sqrt_pd(squared));
            [mul(x, scale), mul(y, scale), mul(z, scale)]
        };
        // The lens's constants, broadcast once.
        let lens = lens.map(|(l, points)| {
            let lanes = (
                splat(l.axis),
                splat(l.lens_x),
                splat(l.lens_y),
                _mm256_set1_pd(l.radius),
                _mm256_set1_pd(l.focus_distance),
            );
            (lanes, points)
        });
        let whole = out.len() - out.len() % 4;
        let pinhole_direction = |at: usize| {
            // SAFETY: callers pass `at + 4 <= whole <= u.len() = v.len()`.
            let (u, v) = unsafe {
                (
                    _mm256_loadu_pd(u.as_ptr().add(at)),
                    _mm256_loadu_pd(v.as_ptr().add(at)),
                )
            };
            normalize([0, 1, 2].map(|a| add(add(mul(u, right[a]), mul(v, up[a])), forward[a])))
        };
        let store = |rays: &mut [Ray], origin, direction| {
            for ray in rays.iter_mut() {
                ray.tmin = 0.0;
                ray.tmax = f64::INFINITY;
            }
            // SAFETY: AVX is enabled in this function.
            unsafe {
                store_lanes(rays, origin, |ray| &mut ray.origin);
                store_lanes(rays, direction, |ray| &mut ray.direction);
            }
        };
        let Some(((axis, lens_x, lens_y, radius, focus_distance), points)) = lens else {
            // A pinhole ray's chain is short enough for one loop.
            for (g, rays) in out[..whole].chunks_exact_mut(4).enumerate() {
                store(rays, eye, pinhole_direction(4 * g));
            }
            return whole;
        };
        let zero = _mm256_setzero_pd();
        let mut directions = [[zero; 3]; GROUPS];
        let mut disk = [(zero, zero); GROUPS];
        for first in (0..whole).step_by(RAYS_PER_PHASE) {
            let rays = &mut out[first..whole.min(first + RAYS_PER_PHASE)];
            let groups = rays.len() / 4;
            for (g, direction) in directions.iter_mut().enumerate().take(groups) {
                *direction = pinhole_direction(first + 4 * g);
            }
            let points = &points[first..first + 4 * groups];
            if self.lanes == Lanes::Avx512 {
                // SAFETY: the CPU has AVX-512F.
                unsafe { concentric_disks_avx512(points, &mut disk[..groups]) };
            } else {
                for (p, disk) in points.chunks_exact(4).zip(&mut disk[..groups]) {
                    // SAFETY: AVX is enabled in this function.
                    *disk = unsafe { concentric_disk_avx(p) };
                }
            }
            for (g, rays) in rays.chunks_exact_mut(4).enumerate() {
                let (direction, (dx, dy)) = (directions[g], disk[g]);
                let dot = add(
                    add(mul(direction[0], axis[0]), mul(direction[1], axis[1])),
                    mul(direction[2], axis[2]),
                );
                let scale = _mm256_div_pd(focus_distance, dot);
                let focus = [0, 1, 2].map(|a| add(eye[a], mul(direction[a], scale)));
                let origin = [0, 1, 2].map(|a| {
                    add(
                        eye[a],
                        mul(radius, add(mul(dx, lens_x[a]), mul(dy, lens_y[a]))),
                    )
                });
                let toward = [0, 1, 2].map(|a| _mm256_sub_pd(focus[a], origin[a]));
                store(rays, origin, normalize(toward));
            }
        }
        whole
    }
}

/// Lens rays [`Camera::rays_at`] takes through each phase of its work before the next:
/// a renderer's group of pixels.
#[cfg(target_arch = "x86_64")]
const RAYS_PER_PHASE: usize = crate::render::GROUP;

/// Stores lane `i` of `x`, `y` and `z` as the vector `field(&mut rays[i])`, for four rays.
///
/// # Safety
/// Only from a function with AVX enabled.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn store_lanes(
    rays: &mut [Ray],
    [x, y, z]: [std::arch::x86_64::__m256d; 3],
    field: impl Fn(&mut Ray) -> &mut DVec3,
) {
    use std::arch::x86_64::*;
    // SAFETY: AVX is enabled in the caller; a DVec3 is three f64s, x, y, z in order
    // (`repr(C)`).
    unsafe {
        // (x0 y0 x2 y2), (x1 y1 x3 y3), and the z pairs (z0 z1), (z2 z3).
        let (even, odd) = (_mm256_unpacklo_pd(x, y), _mm256_unpackhi_pd(x, y));
        let xy = [
            _mm256_castpd256_pd128(even),
            _mm256_castpd256_pd128(odd),
            _mm256_extractf128_pd::<1>(even),
            _mm256_extractf128_pd::<1>(odd),
        ];
        let (z01, z23) = (_mm256_castpd256_pd128(z), _mm256_extractf128_pd::<1>(z));
        let zs = [
            z01,
            _mm_unpackhi_pd(z01, z01),
            z23,
            _mm_unpackhi_pd(z23, z23),
        ];
        for ((ray, xy), z) in rays.iter_mut().zip(xy).zip(zs) {
            let vector = (field(ray) as *mut DVec3).cast::<f64>();
            _mm_storeu_pd(vector, xy);
            _mm_store_sd(vector.add(2), z);
        }
    }
}

/// [`concentric_disk`] of the four points `p`, lane by lane, with the same operations.
///
/// # Safety
/// Only from a function with AVX enabled.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn concentric_disk_avx(
    p: &[(f64, f64)],
) -> (std::arch::x86_64::__m256d, std::arch::x86_64::__m256d) {
    use std::arch::x86_64::*;
    // SAFETY: AVX is enabled in the caller.
    unsafe {
        let a = _mm256_setr_pd(p[0].0, p[1].0, p[2].0, p[3].0);
        let b = _mm256_setr_pd(p[0].1, p[1].1, p[2].1, p[3].1);
        let (one, two) = (_mm256_set1_pd(1.0), _mm256_set1_pd(2.0));
        let x = _mm256_sub_pd(_mm256_mul_pd(two, a), one);
        let y = _mm256_sub_pd(_mm256_mul_pd(two, b), one);
        let magnitude = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
        let (ax, ay) = (_mm256_and_pd(x, magnitude), _mm256_and_pd(y, magnitude));
        // Where |x| > |y|: φ from y/x, the point (x cos φ, x sin φ); elsewhere φ from x/y,
        // the point (y sin φ, y cos φ).
        let wide = _mm256_cmp_pd::<_CMP_GT_OQ>(ax, ay);
        let (r, other) = (_mm256_blendv_pd(y, x, wide), _mm256_blendv_pd(x, y, wide));
        let phi = _mm256_mul_pd(
            _mm256_set1_pd(std::f64::consts::FRAC_PI_4),
            _mm256_div_pd(other, r),
        );
        let (sin, cos) = sin_cos_quarter_avx(phi);
        let first = _mm256_mul_pd(r, _mm256_blendv_pd(sin, cos, wide));
        let second = _mm256_mul_pd(r, _mm256_blendv_pd(cos, sin, wide));
        // The centre: x = y = 0 (where 0/0 made φ NaN).
        let zero = _mm256_setzero_pd();
        let centre = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_EQ_OQ>(x, zero),
            _mm256_cmp_pd::<_CMP_EQ_OQ>(y, zero),
        );
        (
            _mm256_blendv_pd(first, zero, centre),
            _mm256_blendv_pd(second, zero, centre),
        )
    }
}

/// A lens point `(f64, f64)` is its two numbers in order, nothing between or after them
/// ([`concentric_disks_avx512`] loads eight points as sixteen numbers). Rust does not
/// promise a tuple's layout, so it is checked when compiling.
#[cfg(target_arch = "x86_64")]
const POINT_LAYOUT: () = assert!(
    std::mem::size_of::<(f64, f64)>() == 16
        && std::mem::offset_of!((f64, f64), 0) == 0
        && std::mem::offset_of!((f64, f64), 1) == 8
);

/// [`concentric_disk_avx`] of each group of four `points`, into `out` (a group each),
/// eight points at a time with AVX-512 (the last four alone): the same operations lane
/// by lane, so the same bits.
///
/// # Safety
/// The CPU must have AVX-512F; `points` must hold four points per entry of `out`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn concentric_disks_avx512(
    points: &[(f64, f64)],
    out: &mut [(std::arch::x86_64::__m256d, std::arch::x86_64::__m256d)],
) {
    use std::arch::x86_64::*;
    assert_eq!(points.len(), 4 * out.len());
    let () = POINT_LAYOUT;
    let (one, two, zero) = (
        _mm512_set1_pd(1.0),
        _mm512_set1_pd(2.0),
        _mm512_setzero_pd(),
    );
    // Lane i of a point pair's two registers: its first (even) or second (odd) number.
    let (even, odd) = (
        _mm512_setr_epi64(0, 2, 4, 6, 8, 10, 12, 14),
        _mm512_setr_epi64(1, 3, 5, 7, 9, 11, 13, 15),
    );
    let mut pairs = out.chunks_exact_mut(2);
    for (p, out) in points.chunks_exact(8).zip(&mut pairs) {
        // SAFETY: eight points are sixteen contiguous f64s, each point's first number
        // first (`POINT_LAYOUT`); AVX-512F is enabled here.
        let (a, b) = unsafe {
            let numbers = p.as_ptr().cast::<f64>();
            let (low, high) = (_mm512_loadu_pd(numbers), _mm512_loadu_pd(numbers.add(8)));
            (
                _mm512_permutex2var_pd(low, even, high),
                _mm512_permutex2var_pd(low, odd, high),
            )
        };
        let x = _mm512_sub_pd(_mm512_mul_pd(two, a), one);
        let y = _mm512_sub_pd(_mm512_mul_pd(two, b), one);
        let wide = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(_mm512_abs_pd(x), _mm512_abs_pd(y));
        let (r, other) = (
            _mm512_mask_blend_pd(wide, y, x),
            _mm512_mask_blend_pd(wide, x, y),
        );
        let phi = _mm512_mul_pd(
            _mm512_set1_pd(std::f64::consts::FRAC_PI_4),
            _mm512_div_pd(other, r),
        );
        let (sin, cos) = sin_cos_quarter_lanes!(phi, _mm512_mul_pd, _mm512_add_pd, _mm512_set1_pd);
        let first = _mm512_mul_pd(r, _mm512_mask_blend_pd(wide, sin, cos));
        let second = _mm512_mul_pd(r, _mm512_mask_blend_pd(wide, cos, sin));
        // The centre: x = y = 0 (where 0/0 made φ NaN).
        let centre =
            _mm512_cmp_pd_mask::<_CMP_EQ_OQ>(x, zero) & _mm512_cmp_pd_mask::<_CMP_EQ_OQ>(y, zero);
        let (dx, dy) = (
            _mm512_mask_blend_pd(centre, first, zero),
            _mm512_mask_blend_pd(centre, second, zero),
        );
        let halves = |v| (_mm512_castpd512_pd256(v), _mm512_extractf64x4_pd::<1>(v));
        let ((dx0, dx1), (dy0, dy1)) = (halves(dx), halves(dy));
        out[0] = (dx0, dy0);
        out[1] = (dx1, dy1);
    }
    if let [last] = pairs.into_remainder() {
        // SAFETY: AVX-512F implies AVX.
        *last = unsafe { concentric_disk_avx(&points[points.len() - 4..]) };
    }
}

/// [`sin_cos_quarter`] in the lanes that `$mul`, `$add` and `$splat` (intrinsics of one
/// width) work on: [`sin_cos_quarter`]'s operations in its order, so that the scalar and
/// vector paths give the same bits. Expanded where the width's features are enabled.
#[cfg(target_arch = "x86_64")]
macro_rules! sin_cos_quarter_lanes {
    ($phi:expr, $mul:ident, $add:ident, $splat:ident) => {{
        let f = &INVERSE_FACTORIAL;
        let phi = $phi;
        let p2 = $mul(phi, phi);
        let mut sin = $splat(-f[15]);
        let mut cos = $splat(f[16]);
        for k in (0..7).rev() {
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            sin = $add($splat(sign * f[2 * k + 1]), $mul(p2, sin));
            cos = $add($splat(-sign * f[2 * k + 2]), $mul(p2, cos));
        }
        ($mul(phi, sin), $add($splat(1.0), $mul(p2, cos)))
    }};
}
#[cfg(target_arch = "x86_64")]
use sin_cos_quarter_lanes;

/// [`sin_cos_quarter`] of four angles, with the same operations.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn sin_cos_quarter_avx(
    phi: std::arch::x86_64::__m256d,
) -> (std::arch::x86_64::__m256d, std::arch::x86_64::__m256d) {
    use std::arch::x86_64::*;
    // SAFETY (every intrinsic below): only called from functions with AVX enabled, into
    // which it is inlined.
    unsafe { sin_cos_quarter_lanes!(phi, _mm256_mul_pd, _mm256_add_pd, _mm256_set1_pd) }
}

/// Shirley and Chiu's area-preserving map from the unit square to the unit disk. Its
/// angle is within a quarter turn of an axis, whose sine and cosine [`sin_cos_quarter`]
/// gives.
#[inline(always)]
fn concentric_disk(a: f64, b: f64) -> (f64, f64) {
    let (x, y) = (2.0 * a - 1.0, 2.0 * b - 1.0);
    if x == 0.0 && y == 0.0 {
        return (0.0, 0.0);
    }
    if x.abs() > y.abs() {
        let (sin, cos) = sin_cos_quarter(std::f64::consts::FRAC_PI_4 * (y / x));
        (x * cos, x * sin)
    } else {
        // The angle is π/2 − φ: its cosine is sin φ, its sine cos φ.
        let (sin, cos) = sin_cos_quarter(std::f64::consts::FRAC_PI_4 * (x / y));
        (y * sin, y * cos)
    }
}

/// `1/n!` for `n` in `0..=16`.
const INVERSE_FACTORIAL: [f64; 17] = {
    let mut table = [1.0; 17];
    let mut n = 1;
    while n < 17 {
        table[n] = table[n - 1] / n as f64;
        n += 1;
    }
    table
};

/// `(sin φ, cos φ)` for `|φ| ≤ π/4`, by their Taylor series up to `φ¹⁵` and `φ¹⁶` (the
/// first terms left out are below 5·10⁻¹⁷ and 3·10⁻¹⁸ there): within a few units in the
/// last place of the library's, without a call, and so cheap to inline where camera rays
/// are made.
#[inline(always)]
fn sin_cos_quarter(phi: f64) -> (f64, f64) {
    let f = &INVERSE_FACTORIAL;
    let p2 = phi * phi;
    let mut sin = -f[15];
    let mut cos = f[16];
    for k in (0..7).rev() {
        // sin: 1/1! − φ²/3! + …; cos: 1/0! − φ²/2! + …, alternating from the innermost.
        let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
        sin = sign * f[2 * k + 1] + p2 * sin;
        cos = -sign * f[2 * k + 2] + p2 * cos;
    }
    (phi * sin, 1.0 + p2 * cos)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole(frame: CameraFrame) -> CameraDesc {
        CameraDesc { frame, lens: None }
    }

    #[test]
    fn look_at_right_is_world_plus_x_when_looking_down_minus_z() {
        let frame = look_at_frame(DVec3::new(0.0, 0.0, 5.0), DVec3::ZERO, DVec3::Y, 90.0).unwrap();
        assert!((frame.right - DVec3::X).length() < 1e-15, "{}", frame.right);
        assert!((frame.up - DVec3::Y).length() < 1e-15, "{}", frame.up);
        assert_eq!(frame.forward, DVec3::NEG_Z);
    }

    #[test]
    fn look_at_scales_right_and_up_by_half_the_field_of_view() {
        let frame = look_at_frame(DVec3::ZERO, DVec3::Z, DVec3::Y, 60.0).unwrap();
        let k = (30f64).to_radians().tan();
        assert!((frame.right.length() - k).abs() < 1e-15);
        assert!((frame.up.length() - k).abs() < 1e-15);
        // Looking down +z with up +y, the image's right is world -x: the mirror of the
        // default basis camera.
        assert!(frame.right.x < 0.0);
    }

    #[test]
    fn a_field_of_view_too_narrow_for_normalize_still_gives_the_view_direction() {
        // `right` is then shorter than the square root of the smallest normal float, so
        // `normalize` alone would give NaN; every ray, pinhole or through a lens focused
        // on the axis, must still be (nearly) the view direction.
        let (from, at) = (DVec3::new(0.0, 0.6, 5.0), DVec3::new(0.0, 0.4, 0.0));
        let forward = (at - from).normalize();
        for vfov in [1e-100, 1e-200, 31e-300, 5e-324] {
            let frame = look_at_frame(from, at, DVec3::Y, vfov).unwrap();
            assert!(frame.up.is_finite() && frame.right.is_finite(), "{vfov}");
            for lens in [
                None,
                Some(ThinLens {
                    radius: 0.1,
                    focus_distance: 5.0,
                }),
            ] {
                let camera = Camera::new(&CameraDesc { frame, lens }, 32, 24);
                for (x, y) in [(0, 0), (31, 23), (16, 12)] {
                    let ray = camera.ray(x, y, 0.5, 0.5, (0.9, 0.2));
                    let axis = if lens.is_some() {
                        (from + forward * 5.0 - ray.origin).normalize()
                    } else {
                        forward
                    };
                    assert!((ray.direction - axis).length() < 1e-15, "{vfov} {ray:?}");
                }
            }
        }
    }

    #[test]
    fn unit_is_normalize_bit_for_bit_where_normalize_works() {
        let mut random = crate::test_random::XorShift::new(5);
        for _ in 0..10_000 {
            let v = DVec3::new(random.unit_f64(), random.unit_f64(), random.unit_f64()) - 0.5;
            let scale = 2f64.powi(random.below(1000) as i32 - 500);
            assert_eq!(unit(v * scale), (v * scale).normalize(), "{v}");
            // Far outside that range, the same direction.
            for far in [v * 1e-300, v * 1e300] {
                assert!((unit(far) - v.normalize()).length() < 1e-15, "{far}");
            }
        }
    }

    #[test]
    fn up_parallel_to_the_view_is_refused() {
        assert!(look_at_frame(DVec3::ZERO, DVec3::Y, DVec3::Y, 60.0).is_none());
        assert!(look_at_frame(DVec3::ZERO, DVec3::Y, DVec3::NEG_Y * 3.0, 60.0).is_none());
    }

    #[test]
    fn the_default_camera_maps_pixel_centres_as_the_contract_says() {
        let frame = CameraFrame {
            origin: DVec3::ZERO,
            right: DVec3::X,
            up: DVec3::Y,
            forward: DVec3::Z,
        };
        let camera = Camera::new(&pinhole(frame), 640, 480);
        for (x, y) in [(0, 0), (639, 479), (320, 240), (17, 400)] {
            let ray = camera.ray(x, y, 0.5, 0.5, (0.5, 0.5));
            // Integer form of the mapping: u = (2x + 1 - W) / H, v = (H - 2y - 1) / H.
            let u = (2.0 * x as f64 + 1.0 - 640.0) / 480.0;
            let v = (480.0 - 2.0 * y as f64 - 1.0) / 480.0;
            let expected = DVec3::new(u, v, 1.0).normalize();
            assert!((ray.direction - expected).length() < 1e-15, "({x}, {y})");
            assert_eq!(ray.origin, DVec3::ZERO);
        }
    }

    #[test]
    fn rays_in_groups_are_bit_for_bit_the_rays_one_by_one() {
        // Frames of every scale and orientation, pinholes and lenses, and runs of every
        // length around the vector width (the rest goes one by one). Lens points include
        // the centre, the diagonals (|x| = |y|) and the square's edges.
        let mut random = crate::test_random::XorShift::new(0x2545_f491_4f6c_dd1d);
        let mut next = || random.unit_f64() * 2.0 - 1.0;
        let special = [
            (0.5, 0.5),
            (0.25, 0.25),
            (0.75, 0.25),
            (0.0, 0.0),
            (0.0, 0.7),
            (0.3, 0.0),
        ];
        let bits = |r: &Ray| {
            [r.origin, r.direction]
                .map(|v| v.to_array().map(f64::to_bits))
                .concat()
        };
        for scale in [1e-9, 0.37, 1.0, 3e4, 1e12] {
            let mut v3 = || DVec3::new(next(), next(), next()) * scale;
            let frame = CameraFrame {
                origin: v3(),
                right: v3(),
                up: v3(),
                forward: v3(),
            };
            let thin_lens = ThinLens {
                radius: 0.3 * scale,
                focus_distance: 2.0 * scale,
            };
            for lens in [None, Some(thin_lens)] {
                let camera = Camera::new(&CameraDesc { frame, lens }, 1920, 1080);
                // Every length around the vector width, and around the phases' length.
                for n in (0..=9).chain([63, 64, 65, 130]) {
                    let u: Vec<f64> = (0..n).map(|_| next() * 2.0).collect();
                    let v: Vec<f64> = (0..n).map(|_| next()).collect();
                    let points: Vec<(f64, f64)> = (0..n)
                        .map(|i| {
                            special
                                .get(i + n % 3)
                                .copied()
                                .unwrap_or((next().abs(), next().abs()))
                        })
                        .collect();
                    let unused = camera.ray_at(0.0, 0.0, (0.5, 0.5));
                    let mut rays = vec![unused; n];
                    match lens {
                        None => camera.pinhole_rays(&u, &v, &mut rays),
                        Some(_) => camera.lens_rays(&u, &v, &points, &mut rays),
                    }
                    for i in 0..n {
                        let one = camera.ray_at(u[i], v[i], points[i]);
                        assert_eq!(
                            bits(&rays[i]),
                            bits(&one),
                            "scale {scale}, {lens:?}, ray {i} of {n}"
                        );
                        assert_eq!((rays[i].tmin, rays[i].tmax), (one.tmin, one.tmax));
                    }
                }
            }
        }
    }

    #[test]
    fn screen_coordinates_in_groups_are_bit_for_bit_those_one_by_one() {
        // Image sizes whose ratios and divisions round, offsets anywhere in the pixel
        // (its edges too), and runs of every length around the vector width.
        let mut random = crate::test_random::XorShift::new(0x9e37_79b9_7f4a_7c15);
        let frame = CameraFrame {
            origin: DVec3::ZERO,
            right: DVec3::X,
            up: DVec3::Y,
            forward: DVec3::NEG_Z,
        };
        for (width, height) in [(1920, 1080), (641, 479), (3, 7), (1, 1), (16_384, 9)] {
            let camera = Camera::new(&pinhole(frame), width, height);
            for n in 0..=11 {
                let pixels: Vec<(u32, u32)> = (0..n)
                    .map(|i| {
                        let x = (random.unit_f64() * f64::from(width)) as u32;
                        (x.min(width - 1), i as u32 % height.min(8))
                    })
                    .collect();
                let offset = |i: usize, r: f64| {
                    [0.0, 0.5, 1.0 - f64::EPSILON / 2.0]
                        .get(i % 4)
                        .copied()
                        .unwrap_or(r)
                };
                let u: Vec<f64> = (0..n).map(|i| offset(i, random.unit_f64())).collect();
                let v: Vec<f64> = (0..n).map(|i| offset(i + 1, random.unit_f64())).collect();
                let y0 = height.saturating_sub(8);
                let (mut gu, mut gv) = (u.clone(), v.clone());
                camera.screen_coordinates(&pixels, y0, &mut gu, &mut gv);
                for (i, &(x, dy)) in pixels.iter().enumerate() {
                    let one = (camera.screen_u(x, u[i]), camera.screen_v(y0 + dy, v[i]));
                    assert_eq!(
                        (gu[i].to_bits(), gv[i].to_bits()),
                        (one.0.to_bits(), one.1.to_bits()),
                        "{width}x{height}, pixel {i} of {n}"
                    );
                }
            }
        }
    }

    #[test]
    fn quarter_turn_sines_and_cosines_are_the_library_s_to_within_two_ulps() {
        let steps = 200_000;
        for i in 0..=steps {
            let phi = std::f64::consts::FRAC_PI_4 * (2.0 * f64::from(i) / f64::from(steps) - 1.0);
            let (sin, cos) = sin_cos_quarter(phi);
            let close = |ours: f64, library: f64| {
                (ours - library).abs() <= 2.0 * f64::EPSILON * library.abs()
            };
            assert!(
                close(sin, phi.sin()),
                "sin {phi}: {sin} against {}",
                phi.sin()
            );
            assert!(
                close(cos, phi.cos()),
                "cos {phi}: {cos} against {}",
                phi.cos()
            );
        }
    }

    #[test]
    fn the_lens_disk_map_is_shirley_and_chius() {
        // Against the map written with the library's sine and cosine of the whole angle.
        let reference = |a: f64, b: f64| {
            let (x, y) = (2.0 * a - 1.0, 2.0 * b - 1.0);
            if x == 0.0 && y == 0.0 {
                return (0.0, 0.0);
            }
            let (r, theta) = if x.abs() > y.abs() {
                (x, std::f64::consts::FRAC_PI_4 * (y / x))
            } else {
                (
                    y,
                    std::f64::consts::FRAC_PI_2 - std::f64::consts::FRAC_PI_4 * (x / y),
                )
            };
            (r * theta.cos(), r * theta.sin())
        };
        let n = 301;
        for i in 0..n {
            for j in 0..n {
                let (a, b) = (
                    f64::from(i) / f64::from(n - 1),
                    f64::from(j) / f64::from(n - 1),
                );
                let (x, y) = concentric_disk(a, b);
                let (rx, ry) = reference(a, b);
                assert!(
                    (x - rx).abs() <= 1e-15 && (y - ry).abs() <= 1e-15,
                    "({a}, {b}): ({x}, {y}) against ({rx}, {ry})"
                );
                assert!(x.hypot(y) <= 1.0 + 1e-15);
            }
        }
    }

    #[test]
    fn a_thin_lens_keeps_the_focus_plane_sharp() {
        let frame = look_at_frame(DVec3::new(0.0, 0.0, 5.0), DVec3::ZERO, DVec3::Y, 50.0).unwrap();
        let desc = CameraDesc {
            frame,
            lens: Some(ThinLens {
                radius: 0.5,
                focus_distance: 5.0,
            }),
        };
        let camera = Camera::new(&desc, 64, 48);
        let centre = camera.ray(10, 20, 0.3, 0.7, (0.5, 0.5));
        for lens in [(0.0, 0.0), (0.9, 0.1), (0.25, 0.75)] {
            let ray = camera.ray(10, 20, 0.3, 0.7, lens);
            assert!((ray.origin - frame.origin).length() <= 0.5 + 1e-12);
            // Every lens position sees the same point of the plane z = 0.
            let t = -ray.origin.z / ray.direction.z;
            let t0 = -centre.origin.z / centre.direction.z;
            assert!((ray.at(t) - centre.at(t0)).length() < 1e-12, "{lens:?}");
        }
    }

    /// Whether the ray from `origin` along `direction` (`t ≥ 0`) enters the box from
    /// `low` to `high`, in float64 slabs.
    fn enters(origin: DVec3, direction: DVec3, low: DVec3, high: DVec3) -> bool {
        let (mut near, mut far) = (0.0f64, f64::INFINITY);
        for axis in 0..3 {
            let (o, d) = (origin[axis], direction[axis]);
            if d == 0.0 {
                if o < low[axis] || o > high[axis] {
                    return false;
                }
                continue;
            }
            let (a, b) = ((low[axis] - o) / d, (high[axis] - o) / d);
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
        near <= far
    }

    /// Random cameras (look-at, and bases used as given: skewed, short, long; half of
    /// them through a lens up to twice the scale wide, focused near or far), regions of
    /// their screens (pixel rectangles, as the render loop asks), boxes and planes, at
    /// several scales and distances from the origin. A box around a point of one of the
    /// region's rays (a corner's, an edge's or an inner one, from the lens's rim or
    /// inside), or a plane through it, is never said to be missed; of the boxes and planes
    /// put anywhere, none said to be missed is met by any of the region's rays sampled
    /// along its edges and inside, from along the lens's rim and inside (float64 slabs,
    /// [`Plane::intersect`]), and many are said to be missed, with a lens and without.
    #[test]
    fn a_region_misses_only_boxes_and_planes_that_none_of_its_rays_meets() {
        use crate::test_random::XorShift;
        fn uniform(random: &mut XorShift, low: f64, high: f64) -> f64 {
            low + (high - low) * random.unit_f64()
        }
        fn vector(random: &mut XorShift, length: f64) -> DVec3 {
            DVec3::from_array([(); 3].map(|_| uniform(random, -1.0, 1.0))) * length
        }
        let random = &mut XorShift::new(0x5eed_b0c5);
        // Counts without a lens and with one.
        let (mut anywhere, mut missed, mut planes_missed) = ([0; 2], [0; 2], [0; 2]);
        let mut near_missed = [0; 2];
        let mut no_region = 0;
        for case in 0..4000 {
            let scale = [1e-3, 1.0, 1e3][case % 3];
            let offset = DVec3::splat([0.0, 1e4][case / 3 % 2] * scale);
            let origin = offset + vector(random, 10.0 * scale);
            let frame = if case % 4 == 0 {
                CameraFrame {
                    origin,
                    right: vector(random, 2.0),
                    up: vector(random, 2.0),
                    forward: vector(random, 2.0),
                }
            } else {
                let at = offset + vector(random, 5.0 * scale);
                let vfov = 1.0 + 178.0 * (case as f64 * 0.618_034).fract();
                match look_at_frame(origin, at, DVec3::Y, vfov) {
                    Some(frame) => frame,
                    None => continue,
                }
            };
            let (width, height) = (1 + case as u32 * 37 % 700, 1 + case as u32 * 53 % 500);
            let with_lens = case / 8 % 2 == 1;
            let lens = with_lens.then(|| ThinLens {
                radius: uniform(random, 0.0, 2.0) * scale,
                focus_distance: uniform(random, 0.05, 50.0) * scale,
            });
            let camera = Camera::new(&CameraDesc { frame, lens }, width, height);
            let x0 = (case as u32 * 7919) % width;
            let y0 = (case as u32 * 104_729) % height;
            let (w, h) = (
                1 + (case as u32 % 8).min(width - x0 - 1),
                1 + (case as u32 / 8 % 8),
            );
            let h = h.min(height - y0);
            let (x1, y1) = (x0 + w, y0 + h);
            let u = [camera.screen_u(x0, 0.0), camera.screen_u(x1, 0.0)];
            let v = [camera.screen_v(y1, 0.0), camera.screen_v(y0, 0.0)];
            // The region's rays: its corners, points along its edges, points inside.
            let mut samples = Vec::new();
            for k in 0..=8 {
                let a = f64::from(k) / 8.0;
                for (fx, fy) in [(a, 0.0), (a, 1.0), (0.0, a), (1.0, a)] {
                    samples.push((fx, fy));
                }
            }
            for _ in 0..16 {
                samples.push((uniform(random, 0.0, 1.0), uniform(random, 0.0, 1.0)));
            }
            // Points of the lens: the rim of its square of samples is the disk's rim.
            let mut lens_samples = vec![(0.5, 0.5)];
            if with_lens {
                for k in 0..8 {
                    let a = f64::from(k) / 8.0;
                    lens_samples.extend([(a, 0.0), (1.0 - a, 1.0), (0.0, 1.0 - a), (1.0, a)]);
                }
                lens_samples.push((uniform(random, 0.0, 1.0), uniform(random, 0.0, 1.0)));
            }
            let samples: Vec<_> = (samples.iter())
                .flat_map(|&s| lens_samples.iter().map(move |&l| (s, l)))
                .collect();
            let rays: Vec<Ray> = samples
                .iter()
                .map(|&((fx, fy), lens)| {
                    let sx = f64::from(x0) + fx * f64::from(w);
                    let sy = f64::from(y0) + fy * f64::from(h);
                    let (px, py) = (
                        sx.floor().min(f64::from(x1 - 1)),
                        sy.floor().min(f64::from(y1 - 1)),
                    );
                    camera.ray(px as u32, py as u32, sx - px, sy - py, lens)
                })
                .collect();

            // A box around a point of one of the rays: entered, so never missed.
            let ray = rays[case % rays.len()];
            let point = ray.at(uniform(random, 0.01, 100.0) * scale);
            let half = DVec3::splat(uniform(random, 1e-9, 1.0) * scale);
            assert!(
                enters(ray.origin, ray.direction, point - half, point + half),
                "case {case}: the reference"
            );
            let Some(region) = camera.region(u, v) else {
                assert!(with_lens, "case {case}: a pinhole's region");
                no_region += 1;
                continue;
            };
            assert!(
                !region.misses_box([point - half, point + half]),
                "case {case}: a box on a ray of the region"
            );
            // A plane through that point, at any angle but along the ray: crossed.
            let normal = (vector(random, 1.0) + DVec3::X * 1e-3).normalize();
            let plane = Plane { point, normal };
            if ray.direction.dot(normal) != 0.0 {
                assert!(
                    !region.misses_plane(&plane),
                    "case {case}: a plane a ray of the region crosses"
                );
            }

            // A plane anywhere.
            let plane = Plane {
                point: offset + vector(random, 20.0 * scale),
                normal: vector(random, 1.0).normalize(),
            };
            if region.misses_plane(&plane) {
                planes_missed[usize::from(with_lens)] += 1;
                for (ray, sample) in rays.iter().zip(&samples) {
                    assert!(
                        plane.intersect(ray, f64::INFINITY).is_none(),
                        "case {case}: a ray at {sample:?} of the region crosses a missed plane"
                    );
                }
            }

            // Whether the box is said to be missed; if so, no ray of the region enters it.
            let missed_box = |[low, high]: [DVec3; 2], place: &str| {
                let said = region.misses_box([low, high]);
                if said {
                    for (ray, sample) in rays.iter().zip(&samples) {
                        assert!(
                            !enters(ray.origin, ray.direction, low, high),
                            "case {case}: a ray at {sample:?} of the region enters a missed box {place}"
                        );
                    }
                }
                said
            };

            // A small box near a point of one of the rays, often just outside them all.
            let ray = rays[(case * 7 + 3) % rays.len()];
            let distance = uniform(random, 0.0, 100.0) * scale;
            // Off by a thousandth of the distance to a third of it.
            let off = distance * 10f64.powf(uniform(random, -3.0, -0.5));
            let centre = ray.at(distance) + vector(random, off);
            let half = vector(random, off / 4.0).abs();
            let near = missed_box([centre - half, centre + half], "near the rays");
            near_missed[usize::from(with_lens)] += usize::from(near);

            // A box anywhere.
            let centre = offset + vector(random, 50.0 * scale);
            let half = vector(random, 5.0 * scale).abs();
            anywhere[usize::from(with_lens)] += 1;
            let far = missed_box([centre - half, centre + half], "anywhere");
            missed[usize::from(with_lens)] += usize::from(far);
        }
        // Of the boxes just beside the rays, over a fifth are missed: the tests are tight
        // (through a lens, without the planes through the sides, a ninth).
        for k in 0..2 {
            assert!(
                missed[k] * 4 > anywhere[k] && near_missed[k] * 5 > anywhere[k],
                "{missed:?} and {near_missed:?} near the rays of {anywhere:?} boxes missed"
            );
        }
        assert!(
            planes_missed[0] * 8 > anywhere[0] && planes_missed[1] * 8 > anywhere[1],
            "{planes_missed:?} of {anywhere:?} planes missed"
        );
        assert!(
            no_region * 10 < anywhere[1],
            "{no_region} lens regions none"
        );
    }

    #[test]
    fn regions_miss_what_lies_behind_and_empty_boxes_and_say_nothing_of_the_unknown() {
        let frame = look_at_frame(DVec3::new(0.0, 0.0, 5.0), DVec3::ZERO, DVec3::Y, 40.0).unwrap();
        let behind = [DVec3::new(-1.0, -1.0, 9.0), DVec3::new(1.0, 1.0, 11.0)];
        let (u, v) = ([-0.1, 0.1], [-0.1, 0.1]);
        let region = Camera::new(&pinhole(frame), 64, 64).region(u, v).unwrap();
        assert!(region.misses_box(behind));
        // Through a lens of radius 0.1: what lies behind is missed; a box a tenth ahead of
        // the lens and 0.08 to the side, outside the pinhole's cone, is on rays from the
        // lens's rim; a box beside the focus points is passed by, and one as far beyond
        // them as they are from the lens, outside the pinhole's cone, is not.
        let lens = Some(ThinLens {
            radius: 0.1,
            focus_distance: 5.0,
        });
        let through_lens = Camera::new(&CameraDesc { frame, lens }, 64, 64)
            .region(u, v)
            .unwrap();
        assert!(through_lens.misses_box(behind));
        let before_lens = [DVec3::new(0.08, -0.01, 4.89), DVec3::new(0.09, 0.01, 4.91)];
        assert!(region.misses_box(before_lens));
        assert!(!through_lens.misses_box(before_lens));
        let beside_focus = [DVec3::new(0.3, -0.05, -0.05), DVec3::new(0.4, 0.05, 0.05)];
        assert!(through_lens.misses_box(beside_focus));
        let beyond_focus = [DVec3::new(0.4, -0.05, -5.05), DVec3::new(0.45, 0.05, -4.95)];
        assert!(region.misses_box(beyond_focus));
        assert!(!through_lens.misses_box(beyond_focus));
        // A screen corner whose pinhole ray points back from the lens's axis: no region.
        let skewed = CameraFrame {
            origin: DVec3::ZERO,
            right: DVec3::new(1.0, 0.0, -1.0),
            up: DVec3::Y,
            forward: DVec3::Z,
        };
        let camera = Camera::new(
            &CameraDesc {
                frame: skewed,
                lens,
            },
            64,
            64,
        );
        assert!(camera.region([0.5, 0.9], v).is_some());
        assert!(camera.region([0.5, 1.1], v).is_none());
        let empty = [DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)];
        assert!(region.misses_box(empty));
        let not_finite = [DVec3::splat(f64::NAN), DVec3::splat(1.0)];
        assert!(!region.misses_box(not_finite));
        // A floor below a camera looking down at it; the same floor seen from below.
        let floor = Plane {
            point: DVec3::new(0.0, -1.0, 0.0),
            normal: DVec3::Y,
        };
        assert!(!region.misses_plane(&floor));
        let up = look_at_frame(DVec3::ZERO, DVec3::new(0.0, 5.0, 1.0), DVec3::Y, 40.0).unwrap();
        let sky = Camera::new(&pinhole(up), 64, 64).region(u, v).unwrap();
        assert!(sky.misses_plane(&floor));
        // A camera on the plane says nothing.
        let on = Plane {
            point: DVec3::ZERO,
            normal: DVec3::Y,
        };
        assert!(!sky.misses_plane(&on));
    }
}
