//! The stress suite (`raybatch stress`): the cases where renderers usually break, each
//! answered by raybatch and checked against a reference that does not come from the code
//! under test: hit points built exactly on the surface (a vertex, an edge midpoint, a point
//! projected onto a sphere) so the true distance is known, float64 formulas of a different
//! form than the code's, or closed shapes that no ray from inside may escape.
//!
//! A ray is *wrong* when it hits where the reference misses or misses where it hits, or when
//! its distance differs from the reference by more than the case's tolerance (relative:
//! 10⁻⁵ for float32 triangles, 10⁻⁹ for float64 spheres and planes). Every case of the
//! report must show zero wrong rays; the tests assert it.

use std::fmt::Write as _;

use glam::DVec3;

use crate::manifest::Manifest;
use crate::offset::SurfacePoint;
use crate::plane::Plane;
use crate::procedural;
use crate::ray::Ray;
use crate::scene::{Scene, SceneGeometry};
use crate::sphere::Sphere;

/// How many rays the suite traces.
#[derive(Debug, Clone, Copy)]
pub struct StressOptions {
    /// Rays through the shared vertices and edges of the closed mesh, in all.
    pub leak_rays: usize,
    /// Rays per case of the other groups.
    pub rays: usize,
}

impl StressOptions {
    /// What `raybatch stress` runs: over a million leak rays.
    pub const FULL: StressOptions = StressOptions {
        leak_rays: 1 << 20,
        rays: 20_000,
    };
    /// Fewer rays per case, for a quick look.
    pub const QUICK: StressOptions = StressOptions {
        leak_rays: 1 << 16,
        rays: 2_000,
    };
}

/// Scene scales swept: 10⁻⁴ to 10⁷.
pub const SCALES: [f64; 12] = [
    1e-4, 1e-3, 1e-2, 1e-1, 1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7,
];
/// Translations swept, as `(scale, translation)`.
pub const TRANSLATIONS: [(f64, f64); 4] = [(1.0, 1e2), (1.0, 1e4), (1.0, 1e6), (1e3, 1e6)];

/// Relative distance tolerance for float32 triangles and float64 analytic shapes.
pub const TRIANGLE_TOLERANCE: f64 = 1e-5;
pub const ANALYTIC_TOLERANCE: f64 = 1e-9;

/// One case's outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct Case {
    pub group: &'static str,
    pub name: String,
    pub rays: u64,
    pub wrong: u64,
    /// Largest relative distance error over the rays that hit where they should.
    pub max_error: f64,
}

/// Every case.
#[derive(Debug, Clone, Default)]
pub struct StressReport {
    pub cases: Vec<Case>,
}

impl StressReport {
    pub fn wrong(&self) -> u64 {
        self.cases.iter().map(|c| c.wrong).sum()
    }

    pub fn rays(&self) -> u64 {
        self.cases.iter().map(|c| c.rays).sum()
    }

    /// A Markdown table, one row per case.
    pub fn to_markdown(&self) -> String {
        let mut out = String::from(
            "| group | case | rays | wrong | max rel. distance error |\n|---|---|---:|---:|---:|\n",
        );
        for c in &self.cases {
            let _ = writeln!(
                out,
                "| {} | {} | {} | {} | {:.1e} |",
                c.group, c.name, c.rays, c.wrong, c.max_error
            );
        }
        let _ = writeln!(out, "\n{} rays, {} wrong.", self.rays(), self.wrong());
        out
    }

    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "rays": self.rays(),
            "wrong": self.wrong(),
            "cases": self.cases.iter().map(|c| serde_json::json!({
                "group": c.group, "case": c.name, "rays": c.rays, "wrong": c.wrong,
                "max_error": c.max_error,
            })).collect::<Vec<_>>(),
        })
    }
}

