//! The Embree reference tracer (cargo feature `embree`): triangles and spheres are traced by
//! Embree 3 (`rtcIntersect1`/`rtcOccluded1`) in robust mode, `RTC_SCENE_FLAG_ROBUST`, so
//! rays cannot slip through shared edges. It shares no intersection code with raybatch:
//! triangles are Embree's triangle geometry, spheres its `SPHERE_POINT` geometry (float32
//! centre and radius, as Embree stores them). Planes, which Embree lacks, stay analytic.
//!
//! Rays are the same float64 camera rays rounded to float32 as raybatch rounds them, and
//! the strict interval `tmin < t < tmax` becomes Embree's inclusive `[tnear, tfar]` one
//! float32 step inside it. A ray Embree would refuse (it aborts the process on NaN or
//! huge values) hits nothing without reaching it; [`Unchecked`] leaves that check out,
//! for `raybatch bench`, whose Embree figures are those of a program calling Embree.

use embree3::{BufferUsage, Device, Format, GeometryKind, IntersectContext, RayHit, SceneFlags};
use glam::DVec3;

use crate::bvh::{f32_at_least, f32_at_most};
use crate::plane::Plane;
use crate::ray::Ray;
use crate::scene::{
    Hit, Primitive, SceneCounts, SceneGeometry, Tracer, nearest_plane, nearest_planes,
};
use crate::sphere::Sphere;
use crate::triangle;

/// Embree's "no geometry" id.
const INVALID: u32 = u32::MAX;

/// A scene built by Embree.
pub struct EmbreeScene {
    scene: embree3::Scene<'static>,
    _device: Device,
    triangle_geometry: Option<u32>,
    sphere_geometry: Option<u32>,
    /// Kept for normals (computed from the stored vertices, as raybatch does).
    triangles: Vec<[[f32; 3]; 3]>,
    spheres: Vec<Sphere>,
    planes: Vec<Plane>,
    counts: SceneCounts,
}

/// Embree refused to build the scene.
#[derive(Debug, thiserror::Error)]
#[error("Embree: {0}")]
pub struct EmbreeError(String);

impl EmbreeScene {
    pub fn build(geometry: &SceneGeometry) -> Result<EmbreeScene, EmbreeError> {
        let fail = |what: &str, e: embree3::Error| EmbreeError(format!("{what}: {e:?}"));
        let device = Device::new().map_err(|e| fail("cannot create a device", e))?;
        let mut scene = device
            .create_scene()
            .map_err(|e| fail("cannot create a scene", e))?;
        scene.set_flags(SceneFlags::ROBUST);
        let SceneGeometry {
            triangles,
            spheres,
            planes,
            ..
        } = geometry;

        let mut triangle_geometry = None;
        if !triangles.is_empty() {
            let n = triangles.len();
            let mut mesh = device
                .create_geometry(GeometryKind::TRIANGLE)
                .map_err(|e| fail("cannot create a triangle geometry", e))?;
            mesh.set_new_buffer::<[f32; 3]>(BufferUsage::VERTEX, 0, Format::FLOAT3, 12, 3 * n)
                .map_err(|e| fail("vertex buffer", e))?
                .copy_from_slice(triangles.as_flattened());
            let indices: Vec<[u32; 3]> = (0..n as u32)
                .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
                .collect();
            mesh.set_new_buffer::<[u32; 3]>(BufferUsage::INDEX, 0, Format::UINT3, 12, n)
                .map_err(|e| fail("index buffer", e))?
                .copy_from_slice(&indices);
            let mesh = mesh.commit();
            triangle_geometry = Some(scene.attach_geometry(&mesh));
        }

        let mut sphere_geometry = None;
        if !spheres.is_empty() {
            let mut points = device
                .create_geometry(GeometryKind::SPHERE_POINT)
                .map_err(|e| fail("cannot create a sphere geometry", e))?;
            let data: Vec<[f32; 4]> = spheres
                .iter()
                .map(|s| {
                    let c = s.center.as_vec3();
                    [c.x, c.y, c.z, s.radius as f32]
                })
                .collect();
            points
                .set_new_buffer::<[f32; 4]>(BufferUsage::VERTEX, 0, Format::FLOAT4, 16, data.len())
                .map_err(|e| fail("sphere buffer", e))?
                .copy_from_slice(&data);
            let points = points.commit();
            sphere_geometry = Some(scene.attach_geometry(&points));
        }
        scene.commit();
        if device.get_error() != embree3::sys::RTCError::NONE {
            return Err(EmbreeError(format!(
                "commit failed: {:?}",
                device.get_error()
            )));
        }

        let counts = SceneCounts {
            triangles: triangles.len(),
            spheres: spheres.len(),
            planes: planes.len(),
            accel_bytes: 0,
        };
        Ok(EmbreeScene {
            scene,
            _device: device,
            triangle_geometry,
            sphere_geometry,
            // Kept for the normals of hits.
            triangles: triangles.clone(),
            spheres: spheres.clone(),
            planes: planes.clone(),
            counts,
        })
    }

