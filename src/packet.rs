//! Packets of coherent rays (the camera rays of an 8 × 8 tile) traced together with AVX2
//! (and AVX-512 where the CPU has it).
//!
//! Inner nodes are tested once per packet, with bounds on the packet's entry and exit
//! distances: the products `(plane − origin) · (1/d)` are bilinear in the origin and the
//! reciprocal direction, so their extremes over the packet lie at the corners of the
//! ranges of both, and since rounding is monotonic the corners computed in float32 bound
//! every ray's own computed value. A node is therefore skipped only if every ray's own
//! robust test would skip it. Leaves are tested with exactly the single-ray box and
//! triangle arithmetic: the box against a row of eight rays per instruction, then the
//! triangles either ray by ray (a leaf's blocks two at a time, eight triangles per
//! instruction, as a single ray tests them) or, where most of a row entered the box, each
//! triangle against the row's eight rays at once. With AVX-512 ([`LeafLanes::Sixteen`])
//! the box and the triangles take two rows at a time. Rays from one origin first leave out
//! the leaf's triangles that none of them can hit (module `shear_cull`), which changes
//! no ray's answer. A packet needs all its rays to share the signs of their direction (one
//! near plane per axis); callers trace other rays one by one.

use std::arch::x86_64::*;
use std::cell::Cell;
use std::mem::MaybeUninit;

use crate::bvh::{Bounds, Bvh, LEAF, WIDTH, leaf_range};
use crate::scene::TriangleRay;
use crate::shear_cull::ShearCull;
use crate::simd::{
    Hits, STACK, TriLanes, block_pair_test, block_test, distance, lanes3, lanes4, lanes8, pack,
    prefetch_child, push_sorted, row_constants, row_test, slab_test,
};
use crate::simd512;
use crate::triangle::{BLOCK, Nearest, SEARCH_MARGIN, TriangleBlock, TriangleHit};

/// Most rays in a packet.
pub const PACKET: usize = 64;
/// Rows of eight rays.
const ROWS: usize = PACKET / 8;

/// Rays of a row entering a leaf from which the row test (each triangle against all eight
/// rays) replaces the rays' own block tests (four triangles against one ray).
const ROW_TEST_FROM: u32 = 5;
/// Rays of a pair of rows entering a leaf from which the sixteen-lane row test (each
/// triangle against both rows at once, [`crate::simd512`]) replaces the rows' own tests.
/// Lower than for a row: on a CPU with full-width AVX-512 units a sixteen-lane test costs
/// what an eight-lane one does. Any-hit packets on the torus, whose leaves few rays
/// enter, were slower at 3 than with eight lanes; from 6 they are not (DEVELOPERS.md,
/// which says how to compare).
const WIDE_ROW_TEST_FROM: u32 = 6;
/// Pairs of rows taking a leaf's triangles by the sixteen-lane row test (or twice as many
/// rows by the eight-lane one) from which the triangles no ray can hit are looked for
/// first (`shear_cull`): where fewer do, looking costs about what it saves.
const CULL_FROM_PAIRS: usize = 2;

/// The bound below which a triangle distance may still matter to a ray whose nearest hit
/// so far is `nearest`: strict for any-hit (`t < tmax`), ties admitted for closest (which
/// [`Nearest::improves`] decides).
#[inline(always)]
fn t_triangle<const ANY: bool>(nearest: Nearest) -> f32 {
    if ANY { nearest.t } else { nearest.t.next_up() }
}

/// Stack entries for a leaf carry its parent node and slot (for the leaf's box).
const SLOT_BITS: u32 = 3;

/// One group of rays' constants, a ray per lane of `V`, as `slab_test!` reads them (with
/// a leaf's planes broadcast to every lane).
pub(crate) struct GroupLanes<V> {
    pub origin: [V; 3],
    pub inv_dir: [V; 3],
    pub inv_dir_far: [V; 3],
    /// Offsets of each axis's near and far planes in a node.
    pub near: [usize; 3],
    pub far: [usize; 3],
}

impl<V> GroupLanes<V> {
    /// The group's constants, each read by `lanes` from the packet's per-ray arrays.
    #[inline(always)]
    pub(crate) fn read<R>(
        [origin, inv_dir, inv_dir_far]: [&[R; 3]; 3],
        (near, far): ([usize; 3], [usize; 3]),
        lanes: impl Fn(&R) -> V,
    ) -> GroupLanes<V> {
        GroupLanes {
            origin: origin.each_ref().map(&lanes),
            inv_dir: inv_dir.each_ref().map(&lanes),
            inv_dir_far: inv_dir_far.each_ref().map(&lanes),
            near,
            far,
        }
    }
}

/// A float32 at `p` in all eight lanes.
///
/// # Safety
/// `p` must be valid to read; only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn broadcast_ps(p: *const f32) -> __m256 {
    // SAFETY: as required of the caller.
    unsafe { _mm256_broadcast_ss(&*p) }
}

/// The stack reference of the leaf in `slot` of node `parent`.
#[inline(always)]
pub(crate) fn leaf_entry(parent: u32, slot: usize) -> u32 {
    LEAF | (parent << SLOT_BITS) | slot as u32
}

/// The parent node and slot of a [`leaf_entry`].
#[inline(always)]
pub(crate) fn leaf_parent(entry: u32) -> (usize, usize) {
    let parent = (entry & !LEAF) >> SLOT_BITS;
    (parent as usize, (entry & ((1 << SLOT_BITS) - 1)) as usize)
}

/// Pops entries until one whose distance is at most `horizon`, and returns its
/// reference; `None` once the stack is empty.
///
/// # Safety
/// Every slot below `sp` must have been written.
#[inline(always)]
pub(crate) unsafe fn pop_within(
    stack: &[MaybeUninit<u64>],
    sp: &mut usize,
    horizon: f32,
) -> Option<u32> {
    while *sp > 0 {
        *sp -= 1;
        // SAFETY: as required of the caller.
        let entry = unsafe { stack[*sp].assume_init() };
        if distance(entry) <= horizon {
            return Some(entry as u32);
        }
    }
    None
}

/// What one packet's traversal visited: how well its rays shared the work.
///
/// A packet's inner-node test bounds all its rays at once, so it reaches every leaf that
/// some ray *might* enter. When the rays spread over many small leaves (a detailed mesh
/// seen at low resolution) most leaves it reaches are entered by no ray at all, and
/// tracing the rays one by one is faster. So too where an any-hit packet's rays are mostly
/// stopped, but only after a search that hinted single rays skip ([`Visits::hints_pay`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Visits {
    /// Leaves reached.
    pub leaves: u32,
    /// Rays entering their boxes, summed over those leaves.
    pub entries: u32,
    /// Leaves some ray entered.
    pub entered: u32,
    /// The packet's rays (0 for sphere packets, which do not count them).
    pub rays: u32,
    /// Rays an any-hit packet through the triangles stopped (0 for closest hit, for
    /// sphere packets, and for a packet that gave up).
    pub stopped: u32,
}

impl Visits {
    /// Fewest leaves from which a packet says anything to the pacing ([`record`]): one
    /// reaching fewer (its rays mostly miss) neither starts nor ends a spell of groups
    /// traced one by one.
    pub const JUDGED_FROM: u32 = 16;
    /// Fewest entered leaves from which a packet's rays may be
    /// [`scattered`](Visits::scattered). Where a wasteful packet straddles a mesh's edge,
    /// most of its rays miss and the rest enter a few leaves, one ray each: on the
    /// bench's 320x180 torus in the renderer's order, the packets that began the spells
    /// entered 7, 5 and 3 leaves. Counted as not scattered (when this was
    /// [`Visits::JUDGED_FROM`]), they sent every spell one by one, and the view's batch
    /// queries ran 10–15% slower than side by side (DEVELOPERS.md, "Rays that share no
    /// leaves are traced side by side"). A packet that entered none still says nothing.
    pub const SCATTERED_FROM: u32 = 4;
    /// Fewest leaves from which a packet may be [`wasteful`](Visits::wasteful): one per
    /// ray of a full packet. Timing each packet of `raybatch bench`'s full-HD torus
    /// (through the lens and not) against its rays one by one (a probe, not kept), the
    /// packets that reached fewer were 1.3–3.8x as fast as their rays alone, even with
    /// more leaves than rays entering them (mostly rays that miss, at the surface's
    /// edges). Judged wasteful from 16 leaves, they began spells of one by one over the
    /// groups around them: `raybatch bench --embree --only lens` read the lens view's
    /// `closest 64` at 0.83–0.90x Embree's streams then, 0.92–0.97x at 2d33613
    /// (DEVELOPERS.md, "Packets give way to single rays…").
    pub const WASTEFUL_FROM: u32 = PACKET as u32;
    /// Leaves from which a packet still [`wasteful`](Visits::wasteful) gives up: sixteen
    /// per ray of a full packet. Of the packets of `raybatch bench`'s views, one in 69 at
    /// 320x180 reached more (up to 2047), the others at most 1023, so hardly any that
    /// would have finished is cut short. A packet whose rays are spread much wider than
    /// the leaves (a small image of a large mesh) reaches thousands: each of those cost a
    /// 16x16 view of the million-triangle torus 3 to 8 ms, against 0.1 ms for the whole
    /// image traced one by one (DEVELOPERS.md, "A packet that reaches thousands of
    /// leaves gives up").
    pub const GIVE_UP_FROM: u32 = 16 * PACKET as u32;
    /// Leaves reached per entering ray above which a packet is judged wasteful: where
    /// tracing one by one becomes about as fast, through the triangles (an 82k-triangle
    /// icosphere at 128², the full-HD torus of `raybatch bench`) as through the spheres
    /// (the sphere field at 64²), timing each packet against its rays one by one
    /// (DEVELOPERS.md, "Performance notes").
    pub const MOST_LEAVES_PER_ENTRY: u32 = 1;
    /// An any-hit packet that stopped at least half its rays hands the next groups to
    /// hinted single rays when its rays entered fewer than this percentage of the leaves
    /// it reached ([`Visits::hints_pay`]). Timing each any-hit packet of `raybatch
    /// bench`'s views against its rays one by one with the hint (a probe, not kept), and
    /// replaying the pacing over those times: from 40%, the shadow rays' packets cost
    /// 0.73 of what they did, through the lens 0.97, nefertiti and ogre 1.01; from 30%,
    /// 0.80, 1.00 and 1.00; from 50%, 0.67, 0.98 and 1.02–1.03 (DEVELOPERS.md, "Hinted
    /// single rays take over from some any-hit packets").
    pub const HINTS_PAY_BELOW_ENTERED_PERCENT: u32 = 40;

    /// Whether so few rays entered the leaves the packet reached (at least
    /// [`Visits::WASTEFUL_FROM`]) that the next rays nearby are better traced one by one.
    pub fn wasteful(self) -> bool {
        self.leaves >= Self::WASTEFUL_FROM
            && self.leaves > Self::MOST_LEAVES_PER_ENTRY * self.entries
    }

    /// Whether the rays entered at least [`Visits::SCATTERED_FROM`] leaves and hardly any
    /// of them with more than one ray (at most 1/16 more rays than leaves entered): the
    /// rays share few nodes, and traced one by one, each ray's search would be a chain of
    /// cache misses of its own. So a wasteful packet over a mesh finer than the pixels
    /// (the bench's torus at 320x180: 60 leaves entered, by 60 rays, of 555 reached, on
    /// average). Through the bench's lens, where packets are wasteful because their
    /// bounds are wide, neighbouring rays share leaves (three rays per entered leaf on
    /// average), and a quarter of the wasteful packets enter no leaf at all (their rays
    /// miss); counted as scattered, those made the lens row's batches 7–10% slower than
    /// one by one.
    pub fn scattered(self) -> bool {
        self.entered >= Self::SCATTERED_FROM && 16 * self.entries <= 17 * self.entered
    }

    /// Whether a packet, so far, has reached at least [`Visits::GIVE_UP_FROM`] leaves and
    /// is [`wasteful`](Visits::wasteful): then it stops, reporting no closest hit, and its
    /// rays are to be traced another way. A packet is judged after every leaf, so it
    /// returns hopeless visits exactly when it gave up. What it spent is bounded by that
    /// count; what it saves is unbounded.
    pub fn hopeless(self) -> bool {
        self.leaves >= Self::GIVE_UP_FROM && self.wasteful()
    }