/// Runs every case.
pub fn run(options: StressOptions) -> StressReport {
    let mut cases = Vec::new();
    let mut placements: Vec<(f64, f64)> = SCALES.iter().map(|&s| (s, 0.0)).collect();
    placements.extend(TRANSLATIONS);
    for &(scale, shift) in &placements {
        cases.push(closed_mesh_from_inside(scale, shift, options.rays));
        cases.push(sphere_from_outside(scale, shift, options.rays));
    }
    cases.push(leaks(options.leak_rays));
    for radius in [1e-4, 1e-2, 1.0] {
        for distance in [1e3, 1e5, 1e7] {
            cases.push(tiny_far_sphere(radius, distance, options.rays));
        }
    }
    for radius in [1e3, 1e5, 1e7] {
        cases.push(starting_on_a_huge_sphere(radius, options.rays));
    }
    for &(scale, shift) in &placements {
        for kind in Surface::ALL {
            cases.push(self_intersection(kind, scale, shift, options.rays));
        }
    }
    cases.push(grazing_spheres(options.rays));
    cases.push(needles(1e-2, options.rays));
    cases.push(needles(1e-5, options.rays));
    cases.push(degenerate_triangles(options.rays));
    cases.push(direction_components());
    cases.push(interval_ends());
    cases.push(non_finite_input());
    StressReport { cases }
}

/// Counts rays against their reference.
#[derive(Debug, Default)]
struct Tally {
    rays: u64,
    wrong: u64,
    max_error: f64,
}

impl Tally {
    /// One ray: `got` and `expected` distances (`None`: a miss).
    fn check(&mut self, got: Option<f64>, expected: Option<f64>, tolerance: f64) {
        self.rays += 1;
        match (got, expected) {
            (None, None) => {}
            (Some(got), Some(expected)) => {
                let error = (got - expected).abs() / expected.abs().max(f64::MIN_POSITIVE);
                self.max_error = self.max_error.max(error);
                // A NaN distance is wrong too.
                if error.is_nan() || error > tolerance {
                    self.wrong += 1;
                }
            }
            _ => self.wrong += 1,
        }
    }

    fn case(self, group: &'static str, name: String) -> Case {
        Case {
            group,
            name,
            rays: self.rays,
            wrong: self.wrong,
            max_error: self.max_error,
        }
    }
}

/// Deterministic numbers (SplitMix64), so every run traces the same rays.
pub struct Numbers(u64);

