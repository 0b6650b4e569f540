//! The built scene: geometry in world space with its acceleration structures, ready for
//! rays. Built from a checked [`Manifest`] in two steps so each can be timed:
//! [`SceneGeometry::load`] reads meshes and places them, [`Scene::build`] builds the trees.
//!
//! Spheres and planes are intersected in float64, triangles in float32 (as mesh data is):
//! a float64 camera ray is rounded once for the triangles, with `tmin` rounded down and
//! `tmax` rounded up so the strict interval test is exactly the float64 one.

use std::sync::Arc;

use glam::{DMat4, DVec3, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use rayon::prelude::*;

use crate::bvh::{self, Bounds, BoxRay, BuildPreset, Bvh};
use crate::collapse::LeafCost;
use crate::error::{Error, MeshError};
use crate::hint::AnyHitHint;
use crate::manifest::{MAX_MAGNITUDE, Manifest};
use crate::mesh::{MeshCache, MeshFile};
use crate::offset::{self, SurfacePoint};
use crate::plane::Plane;
use crate::ray::Ray;
use crate::sphere::Sphere;
use crate::triangle::{self, BLOCK, Nearest, ShearedRay, TriangleBlock, TriangleHit};

/// Most triangles one leaf holds (four blocks): the collapse's costs
/// ([`LeafCost::TRIANGLE_BLOCKS`]) choose each leaf's size below it.
const TRIANGLES_PER_LEAF: u32 = 16;
/// Most spheres one leaf holds.
const SPHERES_PER_LEAF: u32 = 4;

/// World-space geometry before acceleration structures are built.
#[derive(Debug, Clone, Default)]
pub struct SceneGeometry {
    /// Every mesh triangle, vertices in stored order.
    pub triangles: Vec<[[f32; 3]; 3]>,
    pub spheres: Vec<Sphere>,
    pub planes: Vec<Plane>,
    /// Skipped content worth telling the user about.
    pub warnings: Vec<String>,
    /// Where `triangles` came from: each mesh file as read (shared through the batch's
    /// [`MeshCache`]) and the manifest transform it was placed with, in manifest order.
    /// Equal sources (same files, same transforms) mean equal triangles.
    pub sources: Vec<MeshPlacement>,
}

/// A mesh file as read (shared through a [`MeshCache`]) and the transform that placed it.
pub type MeshPlacement = (Arc<MeshFile>, DMat4);

impl SceneGeometry {
    /// Whether `self` and `other` were placed from the same mesh files, read once, with
    /// the same transforms, so their triangles are the same.
    pub fn same_triangles_as(&self, other: &[MeshPlacement]) -> bool {
        self.sources.len() == other.len()
            && self
                .sources
                .iter()
                .zip(other)
                .all(|((a, m), (b, n))| Arc::ptr_eq(a, b) && m == n)
    }
}

impl SceneGeometry {
    /// Reads the manifest's meshes (through `cache`) and places every primitive.
    pub fn load(manifest: &Manifest, cache: &mut MeshCache) -> Result<SceneGeometry, Error> {
        let mut geometry = SceneGeometry::load_unplaced(manifest, cache)?;
        geometry.place_triangles(manifest)?;
        Ok(geometry)
    }

    /// [`SceneGeometry::load`] without placing the meshes' triangles: `triangles` stays
    /// empty and `sources` says what they would be. For a job whose triangles are those
    /// of a tree already built ([`Scene::build_around`]); [`SceneGeometry::place_triangles`]
    /// places them.
    pub fn load_unplaced(
        manifest: &Manifest,
        cache: &mut MeshCache,
    ) -> Result<SceneGeometry, Error> {
        let mut geometry = SceneGeometry {
            spheres: manifest
                .spheres
                .iter()
                .map(|s| Sphere {
                    center: s.center,
                    radius: s.radius,
                })
                .collect(),
            planes: manifest
                .planes
                .iter()
                .map(|p| Plane {
                    point: p.point,
                    normal: p.normal,
                })
                .collect(),
            ..SceneGeometry::default()
        };
        for (i, desc) in manifest.meshes.iter().enumerate() {
            let mesh = cache.load(&desc.file).map_err(|source| Error::Mesh {
                key: format!("meshes[{i}].file"),
                source,
            })?;
            geometry.warnings.extend(mesh.warnings.iter().cloned());
            geometry.sources.push((mesh, desc.transform));
        }
        Ok(geometry)
    }

    /// Places the triangles of every source, in order, after those already placed;
    /// `manifest` is the one the sources were loaded from (errors name its files).
    ///
    /// # Panics
    /// If `manifest` has another number of meshes than there are sources.
    pub fn place_triangles(&mut self, manifest: &Manifest) -> Result<(), Error> {
        assert_eq!(
            manifest.meshes.len(),
            self.sources.len(),
            "the manifest the sources were loaded from"
        );
        let sources = std::mem::take(&mut self.sources);
        let placed = sources
            .iter()
            .zip(&manifest.meshes)
            .enumerate()
            .try_for_each(|(i, ((mesh, transform), desc))| {
                self.add_mesh(mesh, *transform, &desc.file)
                    .map_err(|source| Error::Mesh {
                        key: format!("meshes[{i}].file"),
                        source,
                    })
            });
        self.sources = sources;
        placed
    }

    /// Triangles of the geometry, placed or not: those placed, or when none are, those its
    /// sources hold ([`SceneGeometry::load_unplaced`]).
    pub fn triangle_count(&self) -> usize {
        if self.triangles.is_empty() {
            self.sources
                .iter()
                .map(|(mesh, _)| mesh.triangle_count())
                .sum()
        } else {
            self.triangles.len()
        }
    }

    /// Places every instance of `mesh` with `transform` applied after the file's own.
    pub fn add_mesh(
        &mut self,
        mesh: &Arc<MeshFile>,
        transform: DMat4,
        file: &std::path::Path,
    ) -> Result<(), MeshError> {
        self.triangles.reserve(mesh.triangle_count());
        for instance in &mesh.instances {
            let geometry = &mesh.geometries[instance.geometry];
            let m = transform * instance.transform;
            let place = |p: &[f32; 3]| m.transform_point3(DVec3::from_array(p.map(f64::from)));
            let in_range = |q: DVec3| q.is_finite() && q.abs().max_element() <= MAX_MAGNITUDE;
            let to_world = |p: &[f32; 3]| {
                let q = place(p);
                in_range(q).then(|| q.as_vec3().to_array())
            };
            // In parallel for large meshes; a vertex out of range is then looked for again
            // in order, to name the first.
            let world: Option<Vec<[f32; 3]>> = if geometry.positions.len() < PARALLEL_PLACING {
                geometry.positions.iter().map(to_world).collect()
            } else {
                geometry.positions.par_iter().map(to_world).collect()
            };
            let Some(world) = world else {
                let (p, q) = geometry
                    .positions
                    .iter()
                    .map(|p| (p, place(p)))
                    .find(|&(_, q)| !in_range(q))
                    .expect("a vertex out of range");
                return Err(MeshError::Range {
                    path: file.to_path_buf(),
                    message: format!(
                        "vertex {} lands at {} after the transforms, out of range (magnitudes up to {MAX_MAGNITUDE:e})",
                        crate::error::shown_point(*p),
                        crate::error::shown_point(q.to_array())
                    ),
                });
            };
            let corners = |t: &[u32; 3]| t.map(|i| world[i as usize]);
            if geometry.triangles.len() < PARALLEL_PLACING {
                self.triangles
                    .extend(geometry.triangles.iter().map(corners));
            } else {
                self.triangles
                    .par_extend(geometry.triangles.par_iter().map(corners));
            }
        }
        Ok(())
    }
}

/// Vertices or triangles of one mesh instance from which [`SceneGeometry::add_mesh`]
/// places them in parallel. Handing work to the pool and waiting for it costs each call a
/// wake-up of a worker; a glTF file of many small instances (the 67 of the engine of
/// `assimp-testmodels`) paid it twice per instance.
const PARALLEL_PLACING: usize = 1 << 14;

/// What a ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the ray's unit direction.
    pub t: f64,
    pub primitive: Primitive,
}

/// The primitive of a [`Hit`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Primitive {
    /// Index into the manifest's `planes`.
    Plane(u32),
    /// Index into the manifest's `spheres`.
    Sphere(u32),
    /// A triangle: where the tracer that found it stores it (see [`Tracer::triangle_id`]
    /// for its index in [`SceneGeometry::triangles`]), and the barycentric weights of its
    /// second and third vertices.
    Triangle { slot: u32, b1: f32, b2: f32 },
}

/// Answers ray queries against a built scene: raybatch's own [`Scene`], or (with the
/// `embree` feature) the Embree reference. Integrators and the render loop are generic
/// over it, so the choice is made once per job, not per ray.
pub trait Tracer: Sync {
    /// The closest hit with `ray.tmin < t < ray.tmax` over all primitives, if any.
    fn closest_hit(&self, ray: &Ray) -> Option<Hit>;