    /// Whether an any-hit packet that reached at least [`Visits::JUDGED_FROM`] leaves
    /// stopped at least half its rays, while fewer than
    /// [`Visits::HINTS_PAY_BELOW_ENTERED_PERCENT`] percent of those leaves were entered by
    /// any ray: the packet's bounds take in far more than its rays' paths, and the next
    /// rays nearby are better traced one by one, where each ray tests first the triangle
    /// that stopped the ray before it ([`crate::AnyHitHint`]). So shadow rays from
    /// neighbouring points toward one light: the packet searches the leaves around their
    /// origins and between them, while a hinted ray is mostly stopped by its neighbour's
    /// triangle before any search.
    pub fn hints_pay(self) -> bool {
        self.leaves >= Self::JUDGED_FROM
            && self.stopped > 0
            && 2 * self.stopped >= self.rays
            && 100 * u64::from(self.entered)
                < u64::from(Self::HINTS_PAY_BELOW_ENTERED_PERCENT) * u64::from(self.leaves)
    }
}

/// A tree that packets cross, each with its own pacing: a thread's sphere packets may
/// pay where its triangle packets do not. Any-hit packets through the triangles are paced
/// apart from closest-hit ones, as hinted single rays may beat only the former
/// ([`Visits::hints_pay`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PacedTree {
    Triangles,
    TrianglesAnyHit,
    Spheres,
}

thread_local! {
    /// This thread's pacing of packets per [`PacedTree`].
    static PACING: [Cell<Pacing>; 3] = const { [const { Cell::new(Pacing::FRESH) }; 3] };
    /// The triangles that stopped every ray of this thread's last any-hit packet that
    /// hit, when there were at most [`Stoppers::MOST`] of them: its next any-hit packet
    /// tests them before its traversal.
    static STOPPERS: Cell<Stoppers> = const { Cell::new(Stoppers::NONE) };
}

/// The slots of the triangles that stopped an any-hit packet's rays, if few.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Stoppers {
    slots: [u32; Stoppers::MOST],
    len: usize,
    /// A ray stopped elsewhere (by more triangles, or ray by ray): no hint.
    spoiled: bool,
}

impl Stoppers {
    /// The most triangles a hint holds. In a close-up, where a visible triangle spans
    /// many packets, nearly every packet's rays are stopped by one or two.
    const MOST: usize = 2;
    const NONE: Stoppers = Stoppers {
        slots: [0; Stoppers::MOST],
        len: 0,
        spoiled: false,
    };

    /// Notes that the triangle in `slot` stopped rays.
    fn add(&mut self, slot: u32) {
        if self.slots[..self.len].contains(&slot) {
            return;
        }
        if self.len == Self::MOST {
            self.spoiled = true;
        } else {
            self.slots[self.len] = slot;
            self.len += 1;
        }
    }

    /// The hint they leave for the next packet.
    fn hint(self) -> Stoppers {
        if self.spoiled { Stoppers::NONE } else { self }
    }
}

/// Groups of rays traced one by one after a wasteful packet before a packet is tried
/// again (neighbouring groups, the render loop's next ones, often see the same detail);
/// it doubles with each wasteful packet in a row, up to [`MOST_SINGLE_AFTER_WASTE`], so that
/// an image where packets never pay tries few.
pub const SINGLE_AFTER_WASTE: u32 = 2;
/// The most groups traced one by one between two packets.
pub const MOST_SINGLE_AFTER_WASTE: u32 = 128;

/// Whether this thread's next group of rays should be tried as a packet through `tree`:
/// not for a while after a [`wasteful`](Visits::wasteful) one, or one whose rays hinted
/// single rays would stop for less ([`Visits::hints_pay`]). Either way gives the same
/// hits; this only picks the faster.
pub fn worth_trying(tree: PacedTree) -> bool {
    PACING.with(|pacing| {
        let pacing = &pacing[tree as usize];
        let state = pacing.get();
        pacing.set(Pacing {
            left: state.left.saturating_sub(1),
            ..state
        });
        state.left == 0
    })
}

/// Whether the wasteful packet that began this thread's spell of groups traced one by
/// one through `tree` found its rays [`scattered`](Visits::scattered): then they are
/// better traced side by side ([`crate::interleaved`]) than one after the other. Never
/// after a packet judged only by [`Visits::hints_pay`]: side by side, a ray tests only
/// its previous ray's block, not its neighbours' (the bench's shadow rays ran at 0.36x
/// the speed of hinted single rays).
pub fn scattered(tree: PacedTree) -> bool {
    PACING.with(|pacing| pacing[tree as usize].get().scattered)
}

/// Records what a packet through `tree` visited, for [`worth_trying`] and [`scattered`].
pub fn record(tree: PacedTree, visits: Visits) {
    if visits.leaves < Visits::JUDGED_FROM {
        return;
    }
    PACING.with(|pacing| {
        let pacing = &pacing[tree as usize];
        let next = pacing.get().next;
        pacing.set(if visits.wasteful() || visits.hints_pay() {
            Pacing {
                left: next,
                next: (2 * next).min(MOST_SINGLE_AFTER_WASTE),
                scattered: visits.wasteful() && visits.scattered(),
            }
        } else {
            Pacing::FRESH
        });
    });
}

/// A thread's pacing of packets through one tree.
#[derive(Debug, Clone, Copy)]
struct Pacing {
    /// Groups of rays still to trace one by one.
    left: u32,
    /// How many the next wasteful packet sends one by one.
    next: u32,
    /// Whether the last wasteful packet found its rays scattered.
    scattered: bool,
}

impl Pacing {
    const FRESH: Pacing = Pacing {
        left: 0,
        next: SINGLE_AFTER_WASTE,
        scattered: false,
    };
}

/// One ray per lane, eight rays per row; two rows fill a 64-byte AVX-512 register.
#[repr(C, align(64))]
struct Rows([[f32; 8]; ROWS]);

/// A packet's per-ray values, set up once per packet by [`traverse`].
#[repr(C)]
struct RayRows {
    origin: [Rows; 3],
    /// Reciprocal directions for the near planes, and rounded up for the far ones.
    inv: [Rows; 3],
    inv_far: [Rows; 3],
    /// Each ray's shear, for the watertight triangle test.
    shear: [Rows; 3],
    tmin: Rows,
    /// Each ray's axes `k` (`simd::ray_constants`).
    axes: [[usize; 3]; PACKET],
    search: Search,
}

/// Where each ray of a packet stands in its search, a ray per lane as in [`RayRows`]: in
/// rows, so that a row test's hits are taken a row at a time in a few vector instructions
/// ([`fold_row_hits8`], [`fold_row_hits16`]) rather than ray by ray through memory
/// (DEVELOPERS.md, "A row test's hits are taken a row at a time").
#[repr(C)]
struct Search {
    /// The bound a box's entry must stay below: the ray's nearest hit so far, or its
    /// `tmax`; −∞ once the ray is done or in lanes past the packet's rays.
    t_box: Rows,
    /// The bound its triangle distances must stay below (`t_triangle`).
    t_tri: Rows,
    /// The ray's [`Nearest`]: its distance (`tmax` before any hit) and, as bits, its slot.
    /// Closest hit only; any hit leaves them as they start.
    near_t: Rows,
    near_slot: Rows,
    /// The barycentric weights of that hit ([`TriangleHit`]): written, and read, only
    /// where the packet's `found` has the ray's bit (the folds store them masked, so
    /// nothing reads the rest, and the set-up need not write them).
    b: [MaybeUninit<Rows>; 3],
}

/// Closest hits of up to [`PACKET`] rays traced together: `found(i, nearest, hit)` is
/// called for each ray `i` with a triangle hit, the nearest (as [`crate::simd::closest`]
/// finds it). Returns what the traversal visited, or `None`, calling nothing, when the
/// rays' directions differ in sign on some axis, a ray has a NaN, or an origin or
/// direction is infinite. A packet that [gave up](Visits::hopeless) has called nothing
/// either.
///
/// # Safety
/// The CPU must have what [`crate::simd::available`] checks (AVX2 and its bit
/// instructions), and for [`LeafLanes::Sixteen`] what [`simd512::available`] checks; and
/// `bvh.stack_bound() <= STACK`.
#[inline]
pub unsafe fn closest(
    lanes: LeafLanes,
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    found: impl FnMut(usize, Nearest, TriangleHit),
) -> Option<Visits> {
    // SAFETY: as required of the caller.
    unsafe {
        match lanes {
            LeafLanes::Eight => trace_avx2::<false>(bvh, blocks, rays, found, &mut []),
            LeafLanes::Sixteen => trace_avx512::<false>(bvh, blocks, rays, found, &mut []),
        }
    }
}

/// Whether each of up to [`PACKET`] rays hits any triangle (`out[i]` for ray `i`), traced
/// together; rays leave the packet as soon as they hit. Returns what the traversal
/// visited, or `None`, touching nothing, as for [`closest`]; nor does a packet that gave
/// up touch `out`.
///
/// # Safety
/// As for [`closest`].
#[inline]
pub unsafe fn any(
    lanes: LeafLanes,
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    out: &mut [bool],
) -> Option<Visits> {
    assert_eq!(rays.len(), out.len());
    let found = |_, _, _| ();
    // SAFETY: as required of the caller.
    unsafe {
        match lanes {
            LeafLanes::Eight => trace_avx2::<true>(bvh, blocks, rays, found, out),
            LeafLanes::Sixteen => trace_avx512::<true>(bvh, blocks, rays, found, out),
        }
    }
}

/// How many rays a packet's leaf tests take at once: a row of eight (AVX2), or two rows
/// (AVX-512). Either gives the same hits, bit for bit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeafLanes {
    Eight,
    Sixteen,
}

impl LeafLanes {
    /// The widest this CPU supports, if it supports packets at all (AVX2).
    pub fn widest() -> Option<LeafLanes> {
        if simd512::available() {
            Some(LeafLanes::Sixteen)
        } else if crate::simd::available() {
            Some(LeafLanes::Eight)
        } else {
            None
        }
    }
}

/// [`trace`] with eight-lane leaf tests, compiled for AVX2.
///
/// # Safety
/// As for [`closest`], with AVX2 and its bit instructions ([`crate::simd::available`]).
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn trace_avx2<const ANY: bool>(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    closest: impl FnMut(usize, Nearest, TriangleHit),
    any: &mut [bool],
) -> Option<Visits> {
    // SAFETY: as required of the caller.
    unsafe { trace::<ANY, false>(bvh, blocks, rays, closest, any) }
}

/// [`trace`] with sixteen-lane leaf tests, compiled for AVX-512 (and AVX2).
///
/// # Safety
/// As for [`closest`], with AVX-512F as well ([`simd512::available`]).
#[target_feature(enable = "avx2,avx512f,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn trace_avx512<const ANY: bool>(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    closest: impl FnMut(usize, Nearest, TriangleHit),
    any: &mut [bool],
) -> Option<Visits> {
    // SAFETY: as required of the caller.
    unsafe { trace::<ANY, true>(bvh, blocks, rays, closest, any) }
}

/// The packet traversal: closest hits reported to `closest`, or with `ANY` hit flags
/// into `any`; leaf tests sixteen rays wide with `WIDE`.
///
/// # Safety
/// Only from [`trace_avx2`] (without `WIDE`) or [`trace_avx512`], into which it inlines.
#[inline(always)]
unsafe fn trace<const ANY: bool, const WIDE: bool>(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    closest: impl FnMut(usize, Nearest, TriangleHit),
    any: &mut [bool],
) -> Option<Visits> {
    assert!(rays.len() <= PACKET);
    assert!(
        bvh.stack_bound() <= STACK,
        "the scalar path handles deeper trees"
    );
    if rays.is_empty() {
        return Some(Visits::default());
    }
    // SAFETY: AVX2 is enabled where `trace` inlines.
    let packet = unsafe { PacketBounds::of(rays) }?;
    any.fill(false);
    // SAFETY: as above.
    if unsafe { packet.misses(&bvh.bounds()) } {
        return Some(Visits::default());
    }
    // Compiled apart, so that a common origin's node test has nothing to shift.
    // SAFETY: as required of this function.
    unsafe {
        if packet.shift == 0.0 {
            traverse::<ANY, WIDE, false>(&packet, bvh, blocks, rays, closest, any)
        } else {
            traverse::<ANY, WIDE, true>(&packet, bvh, blocks, rays, closest, any)
        }
    }
}

