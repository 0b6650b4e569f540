//! The any-hit hint: the triangle (and the sphere) that stopped a caller's previous
//! any-hit query, tested first by the next one.
//!
//! Neighbouring rays (the pixels of a tile, shadow rays from neighbouring points toward
//! one light) are mostly stopped by the same few triangles, most often by the block of
//! four triangles that stopped the ray before them. A hinted query tests that block
//! first, then the subtree around it ([`crate::scene::HINT_LEVELS`] above its leaf), and
//! only then the whole tree; most hitting rays end after one block test or a short search
//! instead of a descent from the root. A query that hits no triangle clears the hint, so a run of misses pays
//! nothing for it. Spheres likewise: the sphere that stopped the previous ray is tested
//! before the spheres' tree.
//!
//! The hint changes the work, never the answer: the block and the subtree are tested with
//! the traversal's own box and watertight tests over the same interval `tmin < t < tmax`,
//! so a hinted query returns `true` only for a real hit, and when they hold none the whole
//! tree is searched as by an unhinted query. A stale hint, or one from another scene,
//! costs a block test and a short search.
//!
//! ```
//! use raybatch::{AnyHitHint, Ray, Scene, SceneGeometry};
//! # let scene = Scene::build(&SceneGeometry::default());
//! # let rays: Vec<Ray> = Vec::new();
//! // One hint per run of neighbouring rays (per thread, per tile).
//! let mut hint = AnyHitHint::default();
//! let blocked = rays.iter().filter(|r| scene.any_hit_hinted(r, &mut hint)).count();
//! ```

use crate::triangle::BLOCK;

/// Where the previous any-hit queries that used this hint found a triangle and a sphere,
/// or nothing (the default, and after a query whose search of that kind found none).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AnyHitHint {
    /// A slot as in [`crate::scene::Primitive::Triangle`], or [`AnyHitHint::NONE`].
    slot: u32,
    /// An index into the scene's spheres in tree order, or [`AnyHitHint::NONE`].
    sphere: u32,
}

impl Default for AnyHitHint {
    fn default() -> AnyHitHint {
        AnyHitHint {
            slot: AnyHitHint::NONE,
            sphere: AnyHitHint::NONE,
        }
    }
}

impl AnyHitHint {
    const NONE: u32 = u32::MAX;

    /// The slot (see [`crate::scene::Tracer::triangle_id`]) of the triangle that stopped
    /// the last query that searched the triangles, if one did.
    pub fn triangle_slot(&self) -> Option<u32> {
        (self.slot != AnyHitHint::NONE).then_some(self.slot)
    }

    /// The block to test first, if any (it may be out of range for the scene at hand).
    #[inline(always)]
    pub(crate) fn block(&self) -> Option<usize> {
        self.triangle_slot()
            .map(|slot| (slot / BLOCK as u32) as usize)
    }

    /// Records the triangle (its slot) a search of the triangles found, or that it found
    /// none: then the next query starts without a guess.
    #[inline(always)]
    pub(crate) fn remember_triangle(&mut self, slot: Option<u32>) {
        self.slot = slot.unwrap_or(AnyHitHint::NONE);
    }

    /// The sphere (in the scene's tree order) to test first, if any.
    #[inline(always)]
    pub(crate) fn sphere(&self) -> Option<usize> {
        (self.sphere != AnyHitHint::NONE).then_some(self.sphere as usize)
    }

    /// Records the sphere a search of the spheres' tree found, or that it found none.
    #[inline(always)]
    pub(crate) fn remember_sphere(&mut self, sphere: Option<u32>) {
        self.sphere = sphere.unwrap_or(AnyHitHint::NONE);
    }
}