    /// Whether anything is hit with `ray.tmin < t < ray.tmax`.
    fn any_hit(&self, ray: &Ray) -> bool;

    /// [`Tracer::any_hit`] with a hint carried from the caller's previous query (see
    /// [`crate::hint`]), which a tracer may use to find a hit sooner; the answer is the
    /// same. Embree's tracer ignores it.
    fn any_hit_hinted(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        let _ = hint;
        self.any_hit(ray)
    }

    /// [`Tracer::closest_hit`] of every ray: `out[i]` for `rays[i]`. Tracers may trace
    /// coherent runs of rays (neighbouring camera rays) together; results are the same.
    fn closest_hits(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        for (ray, out) in rays.iter().zip(out) {
            *out = self.closest_hit(ray);
        }
    }

    /// [`Tracer::any_hit`] of every ray: `out[i]` for `rays[i]`.
    fn any_hits(&self, rays: &[Ray], out: &mut [bool]) {
        for (ray, out) in rays.iter().zip(out) {
            *out = self.any_hit(ray);
        }
    }

    /// The unit geometric normal at a hit this tracer returned, not flipped toward the
    /// ray: a sphere's `(p − c)/r`, a plane's normal, a triangle's
    /// `normalize(cross(v1 − v0, v2 − v0))`.
    fn normal(&self, ray: &Ray, hit: &Hit) -> DVec3;

    /// [`Tracer::normal`] of every hit: `found(i, normal)` for `hits[i]`, a hit of
    /// `rays[i]`, in no set order; nothing for a `None`. Tracers may compute several at
    /// once; the bits are the same.
    fn normals(&self, rays: &[Ray], hits: &[Option<Hit>], found: impl FnMut(usize, DVec3)) {
        normals_one_by_one(self, rays, hits, found);
    }

    /// The index in [`SceneGeometry::triangles`] of the triangle stored at `slot`.
    fn triangle_id(&self, slot: u32) -> u32;

    /// Primitive counts and memory of what was built.
    fn counts(&self) -> SceneCounts;

    /// Everything this tracer can report a hit on, or `None` when it does not say. The
    /// render loop traces no ray of a tile whose rays all miss it
    /// ([`crate::render::View::tile_misses`]).
    fn extent(&self) -> Option<&Extent> {
        None
    }
}

/// [`Tracer::normals`] by [`Tracer::normal`], one hit at a time.
pub fn normals_one_by_one<T: Tracer + ?Sized>(
    tracer: &T,
    rays: &[Ray],
    hits: &[Option<Hit>],
    mut found: impl FnMut(usize, DVec3),
) {
    for (i, (ray, hit)) in rays.iter().zip(hits).enumerate() {
        if let Some(hit) = hit {
            found(i, tracer.normal(ray, hit));
        }
    }
}

/// Everything a tracer's rays can hit ([`Tracer::extent`]): a box (`[min, max]`) holding
/// every bounded primitive, empty (`min > max`) when there is none, and the planes.
#[derive(Debug, Clone, PartialEq)]
pub struct Extent {
    pub bounds: [DVec3; 2],
    pub planes: Vec<Plane>,
}

/// Sizes of what was built.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SceneCounts {
    pub triangles: usize,
    pub spheres: usize,
    pub planes: usize,
    /// Bytes of triangle blocks, sphere data and tree nodes.
    pub accel_bytes: usize,
}

/// A scene ready for rays.
#[derive(Debug)]
pub struct Scene {
    planes: Vec<Plane>,
    /// Spheres in the tree's leaf order, with their manifest indices.
    spheres: Vec<Sphere>,
    sphere_ids: Vec<u32>,
    /// Spheres in manifest order, for looking up a hit.
    spheres_by_id: Vec<Sphere>,
    sphere_bvh: Bvh<f64>,
    /// Shared, so that jobs of a batch with the same triangles build them once.
    triangles: Arc<TriangleTree>,
    /// Whether the triangle tree is traversed by the AVX2 kernels ([`crate::simd`]).
    simd: bool,
    /// Whether the AVX2 kernels are used at all (the spheres' tree needs no more).
    avx2: bool,
    /// Whether coherent rays meet the spheres as packets: AVX2, and the stack fits.
    sphere_packets: bool,
    /// Whether triangle packets test leaves sixteen rays at a time (AVX-512) rather than
    /// eight ([`crate::packet::LeafLanes`]).
    wide_leaves: bool,
    /// How the batch queries trace groups of coherent rays.
    grouping: Grouping,
    counts: SceneCounts,
    /// [`Tracer::extent`]: the triangles' and spheres' trees' boxes, and the planes.
    extent: Extent,
}

impl Scene {
    /// Builds the trees with the default preset. The scene keeps copies of what it needs;
    /// `geometry` may be dropped (or built again) afterwards.
    pub fn build(geometry: &SceneGeometry) -> Scene {
        Scene::build_with(geometry, BuildPreset::default())
    }

    /// Builds the trees with the given preset.
    pub fn build_with(geometry: &SceneGeometry, preset: BuildPreset) -> Scene {
        let triangles = Arc::new(TriangleTree::build(&geometry.triangles, preset));
        Scene::build_around(geometry, preset, triangles)
    }

    /// Builds the scene as for about `rays` rays: the triangle tree with
    /// [`BuildPreset::for_triangles`] (more build effort when the rays are many per
    /// triangle), the spheres' tree with the default preset (reinsertion did not speed up
    /// a sphere field's tracing; DEVELOPERS.md, "Build"). How a job builds, and the bench.
    pub fn build_for_rays(geometry: &SceneGeometry, rays: u64) -> Scene {
        let preset = BuildPreset::for_triangles(geometry.triangles.len(), rays);
        let triangles = Arc::new(TriangleTree::build(&geometry.triangles, preset));
        Scene::build_around(geometry, BuildPreset::default(), triangles)
    }

    /// Builds the scene around a triangle tree already built from `geometry`'s triangles
    /// (by [`TriangleTree::build`], perhaps for an earlier job); only the spheres' tree is
    /// built. The triangles may be left unplaced ([`SceneGeometry::load_unplaced`]).
    ///
    /// # Panics
    /// If the tree holds a different number of triangles than `geometry`.
    pub fn build_around(
        geometry: &SceneGeometry,
        preset: BuildPreset,
        triangles: Arc<TriangleTree>,
    ) -> Scene {
        let SceneGeometry {
            spheres, planes, ..
        } = geometry;
        assert_eq!(
            triangles.len,
            geometry.triangle_count(),
            "another scene's tree"
        );
        let (sphere_order, sphere_ids, sphere_bvh) = build_spheres(spheres, preset);

        let counts = SceneCounts {
            triangles: triangles.len,
            spheres: spheres.len(),
            planes: planes.len(),
            accel_bytes: triangles.memory_bytes()
                + sphere_order.len() * (std::mem::size_of::<Sphere>() + 4)
                + sphere_bvh.memory_bytes(),
        };
        // Both trees' boxes hold their primitives (the spheres' rounded outward).
        let triangle_box = triangles.bvh.bounds();
        let boxes = sphere_bvh.bounds().union(&Bounds {
            min: triangle_box.min.map(f64::from),
            max: triangle_box.max.map(f64::from),
        });
        let extent = Extent {
            bounds: [boxes.min, boxes.max].map(DVec3::from_array),
            planes: planes.clone(),
        };
        Scene {
            extent,
            planes: planes.clone(),
            spheres: sphere_order,
            sphere_ids,
            spheres_by_id: spheres.clone(),
            simd: simd_available() && triangles.fits_simd_stack(),
            sphere_packets: simd_available() && sphere_bvh.stack_bound() <= SIMD_STACK,
            grouping: Grouping::default(),
            avx2: simd_available(),
            wide_leaves: wide_leaves_available(),
            sphere_bvh,
            triangles,
            counts,
        }
    }

    /// The triangles' tree and blocks, to share with a later scene of the same triangles.
    pub fn triangle_tree(&self) -> &Arc<TriangleTree> {
        &self.triangles
    }

    /// The spheres' tree (for inspection and tests).
    pub fn sphere_bvh(&self) -> &Bvh<f64> {
        &self.sphere_bvh
    }

    /// The spheres in the order of their tree's leaves (for inspection and tests).
    pub fn spheres_in_tree_order(&self) -> &[Sphere] {
        &self.spheres
    }

    /// The triangle tree (for inspection and tests).
    pub fn triangle_bvh(&self) -> &Bvh<f32> {
        &self.triangles.bvh
    }

    /// Whether rays meet the triangles through the AVX2 kernels.
    pub fn uses_simd(&self) -> bool {
        self.simd
    }