/// [`trace`] past the packet's bounds: `SHIFTED` when they are taken from the rays' waist
/// ([`PacketBounds::shift`] is not 0).
///
/// # Safety
/// As for [`trace`], into which it inlines.
#[inline(always)]
unsafe fn traverse<const ANY: bool, const WIDE: bool, const SHIFTED: bool>(
    packet: &PacketBounds,
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    mut closest: impl FnMut(usize, Nearest, TriangleHit),
    any: &mut [bool],
) -> Option<Visits> {
    let n = rays.len();
    let mut visits = Visits {
        rays: n as u32,
        ..Visits::default()
    };
    // Per-ray values, in rows of eight lanes; lanes past `n` repeat the last ray but
    // never hit (their tmax is −∞). Written whole below before any read: zeroing them
    // first cost every packet a 4 kB memset (DEVELOPERS.md).
    let mut storage = MaybeUninit::<RayRows>::uninit();
    let fill = storage.as_mut_ptr();
    // The rows whose rays share their axes `k` (as camera rays nearly always do), which
    // the row test needs.
    let mut shared_axes = [false; ROWS];
    // The largest horizon over the rays still searching.
    let mut packet_tmax = packet.horizon;
    // The same for the node test (less the packet's shift).
    let mut node_tmax = packet.node_tmax::<SHIFTED>(packet_tmax);
    // Each row's set-up at once, a ray per lane: the divisions and choices of
    // `simd::ray_constants`, the same IEEE operations lane by lane (so bit-identical).
    for r in 0..ROWS {
        // SAFETY: AVX2 is enabled where `trace` inlines.
        let row = unsafe { row_constants(std::array::from_fn(|l| &rays[(r * 8 + l).min(n - 1)])) };
        // SAFETY: `rows` points into `storage`, and rows are 32-byte aligned arrays of
        // eight floats; only raw places are formed, so nothing unwritten is referenced.
        let store = |rows: *mut Rows, x: __m256| unsafe {
            _mm256_store_ps((&raw mut (*rows).0[r]).cast::<f32>(), x)
        };
        let row_axes: [[usize; 3]; 8] = std::array::from_fn(|l| row.axes(l));
        shared_axes[r] = row_axes.iter().all(|&k| k == row_axes[0]);
        // SAFETY (this block): `fill` points to `storage`; each place is written, not read.
        unsafe {
            for a in 0..3 {
                store(&raw mut (*fill).origin[a], row.origin[a]);
                store(&raw mut (*fill).inv[a], row.inv[a]);
                store(&raw mut (*fill).inv_far[a], row.inv_far[a]);
                store(&raw mut (*fill).shear[a], row.shear[a]);
            }
            store(&raw mut (*fill).tmin, row.tmin);
            for (l, &axes) in row_axes.iter().enumerate() {
                let k = r * 8 + l;
                let nearest = Nearest::before(if k < n {
                    rays[k].tmax
                } else {
                    f32::NEG_INFINITY
                });
                (*fill).axes[k] = axes;
                let search = &raw mut (*fill).search;
                (*search).near_t.0[r][l] = nearest.t;
                (*search).near_slot.0[r][l] = f32::from_bits(nearest.slot);
                (*search).t_box.0[r][l] = nearest.horizon();
                (*search).t_tri.0[r][l] = t_triangle::<ANY>(nearest);
            }
        }
    }
    // SAFETY: the loop above wrote every field, every row and every ray of `storage`,
    // but for the weights, which stay `MaybeUninit`.
    let RayRows {
        origin,
        inv,
        inv_far,
        shear: shear_rows,
        tmin,
        axes,
        search,
    } = unsafe { storage.assume_init_mut() };
    // The same for pairs of rows, which the sixteen-lane row test needs.
    let shared_pairs: [bool; ROWS / 2] = std::array::from_fn(|pair| {
        let r = 2 * pair;
        shared_axes[r] && shared_axes[r + 1] && axes[r * 8] == axes[r * 8 + 8]
    });
    // Rays from one origin sharing their axes (a pinhole's tile) let a leaf's triangles
    // that none of them can hit be found once per triangle (`shear_cull`).
    let cull = if !SHIFTED
        && packet.origin.iter().all(|&(lo, hi)| lo == hi)
        && shared_axes.iter().all(|&shared| shared)
        && (0..ROWS).all(|r| axes[r * 8] == axes[0])
    {
        // SAFETY: AVX2 is enabled where `trace` inlines.
        let (sx, sy) = unsafe { (row_range(&shear_rows[0]), row_range(&shear_rows[1])) };
        Some(ShearCull::new(
            axes[0],
            packet.origin.map(|(lo, _)| lo),
            sx,
            sy,
        ))
    } else {
        None
    };
    let nodes = bvh.nodes();
    if nodes.is_empty() {
        return Some(visits);
    }
    let mut live = n;
    // A bit per ray with a hit: for closest hit, the nearest so far, in `search`.
    let mut found = 0u64;
    let offset = |side: usize, axis: usize| (side * 3 + axis) * WIDTH;
    let near: [usize; 3] = [0, 1, 2].map(|a| offset(packet.octant[a], a));
    let far: [usize; 3] = [0, 1, 2].map(|a| offset(1 - packet.octant[a], a));

    // The constants of row `$row` (or rows `$row` and `$row + 1`) for the row test, read
    // by `$row_lanes`: they share the axes of ray `8 · $row`.
    macro_rules! row_lanes {
        ($row:expr, $row_lanes:ident) => {{
            let [kx, ky, kz] = axes[$row * 8];
            TriLanes {
                kx,
                ky,
                kz,
                origin_k: [kx, ky, kz].map(|a| $row_lanes(&origin[a])),
                sx: $row_lanes(&shear_rows[0]),
                sy: $row_lanes(&shear_rows[1]),
                sz: $row_lanes(&shear_rows[2]),
                tmin: $row_lanes(&tmin),
            }
        }};
    }
    // Packets over one or two large triangles are stopped by the same triangles
    // as the last packet: tested first, they may leave nothing to traverse.
    let mut stoppers = Stoppers::NONE;
    let hint = if ANY { STOPPERS.get() } else { Stoppers::NONE };
    // Reports the packet's hits, and for any hit leaves its stoppers as the thread's hint.
    macro_rules! finish {
        () => {{
            let mut m = found;
            while m != 0 {
                let k = m.trailing_zeros() as usize;
                m &= m - 1;
                if ANY {
                    any[k] = true;
                    continue;
                }
                let (r, l) = (k / 8, k % 8);
                let nearest = Nearest {
                    t: search.near_t.0[r][l],
                    slot: search.near_slot.0[r][l].to_bits(),
                };
                // SAFETY: ray `k`'s weights were written with its `found` bit.
                let [b0, b1, b2] = search
                    .b
                    .each_ref()
                    .map(|row| unsafe { (*row.as_ptr()).0[r][l] });
                closest(
                    k,
                    nearest,
                    TriangleHit {
                        t: nearest.t,
                        b0,
                        b1,
                        b2,
                    },
                );
            }
            if ANY {
                STOPPERS.set(if found == 0 { hint } else { stoppers.hint() });
                visits.stopped = found.count_ones();
            }
            return Some(visits);
        }};
    }
    for &slot in &hint.slots[..hint.len] {
        // A hint may come from another tree: any of this tree's triangles will do.
        let (b, l) = ((slot / BLOCK as u32) as usize, slot as usize % BLOCK);
        let Some(block) = blocks.get(b) else {
            continue;
        };
        // The triangle against the rays of row `$r` (and `$r + 1`: `$all` has a bit per
        // lane) still searching, as `row_tests` below tests a leaf's.
        macro_rules! hint_row {
            ($r:expr, $all:expr, $row_lanes:ident, $test:path, $fold:ident) => {{
                let r = $r;
                let searching = !(found >> (r * 8)) as u32 & $all;
                if searching != 0 {
                    let row = row_lanes!(r, $row_lanes);
                    // SAFETY: the width's features are enabled where `trace` inlines;
                    // `l < BLOCK`.
                    let (mask, row_hits) =
                        unsafe { $test(block, l, &row, $row_lanes(&search.t_tri)) };
                    if mask & searching != 0 {
                        // SAFETY: as above.
                        let kept =
                            unsafe { $fold::<ANY>(search, r, mask & searching, &row_hits, slot) };
                        found |= u64::from(kept) << (r * 8);
                        live -= kept.count_ones() as usize;
                        if kept != 0 {
                            stoppers.add(slot);
                        }
                    }
                }
            }};
        }
        if WIDE {
            for (pair, &shared) in shared_pairs.iter().enumerate() {
                let r = 2 * pair;
                // SAFETY: as for the row tests below.
                let pair_lanes = |rows: &Rows| unsafe { _mm512_load_ps(rows.0[r].as_ptr()) };
                if shared {
                    hint_row!(r, 0xffff, pair_lanes, simd512::row_test, fold_row_hits16);
                }
            }
        } else {
            for (r, &shared) in shared_axes.iter().enumerate() {
                // SAFETY: rows are 32-byte aligned arrays of eight floats.
                let lane = |rows: &Rows| unsafe { _mm256_load_ps(rows.0[r].as_ptr()) };
                if shared {
                    hint_row!(r, 0xff, lane, row_test, fold_row_hits8);
                }
            }
        }
    }
    if ANY && found != 0 {
        if live == 0 {
            finish!();
        }
        // SAFETY: AVX2 is enabled where `trace` inlines.
        packet_tmax = unsafe { widest_horizon(&search.t_box) };
        node_tmax = packet.node_tmax::<SHIFTED>(packet_tmax);
    }

    let mut stack = [const { MaybeUninit::<u64>::uninit() }; STACK];
    let mut sp = 0usize;
    let mut current = 0u32;
    loop {
        if current & LEAF == 0 {
            let node = &nodes[current as usize];
            let planes = node.planes.as_ptr().cast::<f32>();
            // SAFETY: plane offsets are below 6 × 8 floats of a 64-byte aligned node.
            let load = |offset: usize| unsafe { _mm256_load_ps(planes.add(offset)) };
            // SAFETY: AVX2 is enabled where `trace` inlines.
            let (mask, enter) =
                unsafe { packet.enters::<SHIFTED>(near.map(load), far.map(load), node_tmax) };
            if mask != 0 {
                let mut entries = [0f32; WIDTH];
                // SAFETY: `entries` holds eight floats.
                unsafe { _mm256_storeu_ps(entries.as_mut_ptr(), enter) };
                // Every entered child onto the stack, farthest first; leaves as their
                // parent and slot, so that their box can be read when they are reached.
                // Any-hit packets go nearest first too: a packet's rays then meet the
                // surfaces facing them first and leave it sooner (DEVELOPERS.md).
                let base = sp;
                let mut m = mask;
                while m != 0 {
                    let i = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let child = node.children[i];
                    // A packet visits nearly every child it enters, so the child's memory
                    // is asked for now and arrives while the nearer children are traced.
                    prefetch_child(nodes, blocks, child);
                    let reference = if child & LEAF == 0 {
                        child
                    } else {
                        leaf_entry(current, i)
                    };
                    push_sorted(&mut stack, base, &mut sp, pack(entries[i], reference));
                }
            }
        } else {
            // A leaf: its box against every ray, then each entering ray's own triangle tests.
            let (parent, slot) = leaf_parent(current);
            let node = &nodes[parent];
            let planes = node.planes.as_ptr().cast::<f32>();
            let (first, count) = leaf_range(node.children[slot]);
            let mut improved = false;
            visits.leaves += 1;
            // The leaf's triangles no ray can hit, four bits per block: looked for, once the
            // box is tested, only where enough rows will test them together
            // (`CULL_FROM_PAIRS`).
            let leaf_missed: u64;
            macro_rules! look_for_missed {
                ($worth:expr) => {
                    leaf_missed = match &cull {
                        // SAFETY: AVX2 is enabled where `trace` inlines.
                        Some(cull) if $worth => unsafe {
                            cull.missed_in(&blocks[first as usize..(first + count) as usize])
                        },
                        _ => 0,
                    }
                };
            }
            let entries_before = visits.entries;

            // Each of the leaf's triangles against the rays `8 · $row + i` of `$hits` at
            // once, by `$test` over the rays' constants in `$row_lanes` (which share the
            // axes of ray `8 · $row`), whose hits `$fold` takes into `search`: kept if
            // nearest (closest hit), or ending the rays' search (any hit, which also
            // clears their bits in `$hits`, and stops when none is left).
            macro_rules! row_tests {
                ($row:expr, $hits:ident, $row_lanes:ident, $test:path, $fold:ident) => {{
                    let row = row_lanes!($row, $row_lanes);
                    'blocks: for b in first..first + count {
                        let block = &blocks[b as usize];
                        for l in 0..BLOCK {
                            if ANY && $hits == 0 {
                                break 'blocks;
                            }
                            if leaf_missed >> ((b - first) as usize * BLOCK + l) & 1 != 0 {
                                continue;
                            }
                            // The last block repeats its last triangle in unused lanes.
                            if l > 0 && block.ids[l] == block.ids[l - 1] {
                                break;
                            }
                            // SAFETY: the width's features are enabled where `trace` inlines.
                            let (mask, row_hits) =
                                unsafe { $test(block, l, &row, $row_lanes(&search.t_tri)) };
                            if mask & $hits == 0 {
                                continue;
                            }
                            let slot = b * BLOCK as u32 + l as u32;
                            // SAFETY: as above.
                            let kept = unsafe {
                                $fold::<ANY>(search, $row, mask & $hits, &row_hits, slot)
                            };
                            if kept != 0 {
                                found |= u64::from(kept) << ($row * 8);
                                improved = true;
                                if ANY {
                                    $hits &= !kept;
                                    live -= kept.count_ones() as usize;
                                    stoppers.add(slot);
                                }
                            }
                        }
                    }
                }};
            }
            // The triangles against the rays of row `$r` that entered the box (`$hits`):
            // each triangle against the row at once where enough of it entered, otherwise
            // each ray against the blocks (two at a time, eight triangles per instruction, as
            // a single ray tests them).
            macro_rules! row_triangles {
                ($r:expr, $hits:expr) => {{
                    let r: usize = $r;
                    let mut hits: u32 = $hits;
                    if hits.count_ones() >= ROW_TEST_FROM && shared_axes[r] {
                        // SAFETY: rows are 32-byte aligned arrays of eight floats.
                        let lane = |rows: &Rows| unsafe { _mm256_load_ps(rows.0[r].as_ptr()) };
                        row_tests!(r, hits, lane, row_test, fold_row_hits8);
                    } else {
                        while hits != 0 {
                            let k = r * 8 + hits.trailing_zeros() as usize;
                            hits &= hits - 1;
                            // Ray `k`'s constants in every lane of a block test, from its rows,
                            // four lanes wide for one block and eight for two.
                            let l = k % 8;
                            let [kx, ky, kz] = axes[k];
                            macro_rules! ray_lanes {
                                ($set1:ident) => {
                                    TriLanes {
                                        kx,
                                        ky,
                                        kz,
                                        origin_k: [kx, ky, kz].map(|a| $set1(origin[a].0[r][l])),
                                        sx: $set1(shear_rows[0].0[r][l]),
                                        sy: $set1(shear_rows[1].0[r][l]),
                                        sz: $set1(shear_rows[2].0[r][l]),
                                        tmin: $set1(tmin.0[r][l]),
                                    }
                                };
                            }
                            // SAFETY (here and below): AVX2 is enabled where `trace` inlines.
                            let (set4, set8) = (
                                |x: f32| unsafe { _mm_set1_ps(x) },
                                |x: f32| unsafe { _mm256_set1_ps(x) },
                            );
                            let (tri, tri8) = (ray_lanes!(set4), ray_lanes!(set8));
                            // The leaf's blocks two at a time (as `simd::closest` tests
                            // them), then the last alone if their number is odd.
                            let end = first + count;
                            let mut b = first;
                            let mut nearest = Nearest {
                                t: search.near_t.0[r][l],
                                slot: search.near_slot.0[r][l].to_bits(),
                            };
                            let mut hit = None;
                            while b < end {
                                // Blocks whose every triangle no ray can hit are skipped.
                                let tested = if b + 1 < end { 0xff } else { 0xf };
                                if leaf_missed >> ((b - first) as usize * BLOCK) & tested == tested
                                {
                                    b += 2;
                                    continue;
                                }
                                let limit = t_triangle::<ANY>(nearest);
                                let (mask, kept) = if b + 1 < end {
                                    let (mask, lanes) = unsafe {
                                        block_pair_test(blocks, b as usize, &tri8, set8(limit))
                                    };
                                    let keep = mask != 0 && !ANY;
                                    (
                                        mask,
                                        keep && unsafe {
                                            lanes.keep_nearest(mask, b, &mut nearest, &mut hit)
                                        },
                                    )
                                } else {
                                    let (mask, lanes) = unsafe {
                                        block_test(&blocks[b as usize], &tri, set4(limit))
                                    };
                                    let keep = mask != 0 && !ANY;
                                    (
                                        mask,
                                        keep && lanes.keep_nearest(mask, b, &mut nearest, &mut hit),
                                    )
                                };
                                b += 2;
                                if mask == 0 {
                                    continue;
                                }
                                if ANY {
                                    found |= 1 << k;
                                    stoppers.spoiled = true;
                                    search.t_box.0[r][l] = f32::NEG_INFINITY;
                                    search.t_tri.0[r][l] = f32::NEG_INFINITY;
                                    live -= 1;
                                    improved = true;
                                    break;
                                }
                                if kept {
                                    search.t_box.0[r][l] = nearest.horizon();
                                    search.t_tri.0[r][l] = t_triangle::<ANY>(nearest);
                                    improved = true;
                                }
                            }
                            if let Some(hit) = hit {
                                found |= 1 << k;
                                search.near_t.0[r][l] = nearest.t;
                                search.near_slot.0[r][l] = f32::from_bits(nearest.slot);
                                let weights = [hit.b0, hit.b1, hit.b2];
                                for (row, weight) in search.b.iter_mut().zip(weights) {
                                    // SAFETY: a place of the row, written through its pointer.
                                    unsafe { (*row.as_mut_ptr()).0[r][l] = weight };
                                }
                            }
                        }
                    }
                }};
            }

            if WIDE {
                // Two rows at a time: the box against sixteen rays, then each triangle
                // against both rows at once where enough of them entered and they share
                // their axes, otherwise row by row. The box goes first against every pair
                // (a pair's tests change only its own rays' bounds), so that the triangles
                // none can hit are looked for only where enough pairs will test them.
                let entered: [u32; ROWS / 2] = std::array::from_fn(|pair| {
                    let r = 2 * pair;
                    // SAFETY: rows are 64-byte aligned, so rows `r` and `r + 1` are sixteen
                    // floats on a 64-byte boundary; AVX-512F is enabled where `trace`
                    // inlines.
                    let pair_lanes = |rows: &Rows| unsafe { _mm512_load_ps(rows.0[r].as_ptr()) };
                    let group = GroupLanes::read([origin, inv, inv_far], (near, far), pair_lanes);
                    // SAFETY: plane offsets plus the slot stay within the node's 6 × 8
                    // floats; AVX-512F is enabled where `trace` inlines.
                    unsafe {
                        let (tmin, tmax) = (pair_lanes(tmin), pair_lanes(&search.t_box));
                        simd512::leaf_box_test(&group, planes, slot, tmin, tmax)
                    }
                });
                let row_tested = (0..ROWS / 2)
                    .filter(|&p| entered[p].count_ones() >= WIDE_ROW_TEST_FROM && shared_pairs[p])
                    .count();
                look_for_missed!(row_tested >= CULL_FROM_PAIRS);
                for (pair, &shared) in shared_pairs.iter().enumerate() {
                    let r = 2 * pair;
                    // SAFETY: as above.
                    let pair_lanes = |rows: &Rows| unsafe { _mm512_load_ps(rows.0[r].as_ptr()) };
                    let mut hits = entered[pair];
                    visits.entries += hits.count_ones();
                    if hits.count_ones() >= WIDE_ROW_TEST_FROM && shared {
                        row_tests!(r, hits, pair_lanes, simd512::row_test, fold_row_hits16);
                    } else {
                        row_triangles!(r, hits & 0xff);
                        row_triangles!(r + 1, hits >> 8);
                    }
                }
            } else {
                // The box first against every row, as for pairs above.
                let entered: [u32; ROWS] = std::array::from_fn(|r| {
                    // SAFETY: rows are 32-byte aligned arrays of eight floats.
                    let lane = |rows: &Rows| unsafe { _mm256_load_ps(rows.0[r].as_ptr()) };
                    let group = GroupLanes::read([origin, inv, inv_far], (near, far), lane);
                    // The single-ray test, the leaf's box against eight rays.
                    // SAFETY: plane offsets plus the slot stay within the node's 6 × 8 floats;
                    // AVX2 is enabled where `trace` inlines.
                    unsafe {
                        let (_, entered) = slab_test! { &group, planes, slot, lane(tmin),
                        lane(&search.t_box), broadcast_ps, _mm256_sub_ps, _mm256_mul_ps,
                        _mm256_max_ps, _mm256_min_ps, _mm256_cmp_ps };
                        _mm256_movemask_ps(entered) as u32
                    }
                });
                let row_tested = (0..ROWS)
                    .filter(|&r| entered[r].count_ones() >= ROW_TEST_FROM && shared_axes[r])
                    .count();
                look_for_missed!(row_tested >= 2 * CULL_FROM_PAIRS);
                for (r, &hits) in entered.iter().enumerate() {
                    visits.entries += hits.count_ones();
                    row_triangles!(r, hits);
                }
            }
            visits.entered += u32::from(visits.entries > entries_before);
            if visits.hopeless() {
                // Nothing is reported: the caller traces the rays another way.
                return Some(visits);
            }
            if improved {
                // SAFETY: AVX2 is enabled where `trace` inlines.
                packet_tmax = unsafe { widest_horizon(&search.t_box) };
                node_tmax = packet.node_tmax::<SHIFTED>(packet_tmax);
            }
        }
        // The next entry that some ray may still need.
        // SAFETY: every slot below `sp` was written above.
        let next = if ANY && live == 0 {
            None
        } else {
            unsafe { pop_within(&stack, &mut sp, packet_tmax) }
        };
        let Some(next) = next else {
            finish!();
        };
        current = next;
    }
}

