//! The any-hit hint: the triangle (and the sphere) that stopped a caller's previous
//! any-hit query, tested first by the next one.
//!
//! Neighbouring rays (the pixels of a tile, shadow rays from neighbouring points toward
//! one light) are mostly stopped by the same few triangles, most often by the block of
//! four triangles that stopped the ray before them. A hinted query tests that block
//! first; if it missed, the block that stopped the ray [`AnyHitHint::ROWS`] queries
//! before (the ray above, in the renderer's 8 × 8 groups of pixels, whose rays go row by
//! row); then the subtree around the first ([`crate::scene::HINT_LEVELS`] above its
//! leaf), then the one around the second, and only then the whole tree. Most hitting rays
//! end after a block test or two or a short search instead of a descent from the root.
//! The subtree's node is kept with each block: the search that found the block named it
//! on its way down, so no table of the tree's blocks is made or read. A query that hits
//! no triangle leaves the next one without a guess, so a run of misses pays nothing for
//! the hint. Spheres likewise: the sphere that stopped the previous ray is tested before
//! the spheres' tree.
//!
//! The hint changes the work, never the answer: the blocks and the subtrees are tested with
//! the traversal's own box and watertight tests over the same interval `tmin < t < tmax`,
//! so a hinted query returns `true` only for a real hit, and when they hold none the whole
//! tree is searched as by an unhinted query. A stale hint, or one from another scene,
//! costs two block tests and at most two short searches (none where a node is past the
//! tree's end).
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
    /// The slots (as in [`crate::scene::Primitive::Triangle`]) found by the last
    /// [`AnyHitHint::ROWS`] queries that searched the triangles, or [`AnyHitHint::NONE`];
    /// a ring whose newest entry is at `newest`.
    slots: [u32; AnyHitHint::ROWS],
    /// For each entry of `slots`, the node of the triangle tree whose subtree is searched
    /// around it (see [`AnyHitHint::subtrees`]); 0, the root, when unknown.
    subtrees: [u32; AnyHitHint::ROWS],
    newest: u8,
    /// An index into the scene's spheres in tree order, or [`AnyHitHint::NONE`].
    sphere: u32,
}

impl Default for AnyHitHint {
    fn default() -> AnyHitHint {
        AnyHitHint {
            slots: [AnyHitHint::NONE; AnyHitHint::ROWS],
            subtrees: [0; AnyHitHint::ROWS],
            newest: 0,
            sphere: AnyHitHint::NONE,
        }
    }
}

impl AnyHitHint {
    const NONE: u32 = u32::MAX;

    /// How many queries back the second guess looks: a row of the renderer's square
    /// groups of pixels ([`crate::render::PACKET_SIDE`]), whose rays go row by row, so
    /// that the ray that many queries back is the one above.
    pub const ROWS: usize = crate::render::PACKET_SIDE as usize;

    /// The slot (see [`crate::scene::Tracer::triangle_id`]) of the triangle that stopped
    /// the last query that searched the triangles, if one did.
    pub fn triangle_slot(&self) -> Option<u32> {
        let slot = self.slots[usize::from(self.newest)];
        (slot != AnyHitHint::NONE).then_some(slot)
    }

    /// The blocks to test first, in order, if any (they may be out of range for the scene
    /// at hand): the previous query's, then the one [`AnyHitHint::ROWS`] queries back
    /// when it is another.
    #[inline(always)]
    pub(crate) fn blocks(&self) -> [Option<usize>; 2] {
        let block =
            |slot: u32| (slot != AnyHitHint::NONE).then_some((slot / BLOCK as u32) as usize);
        let previous = block(self.slots[usize::from(self.newest)]);
        // The oldest entry of the ring: the next query's `ROWS`-th predecessor.
        let above = block(self.slots[(usize::from(self.newest) + 1) % AnyHitHint::ROWS]);
        [previous, above.filter(|&b| Some(b) != previous)]
    }

    /// The subtrees around [`AnyHitHint::blocks`]' blocks, in the same order: the node
    /// [`crate::scene::HINT_LEVELS`] above the one holding each block's leaf, as the search
    /// that found it named it (0 when unknown: the whole tree).
    #[inline(always)]
    pub(crate) fn subtrees(&self) -> [u32; 2] {
        let newest = usize::from(self.newest);
        [
            self.subtrees[newest],
            self.subtrees[(newest + 1) % AnyHitHint::ROWS],
        ]
    }

    /// The subtrees a query searches, in order, once the hint's blocks have missed: the
    /// first block's, then the second's when there is a second block. None unless the
    /// first block is one of the `blocks` blocks of the tree at hand; none that is the
    /// root (the whole tree is searched next anyway), searched already, or past the
    /// tree's `nodes` nodes (a stale hint).
    #[inline(always)]
    pub(crate) fn subtrees_to_search(&self, blocks: usize, nodes: usize) -> [Option<u32>; 2] {
        let [first, second] = self.blocks();
        if first.is_none_or(|b| b >= blocks) {
            return [None, None];
        }
        let [near, far] = self.subtrees();
        let searchable = |node: u32| node != 0 && (node as usize) < nodes;
        [
            Some(near).filter(|&n| searchable(n)),
            Some(far).filter(|&f| second.is_some() && f != near && searchable(f)),
        ]
    }

    /// Records the triangle (its slot) a search of the triangles found, with the subtree
    /// around it, or that it found none: then the next query starts without a guess.
    #[inline(always)]
    pub(crate) fn remember_triangle(&mut self, found: Option<(u32, u32)>) {
        let newest = (usize::from(self.newest) + 1) % AnyHitHint::ROWS;
        let (slot, subtree) = found.unwrap_or((AnyHitHint::NONE, 0));
        self.slots[newest] = slot;
        self.subtrees[newest] = subtree;
        self.newest = newest as u8;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_second_guess_is_the_block_found_rows_queries_back() {
        // Queries found triangles in blocks 10, 11, ..., one block per query, with a miss
        // at query 3; before query `q`, the guesses are the block of query `q − 1` and
        // that of query `q − ROWS`.
        let found = |q: usize| (q != 3).then(|| (10 + q as u32) * BLOCK as u32 + 1);
        let block = |q: usize| found(q).map(|slot| (slot / BLOCK as u32) as usize);
        let mut hint = AnyHitHint::default();
        assert_eq!(hint.blocks(), [None, None]);
        // Each found triangle comes with its subtree (here 100 + q), or none (0) after a miss.
        let subtree = |q: usize| if q == 3 { 0 } else { 100 + q as u32 };
        for q in 0..3 * AnyHitHint::ROWS {
            hint.remember_triangle(found(q).map(|slot| (slot, subtree(q))));
            assert_eq!(hint.triangle_slot(), found(q), "query {q}");
            let back = (q + 1).checked_sub(AnyHitHint::ROWS);
            let above = back.and_then(block);
            assert_eq!(hint.blocks(), [block(q), above], "before query {}", q + 1);
            let above_subtree = back.map_or(0, subtree);
            assert_eq!(
                hint.subtrees(),
                [subtree(q), above_subtree],
                "query {}",
                q + 1
            );
        }
        // The same block twice is tested once.
        let mut hint = AnyHitHint::default();
        for _ in 0..AnyHitHint::ROWS {
            hint.remember_triangle(Some((4 * BLOCK as u32, 1)));
        }
        assert_eq!(hint.blocks(), [Some(4), None]);
    }
}