    /// Our hit for Embree's answer to a query.
    fn hit_of(&self, query: &RayHit) -> Option<Hit> {
        let hit = query.hit;
        if hit.geomID == INVALID {
            return None;
        }
        let primitive = if Some(hit.geomID) == self.sphere_geometry {
            Primitive::Sphere(hit.primID)
        } else {
            Primitive::Triangle {
                slot: hit.primID,
                b1: hit.u,
                b2: hit.v,
            }
        };
        Some(Hit {
            t: f64::from(query.ray.tfar),
            primitive,
        })
    }

    /// Embree's ray for `(tmin, tmax)`: float32, bounds one step inside the interval, and
    /// the near bound no smaller than the least normal float: Embree's threads read
    /// subnormals as zero, and its test is inclusive, so `next_up(0)` let a ray starting
    /// on a triangle hit it at `t = 0`. Embree may not take it (see [`takes`]).
    #[inline(always)]
    fn embree_ray(ray: &Ray, tmax: f64) -> embree3::Ray {
        let tnear = f32_at_most(ray.tmin).next_up();
        let tfar = f32_at_least(tmax).next_down();
        embree3::Ray::segment(
            ray.origin.as_vec3().to_array(),
            ray.direction.as_vec3().to_array(),
            // Not `max`, which would drop a NaN that `takes` must see.
            if tnear < f32::MIN_POSITIVE {
                f32::MIN_POSITIVE
            } else {
                tnear
            },
            tfar,
        )
    }

    /// A ray a stream skips in place of one Embree does not take: `tfar < tnear` marks it
    /// inactive, and its `tfar` is not the −∞ that marks an occluded ray.
    fn skipped_ray() -> embree3::Ray {
        embree3::Ray::segment([0.0; 3], [0.0, 0.0, 1.0], 0.0, -1.0)
    }

    fn closest<const CHECKED: bool>(&self, ray: &Ray) -> Option<Hit> {
        let plane = nearest_plane(&self.planes, ray);
        if self.triangle_geometry.is_none() && self.sphere_geometry.is_none() {
            return plane;
        }
        let tmax = plane.map_or(ray.tmax, |h| h.t);
        let embree_ray = Self::embree_ray(ray, tmax);
        if CHECKED && !takes(&embree_ray) {
            return plane;
        }
        let mut query = RayHit::from_ray(embree_ray);
        self.scene
            .intersect(&mut IntersectContext::incoherent(), &mut query);
        self.hit_of(&query).or(plane)
    }

    /// Embree's coherent stream API (`rtcIntersect1M`) over all the rays at once.
    fn closest_stream<const CHECKED: bool>(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        nearest_planes(&self.planes, rays, out);
        if self.triangle_geometry.is_none() && self.sphere_geometry.is_none() {
            return;
        }
        let mut stream: Vec<RayHit> = rays
            .iter()
            .zip(out.iter())
            .map(|(ray, plane)| {
                let tmax = plane.map_or(ray.tmax, |h| h.t);
                RayHit::from_ray(Self::embree_ray(ray, tmax))
            })
            .collect();
        // Checked in a pass of its own: in the loop above, the check made the checked
        // streams 9% slower (ogre, `raybatch bench --embree --only ogre --threads 1`).
        if CHECKED {
            for query in stream.iter_mut().filter(|q| !takes(&q.ray)) {
                query.ray = Self::skipped_ray();
            }
        }
        self.scene
            .intersect_stream_aos(&mut IntersectContext::coherent(), &mut stream);
        for (query, out) in stream.iter().zip(out.iter_mut()) {
            if let Some(hit) = self.hit_of(query) {
                *out = Some(hit);
            }
        }
    }