/// The smallest and the largest of a packet's values in `rows` (lanes past its rays
/// repeat its last ray).
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn row_range(rows: &Rows) -> (f32, f32) {
    // SAFETY: AVX2 is enabled in the caller; rows are 32-byte aligned arrays of eight floats.
    unsafe {
        let first = _mm256_load_ps(rows.0[0].as_ptr());
        let (mut lo, mut hi) = (first, first);
        for row in &rows.0[1..] {
            let x = _mm256_load_ps(row.as_ptr());
            (lo, hi) = (_mm256_min_ps(lo, x), _mm256_max_ps(hi, x));
        }
        let (lo, hi) = (lanes8(lo), lanes8(hi));
        (
            lo.into_iter().fold(f32::INFINITY, f32::min),
            hi.into_iter().fold(f32::NEG_INFINITY, f32::max),
        )
    }
}

/// The largest horizon in `t_box`, which holds each live ray's and −∞ elsewhere.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn widest_horizon(t_box: &Rows) -> f32 {
    // SAFETY: AVX2 is enabled in the caller; rows are 32-byte aligned arrays of eight floats.
    unsafe {
        let row = |r: usize| _mm256_load_ps(t_box.0[r].as_ptr());
        let mut widest = row(0);
        for r in 1..ROWS {
            widest = _mm256_max_ps(widest, row(r));
        }
        lanes8(widest).into_iter().fold(f32::NEG_INFINITY, f32::max)
    }
}