    /// Turns the AVX2 kernels off (or back on where the CPU has them), to compare the two
    /// paths; both give bit-identical results.
    pub fn set_simd(&mut self, on: bool) {
        self.avx2 = on && simd_available();
        self.simd = self.avx2 && self.triangles.fits_simd_stack();
        self.sphere_packets = self.avx2 && self.sphere_bvh.stack_bound() <= SIMD_STACK;
        self.wide_leaves = self.avx2 && wide_leaves_available();
    }

    /// Whether triangle packets test leaves sixteen rays at a time (AVX-512).
    pub fn uses_wide_leaves(&self) -> bool {
        self.wide_leaves
    }

    /// Has triangle packets test leaves sixteen rays at a time (where the CPU has AVX-512)
    /// or eight, to compare the two; both give bit-identical results.
    pub fn set_wide_leaves(&mut self, on: bool) {
        self.wide_leaves = on && self.avx2 && wide_leaves_available();
    }

    /// The leaf tests of triangle packets.
    #[cfg(target_arch = "x86_64")]
    fn leaf_lanes(&self) -> LeafLanes {
        if self.wide_leaves {
            LeafLanes::Sixteen
        } else {
            LeafLanes::Eight
        }
    }

    /// Whether coherent rays meet the spheres as packets ([`crate::sphere_packet`]).
    pub fn uses_sphere_packets(&self) -> bool {
        self.sphere_packets
    }

    /// How the batch queries trace groups of coherent rays ([`Grouping::Paced`] unless
    /// set; the others are for tests and benches). The hits are the same either way.
    pub fn set_grouping(&mut self, grouping: Grouping) {
        self.grouping = grouping;
    }

