//! What a camera ray computes. The set is closed and each render loop is specialized for
//! one integrator, so nothing is dispatched dynamically per ray.
//!
//! ```json
//! {"type": "hit"}
//! {"type": "depth", "scale": 10}
//! {"type": "normal"}
//! ```

use glam::DVec3;

use crate::manifest::Rgb;
use crate::ray::Ray;
use crate::scene::{Hit, Tracer};

/// The value of one camera ray (linear RGB), traced by any [`Tracer`].
pub trait Integrator: Sync {
    fn value<T: Tracer>(&self, scene: &T, ray: &Ray) -> Rgb;

    /// The value of a ray that hits nothing, when it is the same for every ray (the
    /// background); `None` when it depends on the ray. Where it is known, the render loop
    /// gives it to the rays of a tile that provably miss everything, without tracing
    /// them ([`crate::scene::Tracer::extent`]).
    fn miss(&self) -> Option<Rgb> {
        None
    }

    /// The values of many camera rays, `out[i]` for `rays[i]`: the same as [`value`] for
    /// each, but integrators that ask one query per ray ask them all at once, so that the
    /// tracer can trace coherent rays together.
    ///
    /// [`value`]: Integrator::value
    fn values<T: Tracer>(&self, scene: &T, rays: &[Ray], out: &mut [Rgb]) {
        for (ray, out) in rays.iter().zip(out) {
            *out = self.value(scene, ray);
        }
    }
}

/// Rays asked of the tracer at once: one render packet. The batch functions below work in
/// runs of this many, with buffers on the stack: a heap buffer per packet would take the
/// allocator's lock tens of thousands of times per image.
const RUN: usize = crate::packet::PACKET;

/// The closest hits of a batch of rays, `f(i, hit)` for ray `i`.
fn closest_hits<T: Tracer>(scene: &T, rays: &[Ray], mut f: impl FnMut(usize, Option<Hit>)) {
    for (run, rays) in rays.chunks(RUN).enumerate() {
        let mut hits = [None; RUN];
        scene.closest_hits(rays, &mut hits[..rays.len()]);
        for (i, hit) in hits[..rays.len()].iter().enumerate() {
            f(run * RUN + i, *hit);
        }
    }
}

/// `hit`: `[1, 1, 1]` where the ray hits anything, else the background. An any-hit
/// query: it stops at the first primitive found, whichever is nearest.
#[derive(Debug, Clone, Copy)]
pub struct HitIntegrator {
    pub background: Rgb,
}

impl HitIntegrator {
    fn of(&self, hit: bool) -> Rgb {
        if hit { [1.0; 3] } else { self.background }
    }
}

impl Integrator for HitIntegrator {
    fn miss(&self) -> Option<Rgb> {
        Some(self.background)
    }

    #[inline]
    fn value<T: Tracer>(&self, scene: &T, ray: &Ray) -> Rgb {
        self.of(scene.any_hit(ray))
    }

    fn values<T: Tracer>(&self, scene: &T, rays: &[Ray], out: &mut [Rgb]) {
        for (rays, out) in rays.chunks(RUN).zip(out.chunks_mut(RUN)) {
            let mut hits = [false; RUN];
            scene.any_hits(rays, &mut hits[..rays.len()]);
            for (out, &hit) in out.iter_mut().zip(&hits) {
                *out = self.of(hit);
            }
        }
    }
}

/// `depth`: `[t, t, t] / scale` for the closest hit, else the background.
#[derive(Debug, Clone, Copy)]
pub struct DepthIntegrator {
    pub scale: f64,
    pub background: Rgb,
}

impl DepthIntegrator {
    fn of(&self, hit: Option<Hit>) -> Rgb {
        match hit {
            Some(hit) => [hit.t / self.scale; 3],
            None => self.background,
        }
    }
}

impl Integrator for DepthIntegrator {
    fn miss(&self) -> Option<Rgb> {
        Some(self.background)
    }

    #[inline]
    fn value<T: Tracer>(&self, scene: &T, ray: &Ray) -> Rgb {
        self.of(scene.closest_hit(ray))
    }

    fn values<T: Tracer>(&self, scene: &T, rays: &[Ray], out: &mut [Rgb]) {
        closest_hits(scene, rays, |i, hit| out[i] = self.of(hit));
    }
}