/// The closest-hit end of [`fold_row_hits8`] and [`fold_row_hits16`]: writes the hit
/// values of the kept `$lanes` into `$search`'s rows through `$put` (a blend into a row)
/// and, for the weights, `$store_kept` (a masked store), with the width's division,
/// product, broadcast and `next_up`.
macro_rules! keep_in_rows {
    ($search:expr, $hits:expr, $slot_lanes:expr, $lanes:expr, $put:ident, $store_kept:ident,
     $div:ident, $mul:ident, $set1:ident, $next_up:ident) => {{
        let (search, hits, lanes) = ($search, $hits, $lanes);
        $put(&mut search.near_t, hits.t, lanes);
        $put(&mut search.near_slot, $slot_lanes, lanes);
        for (row, weight) in search.b.iter_mut().zip([hits.u, hits.v, hits.w]) {
            $store_kept(row.as_mut_ptr(), $div(weight, hits.det), lanes);
        }
        $put(&mut search.t_box, $mul(hits.t, $set1(SEARCH_MARGIN)), lanes);
        $put(&mut search.t_tri, $next_up(hits.t), lanes);
    }};
}

/// Takes the hits in lanes `mask` of a row test (of the triangle in `slot` against row
/// `r`, its values in `hits`) into `search`. Closest hit keeps each that improves on its
/// ray's [`Nearest`] (nearer, or as near from a lower slot), with its weights, horizon and
/// triangle bound; any hit ends each ray's search. Returns the lanes taken. Lane for lane
/// the same IEEE operations as [`Nearest::improves`], [`Nearest::horizon`],
/// [`t_triangle`] and [`Hits::hit_in`], so the results are theirs.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn fold_row_hits8<const ANY: bool>(
    search: &mut Search,
    r: usize,
    mask: u32,
    hits: &Hits<__m256>,
    slot: u32,
) -> u32 {
    // SAFETY: AVX2 is enabled in the caller; rows are 32-byte aligned arrays of eight
    // floats.
    unsafe {
        let load = |rows: &Rows| _mm256_load_ps(rows.0[r].as_ptr());
        let lanes_of = |bits: u32| {
            let each = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let set = _mm256_and_si256(_mm256_set1_epi32(bits as i32), each);
            _mm256_castsi256_ps(_mm256_cmpeq_epi32(set, each))
        };
        let put = |rows: &mut Rows, x: __m256, lanes: __m256| {
            let x = _mm256_blendv_ps(load(rows), x, lanes);
            _mm256_store_ps(rows.0[r].as_mut_ptr(), x);
        };
        if ANY {
            let (done, lanes) = (_mm256_set1_ps(f32::NEG_INFINITY), lanes_of(mask));
            put(&mut search.t_box, done, lanes);
            put(&mut search.t_tri, done, lanes);
            return mask;
        }
        let nearest_t = load(&search.near_t);
        let nearest_slot = _mm256_castps_si256(load(&search.near_slot));
        let slot_lanes = _mm256_set1_epi32(slot as i32);
        // `slot < nearest.slot`, unsigned: compared signed with the top bits flipped.
        let flip = _mm256_set1_epi32(i32::MIN);
        let lower_slot = _mm256_cmpgt_epi32(
            _mm256_xor_si256(nearest_slot, flip),
            _mm256_xor_si256(slot_lanes, flip),
        );
        let improves = _mm256_or_ps(
            _mm256_cmp_ps::<_CMP_LT_OQ>(hits.t, nearest_t),
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_EQ_OQ>(hits.t, nearest_t),
                _mm256_castsi256_ps(lower_slot),
            ),
        );
        let kept = _mm256_movemask_ps(improves) as u32 & mask;
        if kept == 0 {
            return 0;
        }
        let slot_lanes = _mm256_castsi256_ps(slot_lanes);
        let store_kept = |rows: *mut Rows, x: __m256, lanes: __m256| {
            let place = (&raw mut (*rows).0[r]).cast::<f32>();
            _mm256_maskstore_ps(place, _mm256_castps_si256(lanes), x);
        };
        keep_in_rows! { search, hits, slot_lanes, lanes_of(kept), put, store_kept,
        _mm256_div_ps, _mm256_mul_ps, _mm256_set1_ps, next_up8 }
        kept
    }
}

/// [`fold_row_hits8`] for a sixteen-lane row test, of rows `r` and `r + 1`.
///
/// # Safety
/// Only from a function with AVX-512F enabled.
#[inline(always)]
unsafe fn fold_row_hits16<const ANY: bool>(
    search: &mut Search,
    r: usize,
    mask: u32,
    hits: &Hits<__m512>,
    slot: u32,
) -> u32 {
    // SAFETY: AVX-512F is enabled in the caller; rows are 64-byte aligned, so rows `r`
    // and `r + 1` (`r` even) are sixteen floats on a 64-byte boundary.
    unsafe {
        let load = |rows: &Rows| _mm512_load_ps(rows.0[r].as_ptr());
        let put = |rows: &mut Rows, x: __m512, lanes: __mmask16| {
            let x = _mm512_mask_blend_ps(lanes, load(rows), x);
            _mm512_store_ps(rows.0[r].as_mut_ptr(), x);
        };
        if ANY {
            let done = _mm512_set1_ps(f32::NEG_INFINITY);
            put(&mut search.t_box, done, mask as __mmask16);
            put(&mut search.t_tri, done, mask as __mmask16);
            return mask;
        }
        let nearest_t = load(&search.near_t);
        let nearest_slot = _mm512_castps_si512(load(&search.near_slot));
        let slot_lanes = _mm512_set1_epi32(slot as i32);
        let improves = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(hits.t, nearest_t)
            | (_mm512_cmp_ps_mask::<_CMP_EQ_OQ>(hits.t, nearest_t)
                & _mm512_cmplt_epu32_mask(slot_lanes, nearest_slot));
        let kept = u32::from(improves) & mask;
        if kept == 0 {
            return 0;
        }
        let slot_lanes = _mm512_castsi512_ps(slot_lanes);
        let store_kept = |rows: *mut Rows, x: __m512, lanes: __mmask16| {
            _mm512_mask_store_ps((&raw mut (*rows).0[r]).cast::<f32>(), lanes, x);
        };
        keep_in_rows! { search, hits, slot_lanes, kept as __mmask16, put, store_kept,
        _mm512_div_ps, _mm512_mul_ps, _mm512_set1_ps, next_up16 }
        kept
    }
}

/// `f32::next_up` of each lane of `x` that is neither NaN nor +∞: one step up in the
/// integers above zero, one step down below it, and the least subnormal from ±0.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn next_up8(x: __m256) -> __m256 {
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        let zero = _mm256_setzero_ps();
        // All ones (−1) where true.
        let above = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(x, zero));
        let below = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LT_OQ>(x, zero));
        let bits = _mm256_castps_si256(x);
        let stepped = _mm256_add_epi32(_mm256_sub_epi32(bits, above), below);
        let least = _mm256_castsi256_ps(_mm256_set1_epi32(1));
        let is_zero = _mm256_cmp_ps::<_CMP_EQ_OQ>(x, zero);
        _mm256_blendv_ps(_mm256_castsi256_ps(stepped), least, is_zero)
    }
}

/// [`next_up8`] in sixteen lanes.
///
/// # Safety
/// Only from a function with AVX-512F enabled.
#[inline(always)]
unsafe fn next_up16(x: __m512) -> __m512 {
    // SAFETY: AVX-512F is enabled in the caller.
    unsafe {
        let zero = _mm512_setzero_ps();
        let one = _mm512_set1_epi32(1);
        let bits = _mm512_castps_si512(x);
        let above = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(x, zero);
        let below = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(x, zero);
        // The least subnormal (bits 1) where neither.
        let stepped = _mm512_mask_add_epi32(one, above, bits, one);
        _mm512_castsi512_ps(_mm512_mask_sub_epi32(stepped, below, bits, one))
    }
}

/// A ray's origin and direction as float64 lanes x, y, z; the fourth lane holds the
/// ray's next float, for callers to leave out.
///
/// # Safety
/// Only from a function with AVX enabled.
#[inline(always)]
unsafe fn origin_and_direction(ray: &TriangleRay) -> (__m256d, __m256d) {
    let floats = (ray as *const TriangleRay).cast::<f32>();
    // SAFETY: a `TriangleRay` is eight floats (origin, direction, tmin, tmax), so both
    // loads of four stay inside it; AVX is enabled in the caller.
    unsafe {
        (
            _mm256_cvtps_pd(_mm_loadu_ps(floats)),
            _mm256_cvtps_pd(_mm_loadu_ps(floats.add(3))),
        )
    }
}

/// How much a packet bounded from its waist widens each end of its node test, per unit
/// of distance: 64u, u = 2⁻²⁴ (see [`PacketBounds::enters`]).
const SHIFTED_SLACK: f32 = 32.0 * f32::EPSILON;

/// A packet's ranges over its rays, per axis `(smallest, largest)`: origin, reciprocal
/// direction for near planes and for far ones; the smallest `tmin` and the largest
/// horizon; and the octant its directions share (1 where negative).
struct PacketBounds {
    octant: [usize; 3],
    /// The range of each ray's point at distance `shift` (its origin when `shift` is 0).
    origin: [(f32, f32); 3],
    inv: [(f32, f32); 3],
    inv_far: [(f32, f32); 3],
    /// The smallest `tmin`, less `shift` (rounded down).
    tmin: f32,
    horizon: f32,
    /// Where the rays come closest together, when their origins differ (a lens): the node
    /// test bounds distances from there, `t − shift`. Zero for a common origin.
    shift: f32,
}