    /// Traces a group of rays as a packet through `tree` when `enabled` (the CPU and tree
    /// allow it) and the pacing does not hold packets back: `trace` runs the packet and
    /// returns what it visited, or `None` when the rays cannot be one. Says how the caller
    /// is to trace the group if it was not traced, or gave up
    /// ([`crate::packet::Visits::hopeless`]).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn traced_as_packet(
        &self,
        tree: PacedTree,
        enabled: bool,
        trace: impl FnOnce() -> Option<crate::packet::Visits>,
    ) -> GroupTrace {
        if !enabled {
            return GroupTrace::OneByOne;
        }
        match self.grouping {
            Grouping::Packets => {}
            Grouping::Paced if crate::packet::worth_trying(tree) => {}
            Grouping::Paced if !crate::packet::scattered(tree) => return GroupTrace::OneByOne,
            Grouping::Paced | Grouping::SideBySide => return GroupTrace::SideBySide,
        }
        let Some(visits) = trace() else {
            return GroupTrace::OneByOne;
        };
        crate::packet::record(tree, visits);
        match visits.hopeless() {
            false => GroupTrace::Packet,
            // As the spell the packet has just begun will trace the next groups.
            true if visits.scattered() => GroupTrace::SideBySide,
            true => GroupTrace::OneByOne,
        }
    }

    /// The closest hit with `ray.tmin < t < ray.tmax` over all primitives.
    #[inline]
    pub fn closest_hit(&self, ray: &Ray) -> Option<Hit> {
        // Skipped, not run empty, when there are no planes or spheres: its `None` would
        // go through memory and stall the triangle search that reads it back.
        let mut best = if self.has_analytic() {
            self.closest_analytic(ray)
        } else {
            None
        };
        if !self.triangles.bvh.is_empty()
            && let Some((nearest, hit)) = self.nearest_triangle(ray, best.map_or(ray.tmax, |h| h.t))
        {
            self.found_triangle(ray, &mut best, nearest, hit);
        }
        best
    }

    /// The float64 distance along `ray` to the plane of the triangle at `slot`
    /// ([`triangle::plane_distance`]), for a hit on a thin triangle
    /// ([`triangle::THIN_ASPECT`]) that the float32 test put `t` away, looking below
    /// `tmax`. The float32 distance is a sum of edge functions over their sum, whose
    /// rounding grows as the triangle thins: on a fan of 200,000 slivers it was off by up
    /// to 2·10⁻⁴. Where the plane's distance falls outside `(ray.tmin, tmax)` (a hit within
    /// rounding of either end), `t`, which the search held inside, is kept. Out of line, so
    /// that the batch queries' callbacks for each hit stay small enough to inline.
    #[cold]
    #[inline(never)]
    fn plane_distance(&self, ray: &Ray, tmax: f64, slot: u32, t: f64) -> f64 {
        let (block, lane) = self.slot(slot);
        let vertices = [0, 1, 2].map(|k| block.vertex(lane, k));
        let plane = triangle::plane_distance(vertices, ray.origin, ray.direction);
        if plane > ray.tmin && plane < tmax {
            plane
        } else {
            t
        }
    }

    /// A triangle hit as the search found it, at the float32 test's distance.
    fn triangle_hit(nearest: Nearest, hit: TriangleHit) -> Hit {
        Hit {
            t: f64::from(nearest.t),
            primitive: Primitive::Triangle {
                slot: nearest.slot,
                b1: hit.b1,
                b2: hit.b2,
            },
        }
    }

    /// Whether the scene has planes or spheres (the analytic searches have work to do).
    #[inline(always)]
    fn has_analytic(&self) -> bool {
        !self.planes.is_empty() || !self.sphere_bvh.is_empty()
    }

    /// The closest plane or sphere hit.
    #[inline(always)]
    fn closest_analytic(&self, ray: &Ray) -> Option<Hit> {
        let plane = nearest_plane(&self.planes, ray);
        self.closest_sphere(ray, plane.map_or(ray.tmax, |h| h.t))
            .or(plane)
    }

    /// Whether the scene's spheres are few enough for a single ray to test in turn,
    /// without their tree: no more than a leaf holds. The tree's set-up and box test cost
    /// a single ray more than so few spheres' own tests (the canonical scene's one sphere
    /// was traced twice as fast without them); batches keep their packets, whose box test
    /// turns most rays away before any sphere's division (DEVELOPERS.md, "A single ray
    /// tests a few spheres in turn").
    #[inline(always)]
    fn has_few_spheres(&self) -> bool {
        self.spheres.len() <= SPHERES_PER_LEAF as usize
    }

    /// The closest sphere hit with `ray.tmin < t < tmax`: few spheres tested in turn
    /// ([`Scene::has_few_spheres`]), more searched in their tree.
    #[inline(always)]
    fn closest_sphere(&self, ray: &Ray, mut tmax: f64) -> Option<Hit> {
        if self.spheres.is_empty() || !finite(ray) {
            return None;
        }
        let mut best = None;
        if self.has_few_spheres() {
            let all = self.spheres.len() as u32;
            self.nearest_sphere_of(ray, (0, all), &mut tmax, &mut best);
            return best;
        }
        let box_ray = BoxRay::new(ray.origin.to_array(), ray.direction.to_array(), ray.tmin);
        let leaf = |first, count, tmax: &mut f64| {
            self.nearest_sphere_of(ray, (first, count), tmax, &mut best);
        };
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only when the CPU has it.
            unsafe { crate::simd::wide_closest(&self.sphere_bvh, &box_ray, &mut tmax, leaf) };
            return best;
        }
        self.sphere_bvh.closest(&box_ray, &mut tmax, leaf);
        best
    }

    /// Of the `count` spheres from position `first` of the tree's leaf order, the nearest
    /// hit with `ray.tmin < t < *tmax`, if any, into `best`, `*tmax` lowered to it.
    #[inline(always)]
    fn nearest_sphere_of(
        &self,
        ray: &Ray,
        (first, count): (u32, u32),
        tmax: &mut f64,
        best: &mut Option<Hit>,
    ) {
        let spheres = &self.spheres[first as usize..(first + count) as usize];
        for (position, sphere) in (first..).zip(spheres) {
            if let Some(t) = sphere.intersect(ray, *tmax) {
                *tmax = t;
                *best = Some(self.sphere_hit(t, position));
            }
        }
    }

    /// Of the `count` spheres from position `first` of the tree's leaf order, the first
    /// with a hit `ray.tmin < t < ray.tmax`, if any.
    #[inline(always)]
    fn first_sphere_of(&self, ray: &Ray, (first, count): (u32, u32)) -> Option<u32> {
        let spheres = &self.spheres[first as usize..(first + count) as usize];
        (first..)
            .zip(spheres)
            .find_map(|(position, s)| s.intersect(ray, ray.tmax).is_some().then_some(position))
    }

    /// The hit on the sphere at `position` of the tree's leaf order.
    fn sphere_hit(&self, t: f64, position: u32) -> Hit {
        Hit {
            t,
            primitive: Primitive::Sphere(self.sphere_ids[position as usize]),
        }
    }

    /// The closest sphere hits of up to [`PACKET`] rays, ray `k` looking below `tmax[k]`,
    /// into `out[k]` (left alone where there is none): as a packet where the CPU and the
    /// rays allow, else ray by ray.
    fn closest_spheres(&self, rays: &[Ray], tmax: &[f64], out: &mut [Option<Hit>]) {
        if self.sphere_bvh.is_empty() {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `sphere_packets` is set only when the CPU has AVX2 and the stack fits.
        if self.traced_as_packet(PacedTree::Spheres, self.sphere_packets, || unsafe {
            crate::sphere_packet::closest(
                &self.sphere_bvh,
                &self.spheres,
                rays,
                tmax,
                |k, t, position| out[k] = Some(self.sphere_hit(t, position)),
            )
        }) == GroupTrace::Packet
        {
            return;
        }
        for (k, ray) in rays.iter().enumerate() {
            if let Some(hit) = self.closest_sphere(ray, tmax[k]) {
                out[k] = Some(hit);
            }
        }
    }

    /// [`Scene::closest_hit`] for many rays: `out[i]` receives ray `i`'s hit. Coherent
    /// rays (neighbouring camera rays, in runs of up to [`crate::packet::PACKET`]) are
    /// traced as packets where the CPU allows, which is much faster unless the triangles
    /// are finer than the rays are apart (then they go one by one for a while, on the
    /// evidence of the last packet: [`crate::packet::Visits`]).
    pub fn closest_hits(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        assert_eq!(rays.len(), out.len());
        let analytic = !self.planes.is_empty() || !self.sphere_bvh.is_empty();
        for (rays, out) in rays.chunks(PACKET).zip(out.chunks_mut(PACKET)) {
            if analytic {
                nearest_planes(&self.planes, rays, out);
                let mut tmax = [0f64; PACKET];
                for (k, ray) in rays.iter().enumerate() {
                    tmax[k] = out[k].map_or(ray.tmax, |h| h.t);
                }
                self.closest_spheres(rays, &tmax[..rays.len()], out);
            } else {
                out.fill(None);
            }
            if self.triangles.bvh.is_empty() {
                continue;
            }
            self.closest_triangles(rays, analytic, out);
        }
    }

    /// The closest triangle hits of up to [`PACKET`] rays into `out`, each ray looking
    /// below its hit there if any (`analytic`: the scene has planes or spheres), else below
    /// its `tmax` ([`Scene::found_triangle`]). As a packet, side by side or one by one, as
    /// the pacing decides.
    #[inline(always)]
    fn closest_triangles(&self, rays: &[Ray], analytic: bool, out: &mut [Option<Hit>]) {
        let prepared = if analytic {
            triangle_rays(self.avx2, rays, |k, ray| out[k].map_or(ray.tmax, |h| h.t))
        } else {
            triangle_rays(self.avx2, rays, |_, ray| ray.tmax)
        };
        let prepared = &prepared[..rays.len()];
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `simd` is set only when the CPU has AVX2 and the stack fits,
        // `wide_leaves` only when it has AVX-512F too.
        match self.traced_as_packet(PacedTree::Triangles, self.simd, || unsafe {
            crate::packet::closest(
                self.leaf_lanes(),
                &self.triangles.bvh,
                &self.triangles.blocks,
                prepared,
                |k, nearest, hit| self.found_triangle(&rays[k], &mut out[k], nearest, hit),
            )
        }) {
            GroupTrace::Packet => return,
            GroupTrace::SideBySide => {
                // SAFETY: as above; only AVX2 is held back by the pacing.
                unsafe {
                    crate::interleaved::closest(
                        &self.triangles.bvh,
                        &self.triangles.blocks,
                        prepared,
                        |k, nearest, hit| self.found_triangle(&rays[k], &mut out[k], nearest, hit),
                    )
                };
                return;
            }
            GroupTrace::OneByOne => {}
        }
        for (k, ray) in rays.iter().enumerate() {
            let tmax = out[k].map_or(ray.tmax, |h| h.t);
            if let Some((nearest, hit)) = self.nearest_triangle(ray, tmax) {
                self.found_triangle(ray, &mut out[k], nearest, hit);
            }
        }
    }

    /// Puts the closest triangle hit of `ray` in `out`, whose hit (if any) bounded the
    /// search: at the float32 test's distance, or on a thin triangle at its plane's
    /// ([`Scene::plane_distance`]).
    #[inline(always)]
    fn found_triangle(&self, ray: &Ray, out: &mut Option<Hit>, nearest: Nearest, hit: TriangleHit) {
        let mut t = f64::from(nearest.t);
        if self.triangles.is_thin(nearest.slot) {
            t = self.plane_distance(ray, out.map_or(ray.tmax, |h| h.t), nearest.slot, t);
        }
        *out = Some(Hit {
            t,
            ..Self::triangle_hit(nearest, hit)
        });
    }

    /// Whether [`Scene::closest_hits`] can trace these rays (at most one packet's worth) as
    /// a packet rather than one by one: AVX2, the same direction signs for all, origins
    /// and directions finite in float32 and no NaN `tmin`. (Just after wasteful packets it
    /// still goes one by one, see [`crate::packet::Visits`].)
    pub fn traces_as_packet(&self, rays: &[Ray]) -> bool {
        let signs = |r: &Ray| r.direction.as_vec3().to_array().map(f32::is_sign_negative);
        let usable = |r: &Ray| finite_in_f32(r) && !r.tmin.is_nan();
        self.simd
            && rays.len() <= PACKET
            && rays
                .iter()
                .all(|r| signs(r) == signs(&rays[0]) && usable(r))
    }

    /// [`Scene::any_hit`] for many rays: `out[i]` receives ray `i`'s answer, with coherent
    /// runs traced as packets as in [`Scene::closest_hits`]. Runs traced one by one carry
    /// an [`AnyHitHint`] from ray to ray, which after some packets (shadow rays from
    /// neighbouring points, [`crate::packet::Visits::hints_pay`]) is the faster way.
    pub fn any_hits(&self, rays: &[Ray], out: &mut [bool]) {
        assert_eq!(rays.len(), out.len());
        let analytic = !self.planes.is_empty() || !self.sphere_bvh.is_empty();
        for (rays, out) in rays.chunks(PACKET).zip(out.chunks_mut(PACKET)) {
            let mut hint = AnyHitHint::default();
            if analytic {
                crate::plane::any_planes(&self.planes, rays, out);
                self.any_spheres(rays, out, &mut hint);
            } else {
                out.fill(false);
            }
            if self.triangles.bvh.is_empty() {
                continue;
            }
            #[cfg(target_arch = "x86_64")]
            {
                let mut triangles = [false; PACKET];
                let n = rays.len();
                // A ray already hit needs no triangle: an empty interval.
                let prepared = || {
                    triangle_rays(self.avx2, rays, |k, ray| {
                        if out[k] { f64::NEG_INFINITY } else { ray.tmax }
                    })
                };
                // SAFETY: traced only where `simd` is set.
                match self.traced_as_packet(PacedTree::TrianglesAnyHit, self.simd, || unsafe {
                    self.any_triangle_packet(&prepared()[..n], &mut triangles[..n])
                }) {
                    GroupTrace::Packet => {
                        for (out, hit) in out.iter_mut().zip(triangles) {
                            *out |= hit;
                        }
                        continue;
                    }
                    GroupTrace::SideBySide => {
                        // SAFETY: as above; only AVX2 is held back by the pacing.
                        unsafe {
                            crate::interleaved::any(
                                &self.triangles.bvh,
                                &self.triangles.blocks,
                                &prepared()[..n],
                                out,
                            )
                        };
                        continue;
                    }
                    GroupTrace::OneByOne => {}
                }
            }
            for (ray, out) in rays.iter().zip(out.iter_mut()) {
                *out = *out || self.any_triangle(ray, &mut hint);
            }
        }
    }

    /// What an any-hit packet of `rays` (at most [`PACKET`]) visits in the triangles' tree,
    /// traced as [`Scene::any_hits`] traces one whatever the pacing; `None` where the CPU
    /// or the rays allow no packet.
    #[cfg(all(test, target_arch = "x86_64"))]
    pub(crate) fn any_hit_packet_visits(&self, rays: &[Ray]) -> Option<crate::packet::Visits> {
        if !self.simd {
            return None;
        }
        let n = rays.len();
        let prepared = triangle_rays(self.avx2, rays, |_, ray| ray.tmax);
        // SAFETY: `simd` is set.
        unsafe { self.any_triangle_packet(&prepared[..n], &mut [false; PACKET][..n]) }
    }

    /// [`crate::packet::any`] through the triangles' tree, at the scene's leaf width.
    ///
    /// # Safety
    /// Only where `simd` is set: only when the CPU has AVX2 and the stack fits (and
    /// `wide_leaves` only when it has AVX-512F too).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn any_triangle_packet(
        &self,
        rays: &[TriangleRay],
        out: &mut [bool],
    ) -> Option<crate::packet::Visits> {
        // SAFETY: as required of the caller.
        unsafe {
            crate::packet::any(
                self.leaf_lanes(),
                &self.triangles.bvh,
                &self.triangles.blocks,
                rays,
                out,
            )
        }
    }

    /// The nearest triangle hit with `ray.tmin < t < tmax` of the ray rounded to float32,
    /// through the AVX2 kernels when the scene uses them: both paths give the same
    /// [`Nearest`] (see its tie rule).
    #[inline(always)]
    fn nearest_triangle(&self, ray: &Ray, tmax: f64) -> Option<(Nearest, TriangleHit)> {
        #[cfg(target_arch = "x86_64")]
        if self.simd {
            // SAFETY: `simd` is set only when the CPU has AVX2 and the stack fits.
            return unsafe {
                crate::simd::closest(&self.triangles.bvh, &self.triangles.blocks, ray, tmax)
            };
        }
        let r = TriangleRay::new(ray, tmax);
        let (sheared, boxes) = (r.sheared(), r.boxes());
        let mut nearest = Nearest::before(r.tmax);
        let mut found = None;
        // Boxes up to the horizon past tmax from the start, as in the AVX2 path.
        let mut tmax = nearest.horizon();
        self.triangles
            .bvh
            .closest(&boxes, &mut tmax, |first, count, tmax| {
                for b in first..first + count {
                    if let Some(hit) = self.triangles.blocks[b as usize].intersect(
                        &sheared,
                        r.tmin,
                        b,
                        &mut nearest,
                    ) {
                        found = Some(hit);
                    }
                }
                *tmax = nearest.horizon();
            });
        found.map(|hit| (nearest, hit))
    }

    /// Whether anything is hit with `ray.tmin < t < ray.tmax`; stops at the first hit found.
    #[inline]
    pub fn any_hit(&self, ray: &Ray) -> bool {
        self.any_hit_hinted(ray, &mut AnyHitHint::default())
    }

    /// [`Scene::any_hit`], testing first the triangles near the one that stopped the
    /// previous query made with `hint`, and updating it (see [`crate::hint`]). The answer
    /// is the same with any hint.
    #[inline]
    pub fn any_hit_hinted(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        (self.has_analytic() && self.any_analytic(ray, hint))
            || (!self.triangles.bvh.is_empty() && self.any_triangle(ray, hint))
    }

    /// Whether a plane or a sphere is hit.
    #[inline(always)]
    fn any_analytic(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        crate::plane::any_plane(&self.planes, ray) || self.any_sphere(ray, hint)
    }

    /// Whether a sphere has `ray.tmin < t < ray.tmax`: few spheres tested in turn
    /// ([`Scene::has_few_spheres`]), more searched in their tree.
    #[inline(always)]
    fn any_sphere(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        if !self.has_few_spheres() {
            return self.any_sphere_in_tree(ray, hint);
        }
        let all = self.spheres.len() as u32;
        all > 0 && finite(ray) && self.first_sphere_of(ray, (0, all)).is_some()
    }

    /// [`Scene::any_sphere`] over the spheres' tree, the hint's sphere tested first. Out
    /// of line: inlined, its stack made every query set up a large frame, on scenes
    /// without spheres too.
    #[inline(never)]
    fn any_sphere_in_tree(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        if let Some(i) = hint.sphere()
            && i < self.spheres.len()
            && self.first_sphere_of(ray, (i as u32, 1)).is_some()
        {
            return true;
        }
        if !finite(ray) {
            return false;
        }
        let box_ray = BoxRay::new(ray.origin.to_array(), ray.direction.to_array(), ray.tmin);
        let mut found = None;
        let leaf = |first, count| {
            found = self.first_sphere_of(ray, (first, count));
            found.is_some()
        };
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only when the CPU has it.
            unsafe { crate::simd::wide_any(&self.sphere_bvh, &box_ray, ray.tmax, leaf) };
            hint.remember_sphere(found);
            return found.is_some();
        }
        self.sphere_bvh.any(&box_ray, ray.tmax, leaf);
        hint.remember_sphere(found);
        found.is_some()
    }

    /// [`Scene::any_sphere`] for up to [`PACKET`] rays, into `out[k]` for rays not already
    /// marked hit: as a packet where the CPU and the rays allow, else ray by ray.
    fn any_spheres(&self, rays: &[Ray], out: &mut [bool], hint: &mut AnyHitHint) {
        if self.sphere_bvh.is_empty() {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `sphere_packets` is set only when the CPU has AVX2 and the stack fits.
        if self.traced_as_packet(PacedTree::Spheres, self.sphere_packets, || {
            let mut tmax = [0f64; PACKET];
            for (k, ray) in rays.iter().enumerate() {
                // A ray already hit needs no sphere: an empty interval.
                tmax[k] = if out[k] { f64::NEG_INFINITY } else { ray.tmax };
            }
            // SAFETY: as above.
            unsafe {
                crate::sphere_packet::any(
                    &self.sphere_bvh,
                    &self.spheres,
                    rays,
                    &tmax[..rays.len()],
                    |k, _, _| out[k] = true,
                )
            }
        }) == GroupTrace::Packet
        {
            return;
        }
        for (ray, out) in rays.iter().zip(out.iter_mut()) {
            *out = *out || self.any_sphere(ray, hint);
        }
    }

    /// Whether a triangle has `ray.tmin < t < ray.tmax` for the ray rounded to float32,
    /// the hint's block tested first.
    #[inline(always)]
    fn any_triangle(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        let blocks = &self.triangles.blocks;
        #[cfg(target_arch = "x86_64")]
        if self.simd {
            // SAFETY: `simd` is set only when the CPU has AVX2 and the stack fits.
            return unsafe { crate::simd::any(&self.triangles.bvh, blocks, ray, hint) };
        }
        self.any_triangle_scalar(ray, hint)
    }

    /// [`Scene::any_triangle`] without AVX2. Out of line, as [`Scene::any_sphere_in_tree`].
    #[inline(never)]
    fn any_triangle_scalar(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        let blocks = &self.triangles.blocks;
        let r = TriangleRay::new(ray, ray.tmax);
        let (sheared, boxes) = (r.sheared(), r.boxes());
        // Boxes up to the horizon past tmax, as in the AVX2 path.
        let horizon = Nearest::before(r.tmax).horizon();
        // The slot of a triangle of block `b` that the ray hits, if any.
        let stopped = |b: usize| {
            let mut nearest = Nearest::before(r.tmax);
            blocks[b]
                .intersect(&sheared, r.tmin, b as u32, &mut nearest)
                .map(|_| nearest.slot)
        };
        let search = |start: u32| {
            let mut found = None;
            let subtree =
                self.triangles
                    .bvh
                    .any_below(start, start, &boxes, horizon, |first, count| {
                        found = (first..first + count).find_map(|b| stopped(b as usize));
                        found.is_some()
                    })?;
            Some((found?, subtree))
        };
        // As the AVX2 path: the hint's blocks, the subtrees around them, the whole tree.
        let mut found = None;
        if let [Some(b), above] = hint.blocks()
            && b < blocks.len()
        {
            let [near, above_subtree] = hint.subtrees();
            found = stopped(b).map(|slot| (slot, near)).or_else(|| {
                above
                    .filter(|&a| a < blocks.len())
                    .and_then(stopped)
                    .map(|slot| (slot, above_subtree))
            });
            let subtrees = hint.subtrees_to_search(blocks.len(), self.triangles.bvh.nodes().len());
            for subtree in subtrees.into_iter().flatten() {
                found = found.or_else(|| search(subtree));
            }
        }
        let found = found.or_else(|| search(0));
        hint.remember_triangle(found);
        found.is_some()
    }

    /// The unit geometric normal at a hit, not flipped toward the ray: a sphere's
    /// `(p − c)/r`, a plane's normal, a triangle's `normalize(cross(v1 − v0, v2 − v0))`.
    pub fn normal(&self, ray: &Ray, hit: &Hit) -> DVec3 {
        match hit.primitive {
            Primitive::Plane(i) => self.planes[i as usize].normal,
            Primitive::Sphere(id) => self.spheres_by_id[id as usize].normal(ray.at(hit.t)),
            Primitive::Triangle { slot, .. } => {
                let (b, lane) = self.slot(slot);
                triangle::geometric_normal(b.vertex(lane, 0), b.vertex(lane, 1), b.vertex(lane, 2))
            }
        }
    }

    /// Where `ray` hit, as a point to start secondary rays from (see [`crate::offset`]):
    /// a sphere's point projected back onto the sphere, a plane's onto the plane, a
    /// triangle's from its barycentric weights, each with its error bound.
    pub fn surface_point(&self, ray: &Ray, hit: &Hit) -> SurfacePoint {
        let raw = ray.at(hit.t);
        match hit.primitive {
            Primitive::Plane(i) => {
                let Plane { point, normal } = self.planes[i as usize];
                let p = raw - normal * (raw - point).dot(normal);
                let error = (raw.abs() + point.abs()) * offset::gamma(8, offset::U64);
                SurfacePoint::new(p, error, normal)
            }
            Primitive::Sphere(id) => {
                let Sphere { center, radius } = self.spheres_by_id[id as usize];
                let normal = (raw - center).normalize();
                let on = normal * radius;
                let error = (center.abs() + on.abs() + DVec3::splat(radius))
                    * offset::gamma(6, offset::U64);
                SurfacePoint::new(center + on, error, normal)
            }
            Primitive::Triangle { slot, b1, b2 } => {
                let (block, lane) = self.slot(slot);
                let [v0, v1, v2] =
                    [0, 1, 2].map(|k| DVec3::from_array(block.vertex(lane, k).map(f64::from)));
                let (b1, b2) = (f64::from(b1), f64::from(b2));
                let b0 = 1.0 - b1 - b2;
                let (w0, w1, w2) = (v0 * b0, v1 * b1, v2 * b2);
                // pbrt's bound for the float32 barycentric sum (the weights come from the
                // float32 test), which also covers this float64 one.
                let error = (w0.abs() + w1.abs() + w2.abs()) * offset::gamma(7, offset::U32);
                let normal = triangle::geometric_normal(
                    block.vertex(lane, 0),
                    block.vertex(lane, 1),
                    block.vertex(lane, 2),
                );
                SurfacePoint::on_triangle(w0 + w1 + w2, error, normal)
            }
        }
    }

    /// [`Tracer::normals`]: with AVX2, triangles' normals four at a time
    /// (`triangle::geometric_normals4`), where each one alone waited on its own square
    /// root and division.
    #[inline]
    pub fn normals(&self, rays: &[Ray], hits: &[Option<Hit>], found: impl FnMut(usize, DVec3)) {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only when the CPU has it.
            unsafe { self.normals_avx2(rays, hits, found) };
            return;
        }
        normals_one_by_one(self, rays, hits, found);
    }

    /// [`Scene::normals`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn normals_avx2(
        &self,
        rays: &[Ray],
        hits: &[Option<Hit>],
        mut found: impl FnMut(usize, DVec3),
    ) {
        // Triangle hits waiting to be taken four at a time: their indices and slots.
        let (mut waiting, mut slots) = ([0usize; 4], [0u32; 4]);
        let mut count = 0;
        for (i, (ray, hit)) in rays.iter().zip(hits).enumerate() {
            let Some(hit) = hit else { continue };
            let Primitive::Triangle { slot, .. } = hit.primitive else {
                found(i, self.normal(ray, hit));
                continue;
            };
            (waiting[count], slots[count]) = (i, slot);
            count += 1;
            if count == 4 {
                // SAFETY: AVX2 is enabled here.
                let normals = unsafe { triangle::geometric_normals4(slots.map(|s| self.slot(s))) };
                for (&i, normal) in waiting.iter().zip(normals) {
                    found(i, normal);
                }
                count = 0;
            }
        }
        // The last few, the lanes past them repeating the first.
        if count > 0 {
            let first = slots[0];
            slots[count..].fill(first);
            // SAFETY: AVX2 is enabled here.
            let normals = unsafe { triangle::geometric_normals4(slots.map(|s| self.slot(s))) };
            for (&i, normal) in waiting[..count].iter().zip(normals) {
                found(i, normal);
            }
        }
    }

    fn slot(&self, slot: u32) -> (&TriangleBlock, usize) {
        let block = &self.triangles.blocks[slot as usize / BLOCK];
        (block, slot as usize % BLOCK)
    }
}