/// `normal`: `0.5 * (n + 1)` for the unit geometric normal `n` of the closest hit, not
/// flipped toward the ray; else the background.
#[derive(Debug, Clone, Copy)]
pub struct NormalIntegrator {
    pub background: Rgb,
}

impl NormalIntegrator {
    fn of(&self, normal: Option<DVec3>) -> Rgb {
        match normal {
            Some(n) => [0.5 * (n.x + 1.0), 0.5 * (n.y + 1.0), 0.5 * (n.z + 1.0)],
            None => self.background,
        }
    }
}

impl Integrator for NormalIntegrator {
    fn miss(&self) -> Option<Rgb> {
        Some(self.background)
    }

    #[inline]
    fn value<T: Tracer>(&self, scene: &T, ray: &Ray) -> Rgb {
        self.of(scene.closest_hit(ray).map(|hit| scene.normal(ray, &hit)))
    }

    /// Asks for the normals of a run's hits at once, which a tracer may compute
    /// several at a time.
    fn values<T: Tracer>(&self, scene: &T, rays: &[Ray], out: &mut [Rgb]) {
        for (rays, out) in rays.chunks(RUN).zip(out.chunks_mut(RUN)) {
            let mut hits = [None; RUN];
            let hits = &mut hits[..rays.len()];
            scene.closest_hits(rays, hits);
            for (out, hit) in out.iter_mut().zip(&*hits) {
                if hit.is_none() {
                    *out = self.background;
                }
            }
            scene.normals(rays, hits, |i, normal| out[i] = self.of(Some(normal)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plane::Plane;
    use crate::sphere::Sphere;
    use crate::{Scene, SceneGeometry};

    /// Every integrator's batch [`Integrator::values`] against its one-ray
    /// [`Integrator::value`], bit for bit, over runs of camera-like rays that hit a sphere,
    /// a plane or a triangle, or nothing: then the value is the background.
    #[test]
    fn values_are_each_ray_s_value_and_misses_are_the_background() {
        let scene = Scene::build(&SceneGeometry {
            spheres: vec![Sphere {
                center: DVec3::new(-0.8, 0.0, 4.0),
                radius: 0.7,
            }],
            planes: vec![Plane {
                point: DVec3::new(0.0, -1.0, 0.0),
                normal: DVec3::new(0.0, 1.0, 0.0),
            }],
            triangles: vec![[[0.2, -0.5, 3.0], [1.4, -0.5, 3.0], [0.8, 0.7, 3.5]]],
            ..SceneGeometry::default()
        });
        // Rays fanning out from the origin over a 24 × 24 grid: a few runs, with misses
        // above the plane's horizon.
        let rays: Vec<Ray> = (0..24 * 24)
            .map(|i| Ray {
                origin: DVec3::ZERO,
                direction: DVec3::new(
                    f64::from(i % 24) / 12.0 - 1.0,
                    f64::from(i / 24) / 12.0 - 1.0,
                    1.0,
                )
                .normalize(),
                tmin: 0.0,
                tmax: f64::INFINITY,
            })
            .collect();
        let background = [0.25, 0.5, 0.75];
        let check = |name: &str, value: &dyn Fn(&Ray) -> Rgb, values: &[Rgb]| {
            let mut misses = 0;
            for (ray, batch) in rays.iter().zip(values) {
                let one = value(ray);
                assert_eq!(one.map(f64::to_bits), batch.map(f64::to_bits), "{name}");
                if scene.closest_hit(ray).is_none() {
                    assert_eq!(one, background, "{name}");
                    misses += 1;
                }
            }
            assert!(misses > 50 && misses < rays.len() - 50, "{name}: {misses}");
        };
        let mut out = vec![[9.0; 3]; rays.len()];
        let hit = HitIntegrator { background };
        hit.values(&scene, &rays, &mut out);
        check("hit", &|r| hit.value(&scene, r), &out);
        let depth = DepthIntegrator {
            scale: 2.0,
            background,
        };
        depth.values(&scene, &rays, &mut out);
        check("depth", &|r| depth.value(&scene, r), &out);
        let normal = NormalIntegrator { background };
        normal.values(&scene, &rays, &mut out);
        check("normal", &|r| normal.value(&scene, r), &out);
    }
}