impl PacketBounds {
    /// The ranges from one pass over the rays, before their per-ray set-up, or `None`
    /// when the rays' direction signs differ, a value is NaN, or an origin or direction
    /// is infinite (they are then traced one by one). The reciprocal of a direction is monotone within a sign, so `1/d` at the
    /// ends of `d`'s range is exactly the range of the rays' own reciprocals.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn of(rays: &[TriangleRay]) -> Option<PacketBounds> {
        // SAFETY: AVX2 is enabled in the caller; a `TriangleRay` is eight floats
        // (`#[repr(C)]`): origin, direction, tmin, tmax.
        unsafe {
            let (mut lo, mut hi) = (
                _mm256_set1_ps(f32::INFINITY),
                _mm256_set1_ps(f32::NEG_INFINITY),
            );
            let (mut all, mut some) = (
                _mm256_castsi256_ps(_mm256_set1_epi32(-1)),
                _mm256_setzero_ps(),
            );
            // NaN anywhere, and (`x − x` is NaN) infinite origins and directions.
            let (mut nan, mut infinite) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            for ray in rays {
                let v = _mm256_loadu_ps((ray as *const TriangleRay).cast::<f32>());
                (lo, hi) = (_mm256_min_ps(lo, v), _mm256_max_ps(hi, v));
                (all, some) = (_mm256_and_ps(all, v), _mm256_or_ps(some, v));
                nan = _mm256_or_ps(nan, _mm256_cmp_ps::<_CMP_UNORD_Q>(v, v));
                let zero = _mm256_sub_ps(v, v);
                infinite = _mm256_or_ps(infinite, _mm256_cmp_ps::<_CMP_UNORD_Q>(zero, zero));
            }
            // Sign bits of the direction (lanes 3–5): set in every ray, or in none.
            let (all, some) = (
                _mm256_movemask_ps(all) >> 3 & 7,
                _mm256_movemask_ps(some) >> 3 & 7,
            );
            let not_finite = _mm256_movemask_ps(nan) | _mm256_movemask_ps(infinite) & 0x3f;
            if all != some || not_finite != 0 {
                return None;
            }
            let mut l = [0f32; 8];
            let mut h = [0f32; 8];
            _mm256_storeu_ps(l.as_mut_ptr(), lo);
            _mm256_storeu_ps(h.as_mut_ptr(), hi);
            // 1/d decreases with d within a sign: the smallest reciprocal is the largest d's.
            let one = _mm_set1_ps(1.0);
            let inv_lo = _mm_div_ps(one, _mm_setr_ps(h[3], h[4], h[5], 1.0));
            let inv_hi = _mm_div_ps(one, _mm_setr_ps(l[3], l[4], l[5], 1.0));
            let scale = _mm_set1_ps(<f32 as crate::bvh::Scalar>::EXIT_SCALE);
            let [inv_lo, inv_hi, far_lo, far_hi] = [
                inv_lo,
                inv_hi,
                _mm_mul_ps(inv_lo, scale),
                _mm_mul_ps(inv_hi, scale),
            ]
            .map(lanes4);
            let mut bounds = PacketBounds {
                octant: [0, 1, 2].map(|a| (all >> a & 1) as usize),
                origin: [0, 1, 2].map(|a| (l[a], h[a])),
                inv: [0, 1, 2].map(|a| (inv_lo[a], inv_hi[a])),
                inv_far: [0, 1, 2].map(|a| (far_lo[a], far_hi[a])),
                tmin: l[6],
                horizon: Nearest::before(h[7]).horizon(),
                shift: 0.0,
            };
            if (0..3).any(|a| l[a] != h[a]) {
                bounds.shift_to_waist(rays);
            }
            Some(bounds)
        }
    }

    /// Moves the packet's reference points from the rays' origins to where the rays come
    /// closest together (their waist: the focus plane, for a lens's rays). Spread over a
    /// lens, the origins make the node test's bounds several times wider than the rays'
    /// own spread near the surfaces they meet; from the waist, about as narrow as a
    /// pinhole's. The distance `s` minimizes the rays' spread (least squares, any `s`
    /// would be correct); each ray's point `o + s·d` is computed in float64 (`s · d` is
    /// exact, the sum within half a unit in the last place) and the ranges rounded
    /// outward, so they hold the exact points. (AVX2 only: called from [`PacketBounds::of`].)
    #[target_feature(enable = "avx2")]
    fn shift_to_waist(&mut self, rays: &[TriangleRay]) {
        // Sums of differences from the first ray, which do not cancel.
        // SAFETY: AVX2 is enabled here.
        let (o0, d0) = unsafe { origin_and_direction(&rays[0]) };
        let zero = _mm256_setzero_pd();
        let (mut sum_o, mut sum_d, mut sum_od, mut sum_dd) = (zero, zero, zero, zero);
        for ray in rays {
            // SAFETY: as above.
            let (o, d) = unsafe { origin_and_direction(ray) };
            let (o, d) = (_mm256_sub_pd(o, o0), _mm256_sub_pd(d, d0));
            sum_o = _mm256_add_pd(sum_o, o);
            sum_d = _mm256_add_pd(sum_d, d);
            sum_od = _mm256_add_pd(sum_od, _mm256_mul_pd(o, d));
            sum_dd = _mm256_add_pd(sum_dd, _mm256_mul_pd(d, d));
        }
        let count = _mm256_set1_pd(rays.len() as f64);
        // Per axis, the covariance of origin and direction and the variance of direction
        // (times the count).
        // SAFETY: AVX2 is enabled here.
        let (covariance, variance) = unsafe {
            (
                lanes3(_mm256_sub_pd(
                    sum_od,
                    _mm256_div_pd(_mm256_mul_pd(sum_o, sum_d), count),
                )),
                lanes3(_mm256_sub_pd(
                    sum_dd,
                    _mm256_div_pd(_mm256_mul_pd(sum_d, sum_d), count),
                )),
            )
        };
        let s = (-covariance.iter().sum::<f64>() / variance.iter().sum::<f64>()) as f32;
        // Only ahead of the origins: rays that spread from the start gain nothing.
        if !(s > 0.0 && s.is_finite()) {
            return;
        }
        let distance = _mm256_set1_pd(f64::from(s));
        let (mut lo, mut hi) = (
            _mm256_set1_pd(f64::INFINITY),
            _mm256_set1_pd(f64::NEG_INFINITY),
        );
        for ray in rays {
            // SAFETY: as above.
            let (o, d) = unsafe { origin_and_direction(ray) };
            let point = _mm256_add_pd(o, _mm256_mul_pd(distance, d));
            (lo, hi) = (_mm256_min_pd(lo, point), _mm256_max_pd(hi, point));
        }
        // SAFETY: as above.
        let (lo, hi) = unsafe { (lanes3(lo), lanes3(hi)) };
        self.origin =
            [0, 1, 2].map(|a| (crate::bvh::f32_below(lo[a]), crate::bvh::f32_above(hi[a])));
        self.tmin = crate::bvh::f32_below(f64::from(self.tmin) - f64::from(s));
        self.shift = s;
    }

    /// The node test's `tmax` for rays that search up to `horizon`: `horizon − shift`,
    /// rounded up.
    #[inline(always)]
    fn node_tmax<const SHIFTED: bool>(&self, horizon: f32) -> f32 {
        if !SHIFTED {
            horizon
        } else {
            crate::bvh::f32_above(f64::from(horizon) - f64::from(self.shift))
        }
    }

    /// Whether the packet surely misses `bounds` (the box around the whole tree), by the
    /// node test's corner bounds, which are monotone in the planes: a packet that enters
    /// some child of the root passes. Sky regions of an image end here, where they paid
    /// the per-ray set-up before.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn misses(&self, bounds: &Bounds<f32>) -> bool {
        let side = |a: usize, upper: bool| {
            let value = if (self.octant[a] == 1) == upper {
                bounds.min[a]
            } else {
                bounds.max[a]
            };
            // SAFETY: AVX2 is enabled in the caller.
            unsafe { _mm256_set1_ps(value) }
        };
        let (near, far) = (
            [0, 1, 2].map(|a| side(a, false)),
            [0, 1, 2].map(|a| side(a, true)),
        );
        // SAFETY: as above.
        unsafe { self.enters_from(near, far, self.horizon) }.0 == 0
    }

    /// [`PacketBounds::enters`] for rays that search up to `horizon`, in the frame the
    /// packet was bounded in. The traversal picks the frame once per packet instead.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn enters_from(
        &self,
        near: [__m256; 3],
        far: [__m256; 3],
        horizon: f32,
    ) -> (u32, __m256) {
        // SAFETY: as required of the caller.
        unsafe {
            if self.shift == 0.0 {
                self.enters::<false>(near, far, horizon)
            } else {
                self.enters::<true>(near, far, self.node_tmax::<true>(horizon))
            }
        }
    }

    /// Which of eight boxes, given by their near and far planes per axis, some ray of the
    /// packet may enter with `tmin <= t <= tmax` (a lane mask), and the packet's lower
    /// bound on the entry distance into each. `tmax` is [`PacketBounds::node_tmax`]'s;
    /// `SHIFTED` when [`PacketBounds::shift`] is not 0.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn enters<const SHIFTED: bool>(
        &self,
        near: [__m256; 3],
        far: [__m256; 3],
        tmax: f32,
    ) -> (u32, __m256) {
        // SAFETY: AVX2 is enabled in the caller.
        unsafe {
            let mut enter = _mm256_set1_ps(self.tmin);
            let mut exit = _mm256_set1_ps(tmax);
            for a in 0..3 {
                let (o, i, f) = (self.origin[a], self.inv[a], self.inv_far[a]);
                enter = _mm256_max_ps(corners(near[a], o, i, Bound::Lower), enter);
                exit = _mm256_min_ps(corners(far[a], o, f, Bound::Upper), exit);
            }
            if SHIFTED {
                // The packet must admit every box a ray's own test admits, and that test
                // rounds in proportion to distances from the ray's origin, `|t| <= |t'| +
                // shift`: entries low by up to 3u|t| (u = 2⁻²⁴), exits high by up to 21u|t|
                // (`EXIT_SCALE` and rounding). From the waist, `t'` is within 3u|t'|, and an
                // exit behind the waist up to 19u|t'| low (its scaled reciprocal narrows a
                // negative `t'`). Widening both ends by 64u(|t'| + shift) covers each case,
                // behind the origins too. The entry is then returned as a distance from
                // the origins, `t' + shift`, rounded down by 64u of it.
                let sign = _mm256_set1_ps(-0.0);
                let shift = _mm256_set1_ps(self.shift);
                let slack = |x: __m256, from_origins: f32| {
                    let size =
                        _mm256_add_ps(_mm256_andnot_ps(sign, x), _mm256_set1_ps(from_origins));
                    _mm256_mul_ps(size, _mm256_set1_ps(SHIFTED_SLACK))
                };
                enter = _mm256_sub_ps(enter, slack(enter, self.shift));
                exit = _mm256_add_ps(exit, slack(exit, self.shift));
                let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(enter, exit)) as u32;
                let from_origin = _mm256_add_ps(enter, shift);
                return (mask, _mm256_sub_ps(from_origin, slack(from_origin, 0.0)));
            }
            let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(enter, exit)) as u32;
            (mask, enter)
        }
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Bound {
    Lower,
    Upper,
}

/// The smallest (or largest) of `(plane − o) · i` over the packet's ranges of `o` and `i`:
/// the extreme of the four corners. A NaN corner (`0 · ∞`: a ray starting on the plane
/// it runs along) stands for a ray whose own test ignores this axis, so the bound becomes
/// unbounded. Written once for both widths: the intrinsics' suffix (`ps` for float32,
/// `pd` for float64) is the macro's choice.
macro_rules! corner_bound {
    ($plane:expr, $o:expr, $i:expr, $bound:expr,
     $set1:ident, $sub:ident, $mul:ident, $min:ident, $max:ident, $cmp:ident, $or:ident,
     $blendv:ident) => {{
        let (plane, (o_lo, o_hi), (i_lo, i_hi)) = ($plane, $o, $i);
        let x_lo = $sub(plane, $set1(o_hi));
        let x_hi = $sub(plane, $set1(o_lo));
        let (i_lo, i_hi) = ($set1(i_lo), $set1(i_hi));
        let c = [
            $mul(x_lo, i_lo),
            $mul(x_lo, i_hi),
            $mul(x_hi, i_lo),
            $mul(x_hi, i_hi),
        ];
        let nan = $or(
            $cmp::<_CMP_UNORD_Q>(c[0], c[1]),
            $cmp::<_CMP_UNORD_Q>(c[2], c[3]),
        );
        let (extreme, unbounded) = match $bound {
            Bound::Lower => ($min($min(c[0], c[1]), $min(c[2], c[3])), f64::NEG_INFINITY),
            Bound::Upper => ($max($max(c[0], c[1]), $max(c[2], c[3])), f64::INFINITY),
        };
        $blendv(extreme, $set1(unbounded as _), nan)
    }};
}
pub(crate) use corner_bound;