impl Tracer for Scene {
    #[inline]
    fn closest_hit(&self, ray: &Ray) -> Option<Hit> {
        Scene::closest_hit(self, ray)
    }

    fn closest_hits(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        Scene::closest_hits(self, rays, out);
    }

    fn any_hits(&self, rays: &[Ray], out: &mut [bool]) {
        Scene::any_hits(self, rays, out);
    }

    #[inline]
    fn any_hit(&self, ray: &Ray) -> bool {
        Scene::any_hit(self, ray)
    }

    #[inline]
    fn any_hit_hinted(&self, ray: &Ray, hint: &mut AnyHitHint) -> bool {
        Scene::any_hit_hinted(self, ray, hint)
    }

    fn normal(&self, ray: &Ray, hit: &Hit) -> DVec3 {
        Scene::normal(self, ray, hit)
    }

    fn normals(&self, rays: &[Ray], hits: &[Option<Hit>], found: impl FnMut(usize, DVec3)) {
        Scene::normals(self, rays, hits, found);
    }

    fn triangle_id(&self, slot: u32) -> u32 {
        let (block, lane) = self.slot(slot);
        block.ids[lane]
    }

    fn counts(&self) -> SceneCounts {
        self.counts
    }

    fn extent(&self) -> Option<&Extent> {
        Some(&self.extent)
    }
}