    fn any<const CHECKED: bool>(&self, ray: &Ray) -> bool {
        if crate::plane::any_plane(&self.planes, ray) {
            return true;
        }
        if self.triangle_geometry.is_none() && self.sphere_geometry.is_none() {
            return false;
        }
        let mut query = Self::embree_ray(ray, ray.tmax);
        if CHECKED && !takes(&query) {
            return false;
        }
        self.scene
            .occluded(&mut IntersectContext::incoherent(), &mut query)
    }

    /// Embree's coherent stream API (`rtcOccluded1M`) over all the rays at once.
    fn any_stream<const CHECKED: bool>(&self, rays: &[Ray], out: &mut [bool]) {
        crate::plane::any_planes(&self.planes, rays, out);
        if self.triangle_geometry.is_none() && self.sphere_geometry.is_none() {
            return;
        }
        let mut stream: Vec<embree3::Ray> = rays
            .iter()
            .map(|ray| Self::embree_ray(ray, ray.tmax))
            .collect();
        if CHECKED {
            for ray in stream.iter_mut().filter(|r| !takes(r)) {
                *ray = Self::skipped_ray();
            }
        }
        self.scene
            .occluded_stream_aos(&mut IntersectContext::coherent(), &mut stream);
        for (ray, out) in stream.iter().zip(out.iter_mut()) {
            // Embree marks an occluded ray by setting its tfar to −∞.
            *out |= ray.tfar == f32::NEG_INFINITY;
        }
    }
}

/// The largest origin or direction component Embree takes (its `FLT_LARGE`).
const EMBREE_LARGEST: f32 = 1.844e18;

/// Whether Embree takes `r`: its own test (`RayK::valid`), without a branch per value. It
/// asserts, aborting the process, on any other ray: one with a NaN bound, or an origin or
/// direction component beyond [`EMBREE_LARGEST`]. With `CHECKED` the queries below give
/// such a ray (a NaN direction, say, from a lens focused closer than its origin's
/// precision) no hit without reaching Embree, as our tracer gives it none.
#[inline(always)]
fn takes(r: &embree3::Ray) -> bool {
    let within = |x: f32| x.abs() <= EMBREE_LARGEST;
    within(r.org_x)
        & within(r.org_y)
        & within(r.org_z)
        & within(r.dir_x)
        & within(r.dir_y)
        & within(r.dir_z)
        & !r.tnear.is_nan()
        & !r.tfar.is_nan()
}

impl Tracer for EmbreeScene {
    fn closest_hit(&self, ray: &Ray) -> Option<Hit> {
        self.closest::<true>(ray)
    }

    fn closest_hits(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        self.closest_stream::<true>(rays, out);
    }

    fn any_hits(&self, rays: &[Ray], out: &mut [bool]) {
        self.any_stream::<true>(rays, out);
    }

    fn any_hit(&self, ray: &Ray) -> bool {
        self.any::<true>(ray)
    }

    fn normal(&self, ray: &Ray, hit: &Hit) -> DVec3 {
        match hit.primitive {
            Primitive::Plane(i) => self.planes[i as usize].normal,
            Primitive::Sphere(i) => self.spheres[i as usize].normal(ray.at(hit.t)),
            Primitive::Triangle { slot, .. } => {
                let [v0, v1, v2] = self.triangles[slot as usize];
                triangle::geometric_normal(v0, v1, v2)
            }
        }
    }

    fn triangle_id(&self, slot: u32) -> u32 {
        slot
    }

    fn counts(&self) -> SceneCounts {
        self.counts
    }
}

/// The Embree queries of an [`EmbreeScene`] without its check of each ray, as a program
/// calling Embree directly makes them: for rays known to be finite and in range, such as
/// `raybatch bench`'s camera rays, so that its Embree figures are Embree's own. Embree
/// aborts the process on any other ray.
pub struct Unchecked<'a>(pub &'a EmbreeScene);

impl Tracer for Unchecked<'_> {
    fn closest_hit(&self, ray: &Ray) -> Option<Hit> {
        self.0.closest::<false>(ray)
    }

    fn closest_hits(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        self.0.closest_stream::<false>(rays, out);
    }

    fn any_hits(&self, rays: &[Ray], out: &mut [bool]) {
        self.0.any_stream::<false>(rays, out);
    }

    fn any_hit(&self, ray: &Ray) -> bool {
        self.0.any::<false>(ray)
    }

    fn normal(&self, ray: &Ray, hit: &Hit) -> DVec3 {
        self.0.normal(ray, hit)
    }

    fn triangle_id(&self, slot: u32) -> u32 {
        self.0.triangle_id(slot)
    }

    fn counts(&self) -> SceneCounts {
        self.0.counts()
    }
}