/// [`corner_bound!`] for eight float32 children.
#[inline(always)]
fn corners(plane: __m256, o: (f32, f32), i: (f32, f32), bound: Bound) -> __m256 {
    // SAFETY: the callers have AVX2 enabled (this is inlined into them).
    unsafe {
        corner_bound!(
            plane,
            o,
            i,
            bound,
            _mm256_set1_ps,
            _mm256_sub_ps,
            _mm256_mul_ps,
            _mm256_min_ps,
            _mm256_max_ps,
            _mm256_cmp_ps,
            _mm256_or_ps,
            _mm256_blendv_ps
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_wasteful_packet_sends_the_next_groups_one_by_one_for_doubling_spells() {
        let leaves = Visits::WASTEFUL_FROM;
        let wasteful = Visits {
            leaves,
            entries: leaves / Visits::MOST_LEAVES_PER_ENTRY - 1,
            entered: 20,
            ..Visits::default()
        };
        let useful = Visits {
            leaves,
            entries: leaves / Visits::MOST_LEAVES_PER_ENTRY,
            entered: 20,
            ..Visits::default()
        };
        // Too few leaves to be wasteful, even with no ray entering them: it ends a spell.
        let few_leaves = Visits {
            leaves: Visits::WASTEFUL_FROM - 1,
            entries: 0,
            entered: 0,
            ..Visits::default()
        };
        let unjudged = Visits {
            leaves: Visits::JUDGED_FROM - 1,
            entries: 0,
            entered: 0,
            ..Visits::default()
        };
        assert!(wasteful.wasteful() && !useful.wasteful());
        assert!(!few_leaves.wasteful() && !unjudged.wasteful());
        // A packet gives up only once it has reached that many leaves, and is wasteful.
        let reached = |leaves, entries| Visits {
            leaves,
            entries,
            ..Visits::default()
        };
        let most = Visits::GIVE_UP_FROM;
        assert!(reached(most, most - 1).hopeless());
        assert!(!reached(most - 1, 0).hopeless() && !reached(most, most).hopeless());
        // Each test runs on its own thread: the pacing starts fresh.
        let spell = |tree| {
            let single = std::iter::repeat_with(|| worth_trying(tree))
                .take_while(|&packet| !packet)
                .count();
            single as u32
        };
        let trees = [
            PacedTree::Triangles,
            PacedTree::TrianglesAnyHit,
            PacedTree::Spheres,
        ];
        for tree in trees {
            assert_eq!(spell(tree), 0);
            record(tree, unjudged);
            assert_eq!(spell(tree), 0);
            for expected in [2, 4, 8, 16, 32, 64, 128, 128] {
                record(tree, wasteful);
                // The other trees' packets are still tried.
                for other in trees.into_iter().filter(|&other| other != tree) {
                    assert_eq!(spell(other), 0);
                }
                assert_eq!(spell(tree), expected);
            }
            // A useful packet ends the doubling, and so does one reaching too few leaves
            // to be wasteful; a packet reaching fewer still says nothing.
            for ends in [useful, few_leaves] {
                record(tree, ends);
                assert_eq!(spell(tree), 0);
                record(tree, wasteful);
                assert_eq!(spell(tree), SINGLE_AFTER_WASTE);
                record(tree, wasteful);
                assert_eq!(spell(tree), 2 * SINGLE_AFTER_WASTE);
            }
            record(tree, useful);
            record(tree, wasteful);
            record(tree, unjudged);
            assert_eq!(spell(tree), SINGLE_AFTER_WASTE);
        }
    }

    #[test]
    fn a_spell_goes_side_by_side_when_its_wasteful_packet_found_the_rays_scattered() {
        // 34 entries over 32 entered leaves is 1/16 more: scattered; one more entry is not.
        let visits = |entries| Visits {
            leaves: 200,
            entries,
            entered: 32,
            ..Visits::default()
        };
        let (scattered, shared) = (visits(34), visits(35));
        assert!(scattered.wasteful() && shared.wasteful());
        assert!(scattered.scattered() && !shared.scattered());
        // Rays that enter too few leaves to tell (mostly misses) are not scattered.
        for entered in [0, Visits::SCATTERED_FROM - 1] {
            let few = Visits {
                leaves: 200,
                entries: entered,
                entered,
                ..Visits::default()
            };
            assert!(few.wasteful() && !few.scattered());
        }
        // A packet across a mesh's edge: most rays miss, the others each in a leaf of
        // their own.
        for entered in [Visits::SCATTERED_FROM, 7] {
            let edge = Visits {
                leaves: 200,
                entries: entered,
                entered,
                ..Visits::default()
            };
            assert!(edge.wasteful() && edge.scattered());
        }
        // Each test runs on its own thread: the pacing starts fresh.
        let tree = PacedTree::Triangles;
        assert!(!super::scattered(tree));
        record(tree, scattered);
        assert!(!worth_trying(tree) && super::scattered(tree));
        record(tree, shared);
        assert!(!worth_trying(tree) && !super::scattered(tree));
        record(tree, scattered);
        // A useful packet ends the spell and forgets it.
        record(
            tree,
            Visits {
                entries: 400,
                ..scattered
            },
        );
        assert!(worth_trying(tree) && !super::scattered(tree));
        assert!(!super::scattered(PacedTree::Spheres));
    }

    /// An any-hit packet that stopped at least half its rays after reaching at least
    /// [`Visits::JUDGED_FROM`] leaves, fewer than 40% of them entered by a ray, sends the
    /// thread's next any-hit groups through the triangles one by one, in the same
    /// doubling spells as a wasteful packet, and never side by side (there a ray tests
    /// only its own previous block, not its neighbour's). The thread's closest-hit
    /// packets through the same triangles, and its sphere packets, are still tried.
    #[test]
    fn an_any_hit_packet_stopped_after_a_wide_search_hands_the_next_groups_to_hints() {
        let visits = |leaves, entered, stopped| Visits {
            leaves,
            // At least one ray per leaf reached: not wasteful.
            entries: 2 * leaves,
            entered,
            rays: 64,
            stopped,
        };
        // 39 entered leaves of 100 is under 40%; 40 is not. Half the rays stopped is
        // enough; one fewer is not; a closest-hit packet stops none.
        let shadow = visits(100, 39, 32);
        assert!(!shadow.wasteful() && shadow.hints_pay());
        for not in [visits(100, 40, 64), visits(100, 39, 31), visits(100, 0, 0)] {
            assert!(!not.hints_pay(), "{not:?}");
        }
        // Fewer leaves than a packet is judged from say nothing.
        let unjudged = visits(Visits::JUDGED_FROM - 1, 0, 64);
        assert!(!unjudged.hints_pay());
        // A partial packet: half of its 10 rays.
        let partial = Visits {
            rays: 10,
            ..visits(100, 10, 5)
        };
        let fewer = Visits {
            stopped: 4,
            ..partial
        };
        assert!(partial.hints_pay() && !fewer.hints_pay());
        // Each test runs on its own thread: the pacing starts fresh.
        let tree = PacedTree::TrianglesAnyHit;
        let spell = |tree| {
            std::iter::repeat_with(|| worth_trying(tree))
                .take_while(|&packet| !packet)
                .count() as u32
        };
        for expected in [2, 4, 8] {
            record(tree, shadow);
            assert!(!super::scattered(tree));
            assert_eq!(spell(PacedTree::Triangles), 0);
            assert_eq!(spell(PacedTree::Spheres), 0);
            assert_eq!(spell(tree), expected);
        }
        record(tree, unjudged);
        record(tree, shadow);
        assert_eq!(spell(tree), 16);
        // A packet that does not pay for hints ends the doubling.
        record(tree, visits(100, 40, 64));
        record(tree, shadow);
        assert_eq!(spell(tree), SINGLE_AFTER_WASTE);
        // Too few leaves to be wasteful, its rays scattered (each entered leaf entered by
        // one ray), and most of them stopped (here by the last packet's triangles,
        // before any leaf): one by one, not side by side.
        let scattered = Visits {
            leaves: Visits::WASTEFUL_FROM - 1,
            entries: 20,
            entered: 20,
            rays: 64,
            stopped: 40,
        };
        assert!(!scattered.wasteful() && scattered.scattered() && scattered.hints_pay());
        record(tree, scattered);
        assert!(!super::scattered(tree));
    }

    /// An any-hit packet whose rays were all stopped by one or two triangles leaves them
    /// to the thread's next packet, which tests them first: a neighbouring packet over the
    /// same large triangle is then answered without reaching a leaf. The answers are
    /// always those of every triangle tested ray by ray: for packets wholly on the large
    /// triangles, partly off them, wholly off them, and after a hint from another tree
    /// whose slots this one does not have or holds other triangles in; at both widths.
    #[test]
    fn an_any_hit_packet_tests_first_the_triangles_that_stopped_the_last_one() {
        if !crate::simd::available() {
            return;
        }
        // Two triangles making the square |x|, |y| < 1 at z = 4, and small triangles
        // scattered off to the side behind it (x from 2 to 4), where the rays through the
        // square never pass.
        let mut random = crate::test_random::XorShift::new(31);
        let mut big = vec![
            [[-1.0, -1.0, 4.0], [1.0, -1.0, 4.0], [1.0, 1.0, 4.0]],
            [[-1.0, -1.0, 4.0], [1.0, 1.0, 4.0], [-1.0, 1.0, 4.0]],
        ];
        let mut coordinate = |scale: f32| (random.unit_f32() - 0.5) * scale;
        for _ in 0..300 {
            let corner = [
                3.0 + coordinate(2.0),
                coordinate(8.0),
                6.0 + coordinate(2.0),
            ];
            big.push(
                [0, 1, 2]
                    .map(|v| std::array::from_fn(|a| corner[a] + if a == v { 0.3 } else { 0.0 })),
            );
        }
        let small = big[2..40].to_vec();
        let build = |triangles: &[[[f32; 3]; 3]]| {
            crate::scene::build_triangles(triangles, crate::bvh::BuildPreset::default())
        };
        let with_square = build(&big);
        // The 8 × 8 rays from the origin through a tile whose corner is at `(x, y)` on the
        // plane z = 4, a ray every 0.01.
        let tile = |x: f32, y: f32| -> Vec<TriangleRay> {
            (0..PACKET)
                .map(|i| TriangleRay {
                    origin: [0.0; 3],
                    direction: [x + 0.01 * (i % 8) as f32, y + 0.01 * (i / 8) as f32, 4.0],
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                })
                .collect()
        };
        let truth = |triangles: &[[[f32; 3]; 3]], rays: &[TriangleRay]| -> Vec<bool> {
            (rays.iter())
                .map(|ray| {
                    triangles.iter().any(|&[a, b, c]| {
                        crate::triangle::intersect(&ray.sheared(), a, b, c, ray.tmin, ray.tmax)
                            .is_some()
                    })
                })
                .collect()
        };
        let mut lanes = vec![LeafLanes::Eight];
        if simd512::available() {
            lanes.push(LeafLanes::Sixteen);
        }
        for lanes in lanes {
            let trace = |(blocks, _, bvh): &(Vec<TriangleBlock>, Vec<u8>, Bvh<f32>),
                         rays: &[TriangleRay]| {
                let mut out = vec![false; rays.len()];
                // SAFETY: the CPU has the lanes' features (checked above); the tree is shallow.
                let visits = unsafe { any(lanes, bvh, blocks, rays, &mut out) }.unwrap();
                (out, visits)
            };
            STOPPERS.set(Stoppers::NONE);
            let on_square = tile(-0.5, -0.5);
            let (hits, first) = trace(&with_square, &on_square);
            assert!(hits.iter().all(|&h| h) && first.leaves > 0, "{lanes:?}");
            // The next tile over the square needs no leaf.
            let next = tile(0.2, -0.5);
            let (hits, visits) = trace(&with_square, &next);
            assert!(hits.iter().all(|&h| h), "{lanes:?}");
            assert_eq!(visits.leaves, 0, "{lanes:?}");
            // Tiles across the square's edge and beyond it, each after a hint.
            for (x, y) in [(0.95, 0.2), (-1.03, -0.5), (1.5, 1.5), (0.3, 0.3)] {
                let rays = tile(x, y);
                let (hits, _) = trace(&with_square, &rays);
                assert_eq!(hits, truth(&big, &rays), "{lanes:?} at {x}, {y}");
            }
            // A hint from the first tree in smaller ones, whose slots hold other triangles
            // or none: no ray through the square hits them.
            for triangles in [&small[..], &small[..1]] {
                assert!(trace(&with_square, &on_square).0.iter().all(|&h| h));
                let (hits, _) = trace(&build(triangles), &on_square);
                assert_eq!(hits, truth(triangles, &on_square), "{lanes:?}");
            }
        }
    }

    /// A row test's hits are taken as the scalar rules take them one ray at a time: for
    /// closest hit, [`Nearest::improves`] (ties included, slots above 2³¹ among them),
    /// then the hit's weights ([`Hits::hit_in`]), [`Nearest::horizon`] and
    /// [`t_triangle`]; for any hit, the ray's bounds to −∞. Every lane outside the
    /// mask, or not improved, keeps all its values. Distances are drawn from a few values
    /// so that ties are common; eight lanes and (with AVX-512) sixteen, in every row.
    #[test]
    fn a_row_tests_hits_are_taken_as_the_scalar_rules_take_them() {
        if !crate::simd::available() {
            return;
        }
        let wide = simd512::available();
        let mut random = crate::test_random::XorShift::new(23);
        let distances = [-0.5, 0.0, 0.5, 1.0, 1.0f32.next_up(), 2.0, 3.0e38, f32::MAX];
        let slots = [0, 3, 4, 7, 1 << 31, u32::MAX - 1];
        let random_rows = |random: &mut crate::test_random::XorShift, of: &[f32]| {
            Rows(std::array::from_fn(|_| {
                std::array::from_fn(|_| of[random.below(of.len() as u64) as usize])
            }))
        };
        let slot_values = slots.map(f32::from_bits);
        let weights = [0.0, 0.25, 1.0, 3.0, 7.0];
        let (mut kept_any, mut kept_tie) = (0, 0);
        for round in 0..4000 {
            let any = round % 3 == 0;
            let lanes = if wide && round % 2 == 1 { 16 } else { 8 };
            let r = random.below(ROWS as u64 / 2) as usize * 2
                + usize::from(lanes == 8) * random.below(2) as usize;
            let mut search = Search {
                t_box: random_rows(&mut random, &distances),
                t_tri: random_rows(&mut random, &distances),
                near_t: random_rows(&mut random, &distances),
                near_slot: random_rows(&mut random, &slot_values),
                b: std::array::from_fn(|_| MaybeUninit::new(random_rows(&mut random, &weights))),
            };
            let before = copy(&search);
            let pick = |random: &mut crate::test_random::XorShift, of: &[f32]| -> Vec<f32> {
                (0..lanes)
                    .map(|_| of[random.below(of.len() as u64) as usize])
                    .collect()
            };
            let [t, u, v, w] =
                [&distances[..], &weights, &weights, &weights].map(|of| pick(&mut random, of));
            let det: Vec<f32> = (0..lanes)
                .map(|_| [1.0, 2.0, 3.0][random.below(3) as usize])
                .collect();
            let mask = random.next_u64() as u32 & ((1 << lanes) - 1);
            let slot = slots[random.below(slots.len() as u64) as usize];
            // SAFETY (both): the CPU has the features, checked above.
            let kept = if lanes == 8 {
                unsafe { fold8(any, &mut search, r, mask, [&t, &u, &v, &w, &det], slot) }
            } else {
                unsafe { fold16(any, &mut search, r, mask, [&t, &u, &v, &w, &det], slot) }
            };
            let mut want = copy(&before);
            let mut want_kept = 0;
            for i in 0..lanes {
                let (row, l) = (r + i / 8, i % 8);
                if mask >> i & 1 == 0 {
                    continue;
                }
                if any {
                    want_kept |= 1 << i;
                    want.t_box.0[row][l] = f32::NEG_INFINITY;
                    want.t_tri.0[row][l] = f32::NEG_INFINITY;
                    continue;
                }
                let nearest = Nearest {
                    t: before.near_t.0[row][l],
                    slot: before.near_slot.0[row][l].to_bits(),
                };
                if !nearest.improves(t[i], slot) {
                    continue;
                }
                want_kept |= 1 << i;
                kept_tie += usize::from(t[i] == nearest.t);
                let nearest = Nearest { t: t[i], slot };
                let hit = Hits {
                    t: t[i],
                    u: u[i],
                    v: v[i],
                    w: w[i],
                    det: det[i],
                }
                .hit_in(|x| x);
                want.near_t.0[row][l] = nearest.t;
                want.near_slot.0[row][l] = f32::from_bits(slot);
                for (b, weight) in want.b.iter_mut().zip([hit.b0, hit.b1, hit.b2]) {
                    // SAFETY: the test's weight rows are all written.
                    unsafe { b.assume_init_mut() }.0[row][l] = weight;
                }
                want.t_box.0[row][l] = nearest.horizon();
                want.t_tri.0[row][l] = t_triangle::<false>(nearest);
            }
            kept_any += usize::from(want_kept != 0);
            let why = format!("round {round}: {lanes} lanes, any {any}, row {r}");
            assert_eq!(kept, want_kept, "{why}");
            assert_eq!(bits(&search), bits(&want), "{why}");
        }
        assert!(
            kept_any > 1000 && kept_tie > 100,
            "{kept_any} kept, {kept_tie} ties"
        );

        // The test writes every weight row whole.
        fn weight_rows(search: &Search) -> [&Rows; 3] {
            // SAFETY: as above.
            search.b.each_ref().map(|b| unsafe { b.assume_init_ref() })
        }
        fn copy(search: &Search) -> Search {
            let rows = |x: &Rows| Rows(x.0);
            Search {
                t_box: rows(&search.t_box),
                t_tri: rows(&search.t_tri),
                near_t: rows(&search.near_t),
                near_slot: rows(&search.near_slot),
                b: weight_rows(search).map(|x| MaybeUninit::new(rows(x))),
            }
        }
        fn bits(search: &Search) -> Vec<u32> {
            let rows = [
                &search.t_box,
                &search.t_tri,
                &search.near_t,
                &search.near_slot,
            ];
            (rows.into_iter().chain(weight_rows(search)))
                .flat_map(|x| {
                    x.0.as_flattened()
                        .iter()
                        .map(|v| v.to_bits())
                        .collect::<Vec<_>>()
                })
                .collect()
        }
        // `$name`: the fold `$fold` of the lane values in the slices, loaded by `$load`.
        macro_rules! fold_in_lanes {
            ($name:ident, $features:literal, $load:ident, $fold:ident) => {
                #[target_feature(enable = $features)]
                fn $name(
                    any: bool,
                    search: &mut Search,
                    r: usize,
                    mask: u32,
                    [t, u, v, w, det]: [&[f32]; 5],
                    slot: u32,
                ) -> u32 {
                    // SAFETY: the features are enabled here; each slice fills a vector.
                    unsafe {
                        let load = |x: &[f32]| $load(x.as_ptr());
                        let (t, u, v, w, det) = (load(t), load(u), load(v), load(w), load(det));
                        let hits = Hits { t, u, v, w, det };
                        if any {
                            $fold::<true>(search, r, mask, &hits, slot)
                        } else {
                            $fold::<false>(search, r, mask, &hits, slot)
                        }
                    }
                }
            };
        }
        fold_in_lanes!(fold8, "avx2", _mm256_loadu_ps, fold_row_hits8);
        fold_in_lanes!(fold16, "avx2,avx512f", _mm512_loadu_ps, fold_row_hits16);
    }

    /// The lanes' `next_up`, eight and (with AVX-512) sixteen at a time, is
    /// `f32::next_up` bit for bit on every float a hit's distance can be: zeros of both
    /// signs, subnormals, normals of both signs up to the largest finite, −∞, and random
    /// bit patterns.
    #[test]
    fn next_up_in_lanes_is_f32_next_up() {
        if !crate::simd::available() {
            return;
        }
        let mut random = crate::test_random::XorShift::new(5);
        let mut values = vec![0.0, -0.0, f32::NEG_INFINITY, f32::MAX, -f32::MAX, 1.0, -1.0];
        for bits in [1, 2, 0x007f_ffff, 0x0080_0000, 0x3f7f_ffff, 0x7f7f_fffe] {
            values.extend([f32::from_bits(bits), -f32::from_bits(bits)]);
        }
        while values.len() < 4096 {
            let x = f32::from_bits(random.next_u64() as u32);
            if !x.is_nan() && x != f32::INFINITY {
                values.push(x);
            }
        }
        #[target_feature(enable = "avx2")]
        fn eight(x: &[f32]) -> [f32; 8] {
            // SAFETY: AVX2 is enabled here; `x` holds at least eight floats.
            unsafe { crate::simd::lanes8(next_up8(_mm256_loadu_ps(x.as_ptr()))) }
        }
        #[target_feature(enable = "avx2,avx512f")]
        fn sixteen(x: &[f32]) -> [f32; 16] {
            // SAFETY: AVX-512F is enabled here; `x` holds sixteen floats.
            unsafe { simd512::lanes16(next_up16(_mm512_loadu_ps(x.as_ptr()))) }
        }
        let wide = simd512::available();
        for chunk in values.chunks_exact(16) {
            let want: Vec<u32> = chunk.iter().map(|x| x.next_up().to_bits()).collect();
            // SAFETY (both): the CPU has the features, checked above.
            let got: Vec<u32> = (chunk.chunks(8).flat_map(|half| unsafe { eight(half) }))
                .map(f32::to_bits)
                .collect();
            assert_eq!(got, want, "eight lanes: {chunk:?}");
            if wide {
                let got: Vec<u32> = unsafe { sixteen(chunk) }.map(f32::to_bits).to_vec();
                assert_eq!(got, want, "sixteen lanes: {chunk:?}");
            }
        }
    }

    /// The packet's node test of the eight boxes of `node`, in the frame it was bounded
    /// in ([`PacketBounds::enters_from`]), as its traversal takes it: the child mask.
    #[target_feature(enable = "avx2")]
    fn packet_mask(packet: &PacketBounds, node: &crate::bvh::Node<f32>) -> u32 {
        let plane = |side: usize, a: usize| {
            // SAFETY: AVX2 is enabled here; `planes[side][a]` holds eight floats.
            unsafe { _mm256_loadu_ps(node.planes[side][a].as_ptr()) }
        };
        let near = [0, 1, 2].map(|a| plane(packet.octant[a], a));
        let far = [0, 1, 2].map(|a| plane(1 - packet.octant[a], a));
        // SAFETY: AVX2 is enabled here.
        unsafe { packet.enters_from(near, far, packet.horizon).0 }
    }

    /// The packet's bounds of `rays`, from a function with AVX2 enabled.
    #[target_feature(enable = "avx2")]
    fn bounds_of(rays: &[TriangleRay]) -> Option<PacketBounds> {
        // SAFETY: AVX2 is enabled here.
        unsafe { PacketBounds::of(rays) }
    }

    /// A packet admits every box that one of its rays' own node tests admits
    /// ([`crate::bvh::intersect_node`], with the ray's horizon), so that packets and single
    /// rays visit the same triangles and find the same hits. Lens packets are bounded
    /// from their waist ([`PacketBounds::shift`]), where distances are small, but a ray's
    /// own test rounds (and widens its exits) in proportion to its distance from its
    /// origin; the boxes here are what that rounding decides: each ray leaves one slab at
    /// `t0` and enters another `k` units in the last place of `t0` later, for `t0` before,
    /// at and past the waist, at several scales and places.
    #[test]
    fn a_packet_admits_every_box_its_rays_own_tests_admit() {
        if !crate::simd::available() {
            return;
        }
        use crate::bvh::{BoxRay, Node, intersect_node};
        use crate::packet_cases::{edge_boxes, lens_packets};
        let mut random = crate::test_random::XorShift::new(17);
        let in_f32 =
            |(o, d): (glam::DVec3, glam::DVec3)| (o.as_vec3().as_dvec3(), d.as_vec3().as_dvec3());
        let (mut shifted, mut borderline) = (0, 0);
        for (rays, focus) in lens_packets(&mut random, in_f32) {
            let rays: Vec<TriangleRay> = rays
                .iter()
                .map(|(o, d)| TriangleRay {
                    origin: o.as_vec3().to_array(),
                    direction: d.as_vec3().to_array(),
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                })
                .collect();
            // SAFETY: the CPU has AVX2 (checked above).
            let packet = unsafe { bounds_of(&rays) }.expect("one octant, finite");
            shifted += usize::from(packet.shift != 0.0);
            for (i, ray) in rays.iter().enumerate().step_by(5) {
                let own = BoxRay::new(ray.origin, ray.direction, ray.tmin);
                let horizon = Nearest::before(ray.tmax).horizon();
                let as_f64 = |v: [f32; 3]| glam::Vec3::from(v).as_dvec3();
                let edge = (as_f64(ray.origin), as_f64(ray.direction));
                for boxes in edge_boxes(edge, focus, 2f64.powi(-24)) {
                    let mut node = Node {
                        planes: [[[f32::INFINITY; WIDTH]; 3], [[f32::NEG_INFINITY; WIDTH]; 3]],
                        children: [0; WIDTH],
                    };
                    for (lane, (b, _)) in boxes.iter().enumerate() {
                        for axis in 0..3 {
                            node.planes[0][axis][lane] = b.min[axis] as f32;
                            node.planes[1][axis][lane] = b.max[axis] as f32;
                        }
                    }
                    let own_mask = intersect_node(&node, &own, horizon).0;
                    // SAFETY: as above.
                    let packet_mask = unsafe { packet_mask(&packet, &node) };
                    for (lane, &(_, k)) in boxes.iter().enumerate() {
                        let admitted = own_mask >> lane & 1 == 1;
                        borderline += usize::from(admitted && k > 0);
                        assert!(
                            !admitted || packet_mask >> lane & 1 == 1,
                            "ray {i} of {:?}… enters box {:?} ({k} ulps past its exit); its \
                             packet (shift {}) does not",
                            rays[0],
                            boxes[lane].0,
                            packet.shift
                        );
                    }
                }
            }
        }
        // Lens packets were bounded from their waist, and rays' own tests admitted boxes
        // they leave before entering (the rounding the packet must cover).
        assert_eq!(shifted, 17);
        assert!(
            borderline > 100,
            "{borderline} boxes admitted past the exit"
        );
    }
}