#[cfg(target_arch = "x86_64")]
use crate::packet::{LeafLanes, PACKET, PacedTree};
#[cfg(target_arch = "x86_64")]
use crate::simd::{STACK as SIMD_STACK, available as simd_available};
#[cfg(target_arch = "x86_64")]
use crate::simd512::available as wide_leaves_available;
#[cfg(not(target_arch = "x86_64"))]
const SIMD_STACK: usize = 0;
#[cfg(not(target_arch = "x86_64"))]
const PACKET: usize = 64;
#[cfg(not(target_arch = "x86_64"))]
fn simd_available() -> bool {
    false
}
#[cfg(not(target_arch = "x86_64"))]
fn wide_leaves_available() -> bool {
    false
}

/// [`nearest_plane`] of each of `rays`, into `out` (several rays at a time).
pub fn nearest_planes(planes: &[Plane], rays: &[Ray], out: &mut [Option<Hit>]) {
    crate::plane::nearest_planes(planes, rays, out, |t, i| plane_hit((t, i)));
}

/// The nearest of `planes` hit with `ray.tmin < t < ray.tmax`, if any.
pub fn nearest_plane(planes: &[Plane], ray: &Ray) -> Option<Hit> {
    crate::plane::nearest_plane(planes, ray).map(plane_hit)
}

/// The hit of plane `i` at `t`.
fn plane_hit((t, i): (f64, u32)) -> Hit {
    Hit {
        t,
        primitive: Primitive::Plane(i),
    }
}

/// A float64 ray rounded for the float32 triangle path: origin and direction to nearest,
/// `tmin` down and `tmax` up. Laid out as eight floats in this order, which packets read
/// with one load ([`crate::packet`]).
#[derive(Debug, Clone, Copy)]
#[repr(C)]
pub struct TriangleRay {
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    pub tmin: f32,
    pub tmax: f32,
}

/// How the batch queries ([`Scene::closest_hits`], [`Scene::any_hits`]) trace groups of
/// coherent rays. The hits are the same in every case; only the speed changes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Grouping {
    /// As packets where the CPU and the rays allow, until packets prove wasteful
    /// ([`crate::packet::Visits`]); then, for a while, one by one, or through the
    /// triangles side by side ([`crate::interleaved`]) where the wasteful packet found
    /// its rays scattered, each in leaves of its own. Any-hit groups also go one by one
    /// for a while after a packet whose rays the hint would have stopped for less
    /// ([`crate::packet::Visits::hints_pay`]).
    #[default]
    Paced,
    /// Every group that can be a packet is one, even after wasteful packets (but for a
    /// packet that gives up, [`crate::packet::Visits::hopeless`]).
    Packets,
    /// No packets: the rays through the triangles side by side, through the spheres one
    /// by one.
    SideBySide,
}

/// How [`Scene::traced_as_packet`] left a group of rays.
#[cfg(target_arch = "x86_64")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum GroupTrace {
    /// Traced as a packet.
    Packet,
    /// Not traced: the pacing holds packets back, and the last wasteful packet found its
    /// rays scattered. The caller traces the rays side by side ([`crate::interleaved`]),
    /// which keeps several waits for memory going at once.
    SideBySide,
    /// Not traced: the CPU, the tree or the rays do not allow a packet, or the pacing
    /// holds packets back over rays that share leaves. The caller traces the rays one by
    /// one, each finding the last one's nodes in the cache.
    OneByOne,
}

/// Whether the ray's origin and direction are finite; others meet no sphere. The sphere
/// tree's box test reads a NaN slab (`0 · ∞`, a ray along a box face) as no constraint,
/// so a ray with a NaN slab on every axis would enter every slot, empty ones too, and
/// their reference back to the root.
#[inline(always)]
fn finite(ray: &Ray) -> bool {
    // All six at once, without a branch each: an exponent of all ones is ±∞ or NaN.
    const EXPONENT: u64 = 0x7ff0_0000_0000_0000;
    let [o, d] = [ray.origin, ray.direction];
    let special = |x: f64| x.to_bits() & EXPONENT == EXPONENT;
    !(special(o.x) | special(o.y) | special(o.z) | special(d.x) | special(d.y) | special(d.z))
}