impl Numbers {
    pub fn new(seed: u64) -> Numbers {
        Numbers(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform on the unit sphere.
    pub fn direction(&mut self) -> DVec3 {
        let z = self.range(-1.0, 1.0);
        let phi = self.range(0.0, std::f64::consts::TAU);
        let r = (1.0 - z * z).max(0.0).sqrt();
        DVec3::new(r * phi.cos(), r * phi.sin(), z)
    }

    /// Uniform on the hemisphere around unit `n`.
    pub fn hemisphere(&mut self, n: DVec3) -> DVec3 {
        let d = self.direction();
        if d.dot(n) < 0.0 { -d } else { d }
    }
}

fn scene(triangles: Vec<[[f32; 3]; 3]>, spheres: Vec<Sphere>, planes: Vec<Plane>) -> Scene {
    Scene::build(&SceneGeometry {
        triangles,
        spheres,
        planes,
        ..SceneGeometry::default()
    })
}

fn ray(origin: DVec3, direction: DVec3) -> Ray {
    Ray {
        origin,
        direction,
        tmin: 0.0,
        tmax: f64::INFINITY,
    }
}

/// The ray from `origin` through `target`, and the distance to it.
pub(crate) fn aimed(origin: DVec3, target: DVec3) -> (Ray, f64) {
    let to = target - origin;
    let distance = to.length();
    (ray(origin, to / distance), distance)
}

fn f32_point(p: DVec3) -> DVec3 {
    p.as_vec3().as_dvec3()
}

/// A closed icosphere of `radius` around `center`, as stored (float32) triangles.
pub(crate) fn icosphere(subdivisions: u32, radius: f64, center: DVec3) -> Vec<[[f32; 3]; 3]> {
    let g = procedural::icosphere(subdivisions);
    let placed: Vec<[f32; 3]> = g
        .positions
        .iter()
        .map(|p| {
            (center + DVec3::from_array(p.map(f64::from)) * radius)
                .as_vec3()
                .to_array()
        })
        .collect();
    g.triangles
        .iter()
        .map(|t| t.map(|i| placed[i as usize]))
        .collect()
}

/// Every vertex and edge midpoint of `triangles`, exactly (float32 sums are exact in
/// float64).
pub(crate) fn shared_targets(triangles: &[[[f32; 3]; 3]]) -> Vec<DVec3> {
    let mut targets = Vec::new();
    for t in triangles {
        let [a, b, c] = t.map(|v| DVec3::from_array(v.map(f64::from)));
        targets.extend([a, (a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5]);
    }
    targets
}

fn place_name(scale: f64, shift: f64) -> String {
    if shift == 0.0 {
        format!("scale {scale:.0e}")
    } else {
        format!("scale {scale:.0e}, moved {shift:.0e}")
    }
}

/// Rays from inside a closed icosphere to its vertices and edge midpoints: each must hit
/// at exactly the distance to its target (the mesh is convex, so nothing is nearer).
fn closed_mesh_from_inside(scale: f64, shift: f64, rays: usize) -> Case {
    let center = DVec3::splat(shift);
    let triangles = icosphere(2, scale, center);
    let targets = shared_targets(&triangles);
    let scene = scene(triangles, vec![], vec![]);
    let mut numbers = Numbers::new(1);
    let mut tally = Tally::default();
    for i in 0..rays {
        // Origins are float32 points, so the triangle path sees the very same ray origin.
        let origin = f32_point(center + numbers.direction() * (0.5 * scale * numbers.unit()));
        let (r, distance) = aimed(origin, targets[i % targets.len()]);
        tally.check(
            scene.closest_hit(&r).map(|h| h.t),
            Some(distance),
            TRIANGLE_TOLERANCE,
        );
    }
    tally.case(
        "scale",
        format!("closed mesh from inside, {}", place_name(scale, shift)),
    )
}

/// A point on the sphere's cap facing `origin`, seen from `origin` without obstruction.
fn visible_point(sphere: &Sphere, origin: DVec3, numbers: &mut Numbers) -> DVec3 {
    let toward = (origin - sphere.center).normalize();
    let cosine_horizon = sphere.radius / (origin - sphere.center).length();
    loop {
        let u = numbers.hemisphere(toward);
        if u.dot(toward) > cosine_horizon + 0.05 * (1.0 - cosine_horizon) {
            return sphere.center + u * sphere.radius;
        }
    }
}

/// The reference for a sphere: the distance to where the line enters it, from the
/// perpendicular foot `(f × d)` form rather than the code's; `None` inside a thin band of
/// relative width 10⁻⁹ around tangency, where the answer is not decided by the reference.
fn sphere_reference(sphere: &Sphere, r: &Ray) -> Option<Option<f64>> {
    let f = sphere.center - r.origin;
    let along = f.dot(r.direction);
    let off = f.cross(r.direction).length();
    let margin = 1e-9 * sphere.radius;
    if (off - sphere.radius).abs() <= margin {
        return None;
    }
    if off > sphere.radius || along <= 0.0 {
        return Some(None);
    }
    let half = ((sphere.radius - off) * (sphere.radius + off)).sqrt();
    Some(Some(along - half))
}

/// The reference distance at which a ray from inside `sphere` leaves it (the far root).
fn sphere_exit(sphere: &Sphere, r: &Ray) -> f64 {
    let f = sphere.center - r.origin;
    let along = f.dot(r.direction);
    let off = f.cross(r.direction).length();
    along
        + ((sphere.radius - off) * (sphere.radius + off))
            .max(0.0)
            .sqrt()
}

/// Whether a ray that started just inside `sphere` met it where it leaves: at the
/// reference exit distance, or for a chord shorter than 1% of the radius (where both the
/// reference and any float64 root lose digits to `r² − l²`) at least half of it.
fn leaves_far_side(sphere: &Sphere, r: &Ray, got: Option<f64>) -> bool {
    let exit = sphere_exit(sphere, r);
    got.is_some_and(|t| {
        if exit > 0.01 * sphere.radius {
            (t - exit).abs() <= ANALYTIC_TOLERANCE * exit
        } else {
            t > 0.5 * exit
        }
    })
}

/// Ray `i` of a sphere case from `origin` (outside), with its reference: even rays aimed
/// at a point of the sphere's visible side (the distance to it is known), odd ones at a
/// point just beside the sphere (some lines cross it, some pass it). `None` for a line too
/// near tangency for the reference to decide.
pub(crate) fn sphere_case_ray(
    sphere: &Sphere,
    origin: DVec3,
    i: usize,
    numbers: &mut Numbers,
) -> Option<(Ray, Option<f64>)> {
    if i.is_multiple_of(2) {
        let (r, distance) = aimed(origin, visible_point(sphere, origin, numbers));
        Some((r, Some(distance)))
    } else {
        let target = sphere.center + numbers.direction() * (1.2 * sphere.radius);
        let (r, _) = aimed(origin, target);
        sphere_reference(sphere, &r).map(|expected| (r, expected))
    }
}

/// Rays from outside to points on a sphere's near side, and rays past it.
fn sphere_from_outside(scale: f64, shift: f64, rays: usize) -> Case {
    let sphere = Sphere {
        center: DVec3::splat(shift),
        radius: scale,
    };
    let scene = scene(vec![], vec![sphere], vec![]);
    let mut numbers = Numbers::new(2);
    let mut tally = Tally::default();
    for i in 0..rays {
        let origin = sphere.center + numbers.direction() * (3.0 * scale);
        if let Some((r, expected)) = sphere_case_ray(&sphere, origin, i, &mut numbers) {
            tally.check(
                scene.closest_hit(&r).map(|h| h.t),
                expected,
                ANALYTIC_TOLERANCE,
            );
        }
    }
    tally.case(
        "scale",
        format!("sphere from outside, {}", place_name(scale, shift)),
    )
}

/// Rays from inside a closed icosphere through its shared vertices and edge midpoints:
/// none may escape.
fn leaks(rays: usize) -> Case {
    let triangles = icosphere(3, 1.0, DVec3::ZERO);
    let targets = shared_targets(&triangles);
    let scene = scene(triangles, vec![], vec![]);
    let mut numbers = Numbers::new(3);
    let mut tally = Tally::default();
    let mut origin = DVec3::ZERO;
    for i in 0..rays {
        if i % 64 == 0 {
            origin = numbers.direction() * (0.9 * numbers.unit());
        }
        let (r, distance) = aimed(origin, targets[i % targets.len()]);
        // Only a miss counts here: the distance is checked by the scale cases.
        let got = scene.any_hit(&r).then_some(distance);
        tally.check(got, Some(distance), 0.0);
    }
    tally.case(
        "leaks",
        "rays from inside through shared vertices and edges of a closed 1,280-triangle mesh"
            .to_string(),
    )
}

/// Tiny spheres far away, where the tutorial's formula sees nothing in float32.
fn tiny_far_sphere(radius: f64, distance: f64, rays: usize) -> Case {
    let mut numbers = Numbers::new(4);
    let sphere = Sphere {
        center: numbers.direction() * distance,
        radius,
    };
    let scene = scene(vec![], vec![sphere], vec![]);
    let mut tally = Tally::default();
    for i in 0..rays {
        if let Some((r, expected)) = sphere_case_ray(&sphere, DVec3::ZERO, i, &mut numbers) {
            tally.check(
                scene.closest_hit(&r).map(|h| h.t),
                expected,
                ANALYTIC_TOLERANCE,
            );
        }
    }
    tally.case(
        "tiny far sphere",
        format!("radius {radius:.0e} at distance {distance:.0e}"),
    )
}

/// Rays leaving a huge sphere from where a camera ray hit it: outward they hit nothing,
/// inward they cross it and leave at the far side's reference distance.
fn starting_on_a_huge_sphere(radius: f64, rays: usize) -> Case {
    let mut numbers = Numbers::new(5);
    let sphere = Sphere {
        center: numbers.direction() * radius * 0.5,
        radius,
    };
    let scene = scene(vec![], vec![sphere], vec![]);
    let mut tally = Tally::default();
    for _ in 0..rays {
        let origin = sphere.center + numbers.direction() * (2.0 * radius);
        let (primary, _) = aimed(origin, visible_point(&sphere, origin, &mut numbers));
        let Some(hit) = scene.closest_hit(&primary) else {
            tally.check(None, Some(1.0), 0.0);
            continue;
        };
        let at = scene.surface_point(&primary, &hit);
        let n = at.normal;
        let outward = numbers.hemisphere(n);
        tally.check(
            scene.closest_hit(&at.spawn(outward)).map(|h| h.t),
            None,
            0.0,
        );
        let inward = at.spawn(-numbers.hemisphere(n));
        let got = scene.closest_hit(&inward).map(|h| h.t);
        let exit = sphere_exit(&sphere, &inward);
        match leaves_far_side(&sphere, &inward, got) {
            true if exit > 0.01 * radius => tally.check(got, Some(exit), ANALYTIC_TOLERANCE),
            right => tally.check(right.then_some(1.0), Some(1.0), 0.0),
        }
    }
    tally.case(
        "huge sphere",
        format!("rays starting on a sphere of radius {radius:.0e}"),
    )
}

/// Surfaces that secondary rays leave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    Sphere,
    Plane,
    /// A closed icosphere.
    ClosedMesh,
    /// Two triangles 2000 times the scale across, hit near their middle.
    BigTriangles,
}

impl Surface {
    pub const ALL: [Surface; 4] = [
        Surface::Sphere,
        Surface::Plane,
        Surface::ClosedMesh,
        Surface::BigTriangles,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Surface::Sphere => "sphere",
            Surface::Plane => "plane",
            Surface::ClosedMesh => "closed mesh",
            Surface::BigTriangles => "big triangles",
        }
    }

    /// The scene of this surface alone at `scale` around `center`.
    pub fn scene(self, scale: f64, center: DVec3, numbers: &mut Numbers) -> Scene {
        match self {
            Surface::Sphere => scene(
                vec![],
                vec![Sphere {
                    center,
                    radius: scale,
                }],
                vec![],
            ),
            Surface::Plane => scene(
                vec![],
                vec![],
                vec![Plane {
                    point: center,
                    normal: numbers.direction(),
                }],
            ),
            Surface::ClosedMesh => scene(icosphere(2, scale, center), vec![], vec![]),
            Surface::BigTriangles => {
                let n = numbers.direction();
                let u = n.any_orthonormal_vector();
                let v = n.cross(u);
                let half = 1000.0 * scale;
                let corner = |a: f64, b: f64| {
                    (center + u * (a * half) + v * (b * half))
                        .as_vec3()
                        .to_array()
                };
                let (p, q, r, s) = (
                    corner(-1.0, -1.0),
                    corner(1.0, -1.0),
                    corner(1.0, 1.0),
                    corner(-1.0, 1.0),
                );
                scene(vec![[p, q, r], [p, r, s]], vec![], vec![])
            }
        }
    }
}

/// Secondary rays leaving a surface where a camera ray hit it, in every direction
/// (grazing ones too): a ray leaving outward must hit nothing (every surface here is
/// convex or flat and alone); one leaving inward into a closed surface must reach the far
/// side (at least a tenth of the scale away) rather than its own starting point; one
/// leaving through a flat surface must hit nothing.
pub fn self_intersection(kind: Surface, scale: f64, shift: f64, rays: usize) -> Case {
    let (wrong, total) = count_self_intersections(kind, scale, shift, rays, SurfacePoint::spawn);
    Case {
        group: "offsets",
        name: format!(
            "{} leaving {}, {}",
            "rays",
            kind.name(),
            place_name(scale, shift)
        ),
        rays: total,
        wrong,
        max_error: 0.0,
    }
}

/// Rays leaving `kind` that hit it again where they start, of all rays traced; `spawn`
/// makes the secondary ray (the robust offset, or an alternative to compare).
pub fn count_self_intersections(
    kind: Surface,
    scale: f64,
    shift: f64,
    rays: usize,
    spawn: impl Fn(&SurfacePoint, DVec3) -> Ray,
) -> (u64, u64) {
    let mut numbers = Numbers::new(6);
    let center = DVec3::splat(shift);
    let scene = kind.scene(scale, center, &mut numbers);
    let (mut wrong, mut total) = (0, 0);
    while total < rays as u64 {
        let origin = center + numbers.direction() * (3.0 * scale);
        let target = center + numbers.direction() * (0.3 * scale);
        let (primary, _) = aimed(origin, target);
        let Some(hit) = scene.closest_hit(&primary) else {
            continue;
        };
        let at = scene.surface_point(&primary, &hit);
        // The side the camera ray came from is "outward" for every surface here.
        let n = if primary.direction.dot(at.normal) < 0.0 {
            at.normal
        } else {
            -at.normal
        };
        let outward = numbers.hemisphere(n);
        total += 1;
        if scene.closest_hit(&spawn(&at, outward)).is_some() {
            wrong += 1;
        }
        let inward = spawn(&at, -numbers.hemisphere(n));
        total += 1;
        let again = scene.closest_hit(&inward);
        let right = match (kind, again) {
            // Flat surfaces: nothing behind them.
            (Surface::Plane | Surface::BigTriangles, again) => again.is_none(),
            (Surface::Sphere, Some(h)) => {
                let sphere = Sphere {
                    center,
                    radius: scale,
                };
                leaves_far_side(&sphere, &inward, Some(h.t))
            }
            // A ray entering a convex mesh leaves through another triangle: meeting the
            // one it started on again is self-intersection.
            (Surface::ClosedMesh, Some(h)) => h.primitive != hit.primitive,
            (_, None) => false,
        };
        if !right {
            wrong += 1;
        }
    }
    (wrong, total)
}

/// Lines passing a sphere just inside and just outside its radius (by 10⁻⁸ to 10⁻³ of it).
fn grazing_spheres(rays: usize) -> Case {
    let mut numbers = Numbers::new(7);
    let mut tally = Tally::default();
    for i in 0..rays {
        let radius = 10f64.powf(numbers.range(-3.0, 6.0));
        let sphere = Sphere {
            center: numbers.direction() * radius * numbers.range(0.0, 100.0),
            radius,
        };
        let scene = scene(vec![], vec![sphere], vec![]);
        let d = numbers.direction();
        let side = d.any_orthonormal_vector();
        let off = radius
            * (1.0 + if i % 2 == 0 { 1.0 } else { -1.0 } * 10f64.powf(numbers.range(-8.0, -3.0)));
        let origin = sphere.center + side * off - d * (radius * numbers.range(2.0, 50.0));
        let r = ray(origin, d);
        if let Some(expected) = sphere_reference(&sphere, &r) {
            tally.check(
                scene.closest_hit(&r).map(|h| h.t),
                expected,
                ANALYTIC_TOLERANCE,
            );
        }
    }
    tally.case(
        "grazing",
        "lines within 10⁻³ of a sphere's radius, inside and out".to_string(),
    )
}

/// The float64 reference for one stored triangle: the distance and barycentric weights
/// where the ray's line meets its plane (Cramer's rule on the exact float32 vertices).
pub(crate) fn triangle_reference(t: &[[f32; 3]; 3], r: &Ray) -> Option<(f64, [f64; 3])> {
    let [a, b, c] = t.map(|v| DVec3::from_array(v.map(f64::from)));
    let (e1, e2) = (b - a, c - a);
    let p = r.direction.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 {
        return None;
    }
    let s = r.origin - a;
    let b1 = s.dot(p) / det;
    let q = s.cross(e1);
    let b2 = r.direction.dot(q) / det;
    let t = e2.dot(q) / det;
    Some((t, [1.0 - b1 - b2, b1, b2]))
}

/// Needle triangles `1/aspect` times longer than wide, hit inside (and only inside), at
/// the float64 plane distance. (The float32 test resolves a needle's plane only to about
/// `10⁻⁷ / aspect`; the tracer takes the distance of a hit on a thin triangle on its plane
/// in float64, see [`crate::triangle::THIN_ASPECT`].)
fn needles(aspect: f64, rays: usize) -> Case {
    let mut numbers = Numbers::new(8);
    let mut tally = Tally::default();
    while tally.rays < rays as u64 {
        let length = 10f64.powf(numbers.range(-2.0, 4.0));
        let along = numbers.direction();
        let across = along.any_orthonormal_vector();
        let base = numbers.direction() * length;
        let tri = [
            base,
            base + along * length,
            base + along * (0.5 * length) + across * (length * aspect),
        ]
        .map(|v| v.as_vec3().to_array());
        let scene = scene(vec![tri], vec![], vec![]);
        let [a, b, c] = tri.map(|v| DVec3::from_array(v.map(f64::from)));
        let weights = [numbers.range(0.25, 0.45), numbers.range(0.25, 0.45)];
        let target = a + (b - a) * weights[0] + (c - a) * weights[1];
        // A float32 origin: the triangle path traces in float32, and a needle is as narrow
        // as float32 resolves, so the reference takes the ray as traced.
        let origin = f32_point(target + numbers.direction() * length);
        let (mut r, _) = aimed(origin, target);
        r.direction = f32_point(r.direction);
        let Some((t, bary)) = triangle_reference(&tri, &r) else {
            continue;
        };
        // Only points clearly inside (a needle's width is near float32's resolution) and
        // rays at least 6° off the plane (grazing ones magnify any error in the plane).
        let normal = (b - a).cross(c - a).normalize();
        if bary.iter().all(|&w| w > 0.2) && t > 0.0 && r.direction.dot(normal).abs() > 0.1 {
            let got = scene.closest_hit(&r).map(|h| h.t);
            tally.check(got, Some(t), TRIANGLE_TOLERANCE);
        }
    }
    tally.case(
        "needles",
        format!(
            "needle triangles {:.0e} times longer than wide (hits and depth)",
            1.0 / aspect
        ),
    )
}

/// Triangles of zero area (three equal vertices, two equal, three in a line) are never
/// hit, even by rays aimed at their points.
fn degenerate_triangles(rays: usize) -> Case {
    let mut numbers = Numbers::new(9);
    let mut tally = Tally::default();
    for i in 0..rays {
        let a = numbers.direction() * 10.0;
        let b = a + numbers.direction();
        let tri = match i % 3 {
            0 => [a, a, a],
            1 => [a, b, a],
            // The midpoint of two float32 points, exactly on their line in float64 too
            // when it is representable; checked below.
            _ => [
                a,
                b,
                (a.as_vec3().as_dvec3() + b.as_vec3().as_dvec3()) * 0.5,
            ],
        }
        .map(|v| v.as_vec3().to_array());
        let [p, q, m] = tri.map(|v| DVec3::from_array(v.map(f64::from)));
        if (q - p).cross(m - p) != DVec3::ZERO {
            continue;
        }
        let scene = scene(vec![tri], vec![], vec![]);
        let target = p + (q - p) * numbers.unit();
        let (r, _) = aimed(target + numbers.direction() * 5.0, target);
        tally.check(scene.closest_hit(&r).map(|h| h.t), None, 0.0);
    }
    tally.case("degenerate", "zero-area triangles".to_string())
}

/// Rays whose direction has components that are zero, tiny, or below float32's range,
/// aimed at grids of small triangles facing each axis: each must hit at the float64
/// distance.
fn direction_components() -> Case {
    let tiny = [0.0, 1e-30, -1e-30, 1e-40, -1e-45, 1e-300, -1e-300];
    let mut tally = Tally::default();
    for axis in 0..3 {
        // A 32×32 grid of triangle pairs on the plane `x[axis] = 1`, corners at exact
        // float32 coordinates.
        let n = 32;
        let place = |u: f64, v: f64| {
            let mut p = [0f32; 3];
            p[axis] = 1.0;
            p[(axis + 1) % 3] = u as f32;
            p[(axis + 2) % 3] = v as f32;
            p
        };
        let mut triangles = Vec::new();
        for j in 0..n {
            for i in 0..n {
                let (u0, v0) = (
                    -1.0 + 2.0 * i as f64 / n as f64,
                    -1.0 + 2.0 * j as f64 / n as f64,
                );
                let (u1, v1) = (u0 + 2.0 / n as f64, v0 + 2.0 / n as f64);
                triangles.push([place(u0, v0), place(u1, v0), place(u1, v1)]);
                triangles.push([place(u0, v0), place(u1, v1), place(u0, v1)]);
            }
        }
        let scene = scene(triangles, vec![], vec![]);
        for (k, &a) in tiny.iter().enumerate() {
            for &b in &tiny {
                for origin_step in 0..5 {
                    let mut d = [0.0; 3];
                    d[axis] = 1.0;
                    d[(axis + 1) % 3] = a;
                    d[(axis + 2) % 3] = b;
                    let mut o = [0.0; 3];
                    // Origins inside cells, clear of edges, so the answer is one cell.
                    o[(axis + 1) % 3] = -0.93 + 0.41 * origin_step as f64 + 0.01 * k as f64;
                    o[(axis + 2) % 3] = 0.77 - 0.37 * origin_step as f64;
                    let r = ray(DVec3::from_array(o), DVec3::from_array(d).normalize());
                    // The plane `x[axis] = 1` is at t = 1 / d[axis] from the origin.
                    tally.check(
                        scene.closest_hit(&r).map(|h| h.t),
                        Some(1.0 / r.direction[axis]),
                        TRIANGLE_TOLERANCE,
                    );
                    tally.check(
                        scene.any_hit(&r).then_some(1.0 / r.direction[axis]),
                        Some(1.0 / r.direction[axis]),
                        0.0,
                    );
                }
            }
        }
    }
    tally.case(
        "directions",
        "direction components 0, ±10⁻³⁰, float32-subnormal and below float32's range".to_string(),
    )
}

/// Surfaces at exactly `t = 5` along +z: a ray whose interval ends at 5 (either end) does
/// not hit; one whose interval reaches one float past 5 does.
fn interval_ends() -> Case {
    let scenes = [
        scene(
            vec![[[-1.0, -1.0, 5.0], [1.0, -1.0, 5.0], [0.0, 1.0, 5.0]]],
            vec![],
            vec![],
        ),
        scene(
            vec![],
            vec![Sphere {
                center: DVec3::new(0.0, 0.0, 6.0),
                radius: 1.0,
            }],
            vec![],
        ),
        scene(
            vec![],
            vec![],
            vec![Plane {
                point: DVec3::new(0.0, 0.0, 5.0),
                normal: DVec3::Z,
            }],
        ),
    ];
    let mut tally = Tally::default();
    for scene in &scenes {
        for (tmin, tmax, expected) in [
            (0.0, 5.0, None),
            (0.0, 5f64.next_up(), Some(5.0)),
            // Intervals end before 6, short of the sphere's far side at 7.
            (5.0, 6.0, None),
            (5f64.next_down(), 6.0, Some(5.0)),
        ] {
            let r = Ray {
                origin: DVec3::ZERO,
                direction: DVec3::Z,
                tmin,
                tmax,
            };
            tally.check(scene.closest_hit(&r).map(|h| h.t), expected, 0.0);
            tally.check(scene.any_hit(&r).then_some(5.0), expected, 0.0);
        }
    }
    tally.case(
        "interval",
        "hits exactly at tmin and tmax excluded, one float inside included".to_string(),
    )
}

/// Manifests with non-finite or out-of-range numbers are refused; rays with non-finite
/// parts find nothing (and do not panic).
fn non_finite_input() -> Case {
    let manifests = [
        r#"{"spheres": [{"center": [0, 0, 1e400], "radius": 1}]}"#,
        r#"{"spheres": [{"center": [0, 0, 3], "radius": 1e300}]}"#,
        r#"{"spheres": [{"center": [0, 0, 3], "radius": 0}]}"#,
        r#"{"planes": [{"point": [0, 0, 3], "normal": [0, 0, 0]}]}"#,
        r#"{"camera": {"forward": [0, 0, 0]}}"#,
        r#"{"camera": {"look_from": [0, 0, 0], "look_at": [0, 0, 0]}}"#,
        r#"{"meshes": [{"file": "m.obj", "transform": {"scale": 1e300}}], "spheres": []}"#,
        r#"{"image": {"width": 0, "height": 4}}"#,
    ];
    let mut tally = Tally::default();
    for text in manifests {
        let refused = Manifest::parse(text.as_bytes(), std::path::Path::new("stress.json"));
        // A refusal is "no hit"; an accepted manifest is a wrong "hit".
        tally.check(refused.ok().map(|_| 1.0), None, 0.0);
    }
    let scene = scene(
        icosphere(1, 1.0, DVec3::new(0.0, 0.0, 3.0)),
        vec![Sphere {
            center: DVec3::new(0.0, 0.0, 3.0),
            radius: 1.0,
        }],
        vec![Plane {
            point: DVec3::new(0.0, 0.0, 9.0),
            normal: DVec3::Z,
        }],
    );
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        for r in [
            ray(DVec3::new(bad, 0.0, 0.0), DVec3::Z),
            ray(DVec3::ZERO, DVec3::new(bad, 0.0, 1.0)),
            ray(DVec3::ZERO, DVec3::ZERO),
        ] {
            tally.check(scene.closest_hit(&r).map(|h| h.t), None, 0.0);
        }
    }
    tally.case(
        "non-finite",
        "non-finite and out-of-range input refused".to_string(),
    )
}