/// Whether the ray's origin and direction stay finite rounded to float32, as triangles are
/// traced.
fn finite_in_f32(ray: &Ray) -> bool {
    ray.origin.as_vec3().is_finite() && ray.direction.as_vec3().is_finite()
}

/// Up to [`PACKET`] rays rounded for the triangle kernels, ray `k` with the interval
/// `(tmin, tmax(k, ray))` rounded outward. With `avx2` (the CPU has it), compiled for it:
/// the conversions of a ray's coordinates, and the roundings, then go four or eight at a
/// time.
#[inline(always)]
fn triangle_rays(
    avx2: bool,
    rays: &[Ray],
    tmax: impl Fn(usize, &Ray) -> f64,
) -> [TriangleRay; PACKET] {
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn compiled_for_avx2(
        rays: &[Ray],
        tmax: impl Fn(usize, &Ray) -> f64,
    ) -> [TriangleRay; PACKET] {
        rounded_rays(rays, tmax)
    }
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: the caller's `avx2` is set only when the CPU has it.
        return unsafe { compiled_for_avx2(rays, tmax) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = avx2;
    rounded_rays(rays, tmax)
}

/// [`triangle_rays`], for any CPU.
#[inline(always)]
fn rounded_rays(rays: &[Ray], tmax: impl Fn(usize, &Ray) -> f64) -> [TriangleRay; PACKET] {
    let n = rays.len().min(PACKET);
    let (mut lower, mut upper) = ([0f64; PACKET], [0f64; PACKET]);
    for (k, ray) in rays[..n].iter().enumerate() {
        lower[k] = ray.tmin;
        upper[k] = tmax(k, ray);
    }
    // Compared bit for bit: −0 and +0 round to different zeros.
    let shared = (lower[..n].iter().zip(&upper[..n]))
        .all(|(l, u)| (l.to_bits() == lower[0].to_bits()) & (u.to_bits() == upper[0].to_bits()));
    let mut prepared = [TriangleRay::EMPTY; PACKET];
    if shared {
        // Camera rays share their interval: rounded once.
        let interval = (bvh::f32_at_most(lower[0]), bvh::f32_at_least(upper[0]));
        for (k, ray) in rays[..n].iter().enumerate() {
            prepared[k] = TriangleRay::rounded(ray, interval);
        }
        return prepared;
    }
    // In front of walls or behind spheres each ray has its own: all rounded in a loop of
    // their own over the whole packet, which has no branches and which the compiler takes
    // several at a time.
    let (mut lower32, mut upper32) = ([0f32; PACKET], [0f32; PACKET]);
    for k in 0..PACKET {
        lower32[k] = bvh::f32_at_most(lower[k]);
        upper32[k] = bvh::f32_at_least(upper[k]);
    }
    for (k, ray) in rays[..n].iter().enumerate() {
        prepared[k] = TriangleRay::rounded(ray, (lower32[k], upper32[k]));
    }
    prepared
}

impl TriangleRay {
    const EMPTY: TriangleRay = TriangleRay {
        origin: [0.0; 3],
        direction: [0.0, 0.0, 1.0],
        tmin: 0.0,
        tmax: 0.0,
    };

    /// The ray rounded for the scalar searches: with its interval rounded outward to
    /// float32, or empty when its origin or direction is not finite in float32. (Such a
    /// ray hits no triangle, but its slabs are NaN, which the box tests pass over, as they
    /// must for a ray along a box's face: it would enter every slot, the empty ones too,
    /// whose reference leads back to the root, and go round the tree for ever. The AVX2
    /// searches turn it away at the tree's box: [`crate::simd::enters`].)
    #[inline(always)]
    pub(crate) fn new(ray: &Ray, tmax: f64) -> TriangleRay {
        let interval = if finite_in_f32(ray) {
            (bvh::f32_at_most(ray.tmin), bvh::f32_at_least(tmax))
        } else {
            (f32::INFINITY, f32::NEG_INFINITY)
        };
        TriangleRay::rounded(ray, interval)
    }

    /// The ray with its interval `(tmin, tmax)` already rounded outward to float32.
    #[inline(always)]
    pub(crate) fn rounded(ray: &Ray, (tmin, tmax): (f32, f32)) -> TriangleRay {
        TriangleRay {
            origin: ray.origin.as_vec3().to_array(),
            direction: ray.direction.as_vec3().to_array(),
            tmin,
            tmax,
        }
    }

    /// The watertight test's view of the ray.
    #[inline(always)]
    pub fn sheared(&self) -> ShearedRay {
        ShearedRay::new(Vec3::from(self.origin), Vec3::from(self.direction))
    }

    /// The box test's view of the ray.
    #[inline(always)]
    pub fn boxes(&self) -> BoxRay<f32> {
        BoxRay::new(self.origin, self.direction, self.tmin)
    }
}

/// Levels above the leaf of a hinted any-hit query's block where its second search starts
/// (see [`crate::hint`]): the subtree under the parent of the node holding the leaf, around
/// the hint. The any-hit searches name that node for the triangle they find, from what
/// their stack entries carry ([`Bvh::any_below`]), so the level is built into them. On
/// the benchmark's camera rays (`raybatch bench --models ../shared/models --only
/// torus,ogre,bunny,nefertiti --threads 1`, `any 1`), one level is 1–3% faster than two
/// on BENCHMARKS.md's Zen 4 host, now that leaves test two blocks at once, and 1–4% on
/// its Intel host (DEVELOPERS.md, "Not kept: climbing from the hint's subtree"); on its
/// first host, before that, one level had given half the speed-up of two, and three no
/// more than two.
pub const HINT_LEVELS: usize = 1;

/// The triangles of a scene, ready for rays: their tree and the blocks its leaves point
/// into. Built once per set of placed triangles and shared between the scenes (jobs) that
/// have exactly those triangles.
#[derive(Debug)]
pub struct TriangleTree {
    blocks: Vec<TriangleBlock>,
    /// Which triangles are thin ([`triangle::is_thin`]): a bit for each lane of each
    /// block, bit `l` of byte `b` for lane `l` of block `b`. Empty when none is.
    thin: Vec<u8>,
    bvh: Bvh<f32>,
    /// Triangles it was built from.
    len: usize,
    preset: BuildPreset,
}

impl TriangleTree {
    /// Builds the tree of `triangles` (which may be empty) with `preset`.
    pub fn build(triangles: &[[[f32; 3]; 3]], preset: BuildPreset) -> TriangleTree {
        let (blocks, thin, bvh) = build_triangles(triangles, preset);
        TriangleTree {
            blocks,
            thin,
            bvh,
            len: triangles.len(),
            preset,
        }
    }

    /// Whether any of the triangles is thin ([`triangle::is_thin`]).
    #[inline(always)]
    pub fn has_thin(&self) -> bool {
        !self.thin.is_empty()
    }

    /// Whether the triangle at `slot` (`4·block + lane`) is thin ([`triangle::is_thin`]).
    #[inline(always)]
    pub fn is_thin(&self, slot: u32) -> bool {
        let slot = slot as usize;
        (self.thin.get(slot / BLOCK)).is_some_and(|lanes| lanes >> (slot % BLOCK) & 1 != 0)
    }

    /// The preset the tree was built with.
    pub fn preset(&self) -> BuildPreset {
        self.preset
    }

    /// Whether the AVX2 kernels' fixed stack holds any traversal of this tree.
    fn fits_simd_stack(&self) -> bool {
        self.bvh.stack_bound() <= SIMD_STACK
    }

    /// The triangle blocks in leaf order (for inspection and tests).
    pub fn blocks(&self) -> &[TriangleBlock] {
        &self.blocks
    }

    /// The tree over the blocks (for inspection and tests).
    pub fn bvh(&self) -> &Bvh<f32> {
        &self.bvh
    }

    /// Bytes of blocks, tree nodes and hint roots (counted whether made yet or not).
    pub fn memory_bytes(&self) -> usize {
        self.blocks.len() * (std::mem::size_of::<TriangleBlock>() + std::mem::size_of::<u32>())
            + self.thin.len()
            + self.bvh.memory_bytes()
    }
}

/// How far ahead of the triangle in hand a pass over a scene's triangles asks the cache
/// for one. A pass with some work per triangle waited on memory, one triangle's lines at
/// a time: asked for ahead, the 36 MB of a million triangles were read in less than half
/// the time (DEVELOPERS.md, "The build asks for triangles before it reads them").
const READ_AHEAD: usize = 48;

/// Asks the cache for triangle `i`, if there is one.
#[inline(always)]
fn prefetch_triangle(triangles: &[[[f32; 3]; 3]], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(t) = triangles.get(i) {
        let start = std::ptr::from_ref(t) as usize;
        crate::simd::prefetch(start, start + std::mem::size_of_val(t));
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (triangles, i);
}

pub(crate) fn build_triangles(
    triangles: &[[[f32; 3]; 3]],
    preset: BuildPreset,
) -> (Vec<TriangleBlock>, Vec<u8>, Bvh<f32>) {
    // Triangles without area are never hit, so they are left out of the tree. Most meshes
    // have none: then the tree is built over the input's own indices, without a list of the
    // kept ones to write and read through.
    let dropped: Vec<u32> = (0..triangles.len() as u32)
        .into_par_iter()
        .filter(|&i| {
            prefetch_triangle(triangles, i as usize + READ_AHEAD);
            triangle::is_degenerate(&triangles[i as usize])
        })
        .collect();
    let kept: Option<Vec<u32>> = (!dropped.is_empty()).then(|| {
        let mut dropped = dropped.iter().peekable();
        (0..triangles.len() as u32)
            .filter(|&i| dropped.next_if_eq(&&i).is_none())
            .collect()
    });
    let id = |k: usize| kept.as_ref().map_or(k as u32, |kept| kept[k]);
    let box_of = |k: usize| {
        // The leaves are made for runs of `k`, and kept triangles are in input order: the
        // triangle `READ_AHEAD` past this one is soon in hand.
        prefetch_triangle(triangles, id(k) as usize + READ_AHEAD);
        let [a, b, c] = triangles[id(k) as usize].map(Vec3A::from);
        Aabb::new(a.min(b).min(c), a.max(b).max(c))
    };
    let params = preset.params(TRIANGLES_PER_LEAF);
    let (mut bvh, order) = Bvh::build_from(
        triangles.len() - dropped.len(),
        box_of,
        params,
        LeafCost::TRIANGLE_BLOCKS,
    );
    let order: Vec<u32> = match &kept {
        Some(kept) => order.into_iter().map(|p| kept[p as usize]).collect(),
        None => order,
    };
    let runs = own_blocks(&mut bvh, order.len());
    let (blocks, thin): (Vec<TriangleBlock>, Vec<u8>) = (0..runs.len())
        .into_par_iter()
        .map(|b| {
            if let Some(&(ahead, count)) = runs.get(b + READ_AHEAD / BLOCK) {
                for &id in &order[ahead as usize..(ahead + count) as usize] {
                    prefetch_triangle(triangles, id as usize);
                }
            }
            let (first, count) = runs[b];
            let run = &order[first as usize..(first + count) as usize];
            let mut block = TriangleBlock {
                v: [[[0.0; BLOCK]; 3]; 3],
                ids: [0; BLOCK],
            };
            let mut thin = 0u8;
            for lane in 0..BLOCK {
                // A leaf's last block repeats its last triangle in unused lanes.
                let id = run[lane.min(run.len() - 1)];
                let triangle = &triangles[id as usize];
                for (k, vertex) in triangle.iter().enumerate() {
                    for (axis, &coordinate) in vertex.iter().enumerate() {
                        block.v[k][axis][lane] = coordinate;
                    }
                }
                block.ids[lane] = id;
                thin |= u8::from(triangle::is_thin(triangle)) << lane;
            }
            (block, thin)
        })
        .unzip();
    // Most meshes have no thin triangle: then `TriangleTree::is_thin` stops at the empty
    // list's length.
    let thin = if thin.iter().any(|&lanes| lanes != 0) {
        thin
    } else {
        Vec::new()
    };
    (blocks, thin, bvh)
}

/// Gives each leaf of `bvh` blocks of its own, and points it at them: a leaf of `n`
/// triangles gets `⌈n / 4⌉` blocks, its last padded with repeats. Returns each block's run
/// `(first, count)` of the build's leaf order (of `triangles` positions). Blocks shared
/// with neighbouring leaves would be fuller, but a ray entering a leaf would test up to
/// two blocks of its neighbours' triangles: the bench's rays tested a fifth fewer blocks
/// with blocks of their own (DEVELOPERS.md, "Each leaf has blocks of its own").
fn own_blocks(bvh: &mut Bvh<f32>, triangles: usize) -> Vec<(u32, u32)> {
    // The leaves' runs tile the leaf order. Each run's count, at its first position,
    // becomes the run's first block.
    let mut first_block = vec![0u32; triangles];
    let mut blocks = 0;
    for (first, count) in bvh.leaves() {
        first_block[first as usize] = count;
        blocks += count.div_ceil(BLOCK as u32) as usize;
    }
    let mut runs = Vec::with_capacity(blocks);
    let mut first = 0;
    while first < triangles {
        let count = first_block[first] as usize;
        assert!(count > 0, "the leaves tile the leaf order");
        first_block[first] = runs.len() as u32;
        for start in (first..first + count).step_by(BLOCK) {
            runs.push((start as u32, BLOCK.min(first + count - start) as u32));
        }
        first += count;
    }
    bvh.map_leaves(|first, count| (first_block[first as usize], count.div_ceil(BLOCK as u32)));
    runs
}

fn build_spheres(spheres: &[Sphere], preset: BuildPreset) -> (Vec<Sphere>, Vec<u32>, Bvh<f64>) {
    let box_of = |i: usize| {
        // Rounded outward past the float64 sums: the true surface reaches exactly c ± r.
        let s = &spheres[i];
        let c = s.center.to_array();
        Aabb::new(
            Vec3A::from_array(c.map(|x| bvh::f32_below(x - s.radius))),
            Vec3A::from_array(c.map(|x| bvh::f32_above(x + s.radius))),
        )
    };
    let params = preset.params(SPHERES_PER_LEAF);
    let (tree, ids) = Bvh::build_from(spheres.len(), box_of, params, LeafCost::ONE_BY_ONE);
    let order = ids.iter().map(|&p| spheres[p as usize]).collect();
    (order, ids, tree)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_hinted_search_names_the_subtree_above_the_leaf_it_stopped_at() {
        // Rays from outside a torus toward its triangles, each query hinted by the one
        // before, on both the AVX2 and the scalar paths. After every hit, the subtree the
        // hint keeps for the found block must be the node `HINT_LEVELS` above the node
        // holding its leaf, as a walk of the whole tree finds it
        // (`Bvh::leaf_ancestors`); a search of one of the hint's subtrees (its first or
        // second block's) names that subtree's node itself for a leaf the node holds.
        let torus = crate::procedural::torus(1.0, 0.35, 96, 40);
        let triangles: Vec<[[f32; 3]; 3]> = torus
            .triangles
            .iter()
            .map(|t| t.map(|i| torus.positions[i as usize]))
            .collect();
        let mut scene = Scene::build(&SceneGeometry {
            triangles: triangles.clone(),
            ..SceneGeometry::default()
        });
        let tree = scene.triangle_tree().clone();
        let (bvh, blocks) = (tree.bvh(), tree.blocks());
        assert!(
            bvh.depth() >= 3,
            "some leaves lie below the hint's subtrees"
        );
        let above = bvh.leaf_ancestors(blocks.len(), HINT_LEVELS);
        let holder = bvh.leaf_ancestors(blocks.len(), 0);
        let mut stand_ins = [[0; 2]; 2];
        for simd in [true, false] {
            scene.set_simd(simd && simd_available());
            let mut hint = AnyHitHint::default();
            for (i, t) in triangles.iter().enumerate() {
                let centroid = t.iter().fold(DVec3::ZERO, |sum, v| {
                    sum + Vec3::from_array(*v).as_dvec3() / 3.0
                });
                let origin = DVec3::new(3.0, 2.5, 1.5 + (i % 5) as f64 * 0.1);
                let ray = Ray {
                    origin,
                    direction: (centroid - origin).normalize(),
                    tmin: 0.0,
                    tmax: f64::INFINITY,
                };
                let [near, far] = hint.subtrees();
                let [first_guess, second_guess] = hint.blocks();
                assert!(scene.any_hit_hinted(&ray, &mut hint), "ray {i}");
                let block = (hint.triangle_slot().expect("a triangle stopped the ray")
                    / BLOCK as u32) as usize;
                let named = hint.subtrees()[0];
                // A leaf held by the root of a hint subtree searched (the first block's,
                // then the second's) is named by that root: seen only when that search
                // found it, so each search is shown to have run.
                let within = first_guess.is_some() && near != 0 && holder[block] == near;
                let within_far = second_guess.is_some() && far != 0 && holder[block] == far;
                assert!(
                    named == above[block]
                        || (within && named == near)
                        || (within_far && named == far),
                    "ray {i}, simd {simd}: block {block} named {named}, not {}",
                    above[block]
                );
                if named != above[block] {
                    stand_ins[usize::from(named == far && !within)][usize::from(simd)] += 1;
                }
            }
        }
        // [first block's, second block's][scalar, AVX2]
        assert!(
            stand_ins.iter().flatten().all(|&n| n > 0),
            "every subtree search found hits in leaves its root holds: {stand_ins:?}"
        );
    }
}
