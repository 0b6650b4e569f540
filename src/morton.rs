//! Leaves in Morton order, the first step of the binary tree's build ([`crate::ploc`]).
//!
//! The codes are obvhs' 63-bit ones (`SortPrecision::U64`): each leaf box's centre within
//! the union of the boxes, 21 bits per axis, interleaved. They are sorted by radix, not by
//! comparison. First every thread sends each of its codes to the bucket of the top
//! [`TOP_BITS`] of the bits in which the codes differ; then each bucket, a few hundred
//! codes that stay in the first-level cache, is split by its next [`DIGIT_BITS`] bits
//! again and again, down to runs of at most [`INSERTION_MAX`] codes, which insertion
//! sorts. Every step keeps the order of equal codes, so leaves with equal codes stay in
//! their own order, whatever the thread count.
//!
//! Why: a comparison sort (rayon's `par_sort_unstable_by_key`, as obvhs sorts) took a
//! median of 42–46 ms on the million-triangle torus's leaves on two threads, this one
//! 30–31 ms, of a build of 150–200 ms (DEVELOPERS.md, "Morton codes are sorted by radix").

use obvhs::aabb::Aabb;
use obvhs::bvh2::node::Bvh2Node;
use obvhs::ploc::morton::morton_encode_u64_unorm;
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// The bits of the first split, made by every thread over its share of the leaves: 4,096
/// buckets. A surface meets about `2^(2k/3)` of the `2^k` cells of a `k`-bit split, so a
/// million triangles leave a few hundred in a bucket.
pub const TOP_BITS: u32 = 12;

/// The bits of each later split, within a bucket.
pub const DIGIT_BITS: u32 = 8;

/// Runs this short are insertion sorted instead of split again.
pub const INSERTION_MAX: usize = 32;

/// Leaves one task takes at least.
const PARALLEL_MIN: usize = 1 << 14;

/// Bits in a code (obvhs' `morton_encode_u64_unorm`: 3 × 21).
const CODE_BITS: u32 = 63;

#[derive(Clone, Copy)]
struct Code {
    code: u64,
    index: u32,
}

/// `leaves` in the order of their centres' Morton codes within `total`, the union of
/// their boxes; leaves with equal codes in the order they have in `leaves`.
pub fn sorted_leaves(leaves: &[Bvh2Node], total: Aabb) -> Vec<Bvh2Node> {
    let count = leaves.len();
    // In f64, as obvhs scales them.
    let scale = 1.0 / total.diagonal().as_dvec3();
    let offset = -total.min.as_dvec3() * scale;
    let code_of =
        |leaf: &Bvh2Node| morton_encode_u64_unorm(leaf.aabb().center().as_dvec3() * scale + offset);
    let share = count
        .div_ceil(rayon::current_num_threads())
        .max(PARALLEL_MIN);

    // Each share's codes, in the leaves' order; the bits in which they differ from the
    // first leaf's; and how many fall in each bucket of the codes' top bits, which is
    // the first split wherever the leaves spread over their whole box.
    let first = leaves.first().map_or(0, code_of);
    let top = |code: &Code| (code.code >> (CODE_BITS - TOP_BITS)) as usize;
    let mut shares: Vec<(Vec<Code>, u64, Vec<usize>)> = (leaves.par_chunks(share).enumerate())
        .map(|(n, chunk)| {
            let mut differ = 0;
            let mut counts = vec![0; 1 << TOP_BITS];
            let codes = (chunk.iter().zip(n * share..))
                .map(|(leaf, index)| {
                    let code = Code {
                        code: code_of(leaf),
                        index: index as u32,
                    };
                    differ |= code.code ^ first;
                    counts[top(&code)] += 1;
                    code
                })
                .collect();
            (codes, differ, counts)
        })
        .collect();
    // The codes agree above their lowest `unsorted` bits, so the first split takes the
    // bits below those: copies of one triangle, or leaves bunched on one side of the box,
    // do not all land in one bucket.
    let differ = shares.iter().fold(0, |all, (_, differ, _)| all | differ);
    let unsorted = u64::BITS - differ.leading_zeros();
    if unsorted == 0 {
        return (leaves.par_iter().with_min_len(PARALLEL_MIN))
            .copied()
            .collect();
    }
    let width = TOP_BITS.min(unsorted);
    let shift = unsorted - width;
    let bucket = |code: &Code| ((code.code >> shift) as usize) & ((1 << width) - 1);
    let counts: Vec<Vec<usize>> = if unsorted == CODE_BITS {
        (shares.iter_mut())
            .map(|(_, _, counts)| std::mem::take(counts))
            .collect()
    } else {
        (shares.par_iter())
            .map(|(codes, _, _)| {
                let mut counts = vec![0; 1 << width];
                for code in codes {
                    counts[bucket(code)] += 1;
                }
                counts
            })
            .collect()
    };

    // Where each share's codes of each bucket go: buckets in order, and within a bucket
    // the shares in order, so that the split keeps the leaves' order.
    let mut bucketed: Vec<Code> = Vec::with_capacity(count);
    let mut places: Vec<Vec<&mut [MaybeUninit<Code>]>> = counts
        .iter()
        .map(|_| Vec::with_capacity(1 << width))
        .collect();
    let mut bucket_sizes = vec![0; 1 << width];
    let mut rest = &mut bucketed.spare_capacity_mut()[..count];
    for (bucket, size) in bucket_sizes.iter_mut().enumerate() {
        for (counts, places) in counts.iter().zip(&mut places) {
            let (mine, later) = std::mem::take(&mut rest).split_at_mut(counts[bucket]);
            *size += mine.len();
            places.push(mine);
            rest = later;
        }
    }
    (shares.par_iter().zip(places.par_iter_mut())).for_each(|((codes, _, _), places)| {
        let mut places: Vec<_> = places.iter_mut().map(|p| p.iter_mut()).collect();
        for &code in codes {
            if let Some(place) = places[bucket(&code)].next() {
                place.write(code);
            }
        }
        assert!(places.iter_mut().all(|p| p.next().is_none()));
    });
    drop(places);
    // SAFETY: the places cover the first `count` elements, and each was written above
    // (each share put as many codes in each bucket as it counted, and the assertion
    // checks that every place was taken).
    unsafe { bucketed.set_len(count) };
    drop(shares);

    // Each bucket sorted in place, then the leaves gathered in that order.
    let mut buckets = Vec::with_capacity(1 << width);
    let mut rest = &mut bucketed[..];
    for &size in &bucket_sizes {
        let (codes, later) = std::mem::take(&mut rest).split_at_mut(size);
        if size > 1 {
            buckets.push(codes);
        }
        rest = later;
    }
    (buckets.into_par_iter().with_min_len(16)).for_each_init(Vec::new, |scratch, codes| {
        sort_bucket(codes, scratch, shift)
    });
    // Gathered in parallel, which also spreads the new array's first page touches.
    (bucketed.par_iter().with_min_len(PARALLEL_MIN))
        .map(|code| leaves[code.index as usize])
        .collect()
}

/// Sorts `codes`, which agree on their bits from `unsorted` up, by code, keeping the order
/// of equal codes. `scratch` is working space. Each split takes the next
/// [`DIGIT_BITS`] bits (the last one fewer), so a run is split at most seven times, and
/// runs whose codes all agree are left as they are: no input sorts in quadratic time.
fn sort_bucket(codes: &mut [Code], scratch: &mut Vec<Code>, unsorted: u32) {
    if unsorted == 0 {
        return;
    }
    if codes.len() <= INSERTION_MAX {
        insertion_sort(codes);
        return;
    }
    let width = DIGIT_BITS.min(unsorted);
    let shift = unsorted - width;
    let digit = |code: &Code| ((code.code >> shift) as usize) & ((1 << width) - 1);
    let mut counts = [0usize; 1 << DIGIT_BITS];
    for code in codes.iter() {
        counts[digit(code)] += 1;
    }
    // Codes that agree on these bits too (copies of a triangle, a cluster far from the
    // rest) need not move.
    if counts[digit(&codes[0])] == codes.len() {
        return sort_bucket(codes, scratch, shift);
    }
    let mut next = [0usize; 1 << DIGIT_BITS];
    let mut at = 0;
    for (next, &count) in next.iter_mut().zip(&counts) {
        *next = at;
        at += count;
    }
    scratch.clear();
    scratch.extend_from_slice(codes);
    for code in scratch.iter() {
        let place = &mut next[digit(code)];
        codes[*place] = *code;
        *place += 1;
    }
    let mut rest = codes;
    for &count in &counts[..1 << width] {
        let (run, later) = rest.split_at_mut(count);
        if count > 1 {
            sort_bucket(run, scratch, shift);
        }
        rest = later;
    }
}

/// Sorts `codes` by code, keeping the order of equal codes.
fn insertion_sort(codes: &mut [Code]) {
    for i in 1..codes.len() {
        let code = codes[i];
        let mut j = i;
        while j > 0 && codes[j - 1].code > code.code {
            codes[j] = codes[j - 1];
            j -= 1;
        }
        codes[j] = code;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_random::XorShift;
    use glam::Vec3A;

    /// The primitives of `leaves` in the order the standard library's stable sort gives
    /// them by obvhs' own 63-bit codes.
    fn stably_sorted(leaves: &[Bvh2Node], total: Aabb) -> Vec<u32> {
        let scale = 1.0 / total.diagonal().as_dvec3();
        let offset = -total.min.as_dvec3() * scale;
        let mut order: Vec<u32> = leaves.iter().map(|leaf| leaf.first_index).collect();
        order.sort_by_key(|&i| {
            let centre = leaves[i as usize].aabb().center().as_dvec3() * scale + offset;
            morton_encode_u64_unorm(centre)
        });
        order
    }

    fn leaves_of(boxes: &[Aabb]) -> Vec<Bvh2Node> {
        (boxes.iter().zip(0..))
            .map(|(b, i)| Bvh2Node::new(*b, 1, i))
            .collect()
    }

    fn point(p: Vec3A) -> Aabb {
        Aabb::new(p, p)
    }

    /// Box sets that stress each step: centres spread over the whole box; every code
    /// equal; all but one leaf in one top bucket, split down to its last bits; and a line
    /// of points where many codes share their digits.
    fn cases(count: usize) -> Vec<(&'static str, Vec<Aabb>)> {
        let mut random = XorShift::new(0x2545_f491_4f6c_dd1d);
        let mut next = move || Vec3A::new(random.unit_f32(), random.unit_f32(), random.unit_f32());
        let spread = (0..count)
            .map(|_| {
                let lo = next() * 100.0;
                Aabb::new(lo, lo + next())
            })
            .collect();
        let copies = vec![Aabb::new(Vec3A::ZERO, Vec3A::ONE); count];
        // With the far corner in the box, every other centre lies in the first four of
        // the 2^21 steps per axis: their codes agree in all but their lowest six bits.
        let cluster = (0..count)
            .map(|i| match i {
                0 => point(Vec3A::splat(1e6)),
                _ => point(next() * 1e6 * 2f32.powi(-19)),
            })
            .collect();
        let line = (0..count)
            .map(|i| point(Vec3A::new((i % 97) as f32, 0.0, 0.0)))
            .collect();
        vec![
            ("spread", spread),
            ("copies", copies),
            ("cluster", cluster),
            ("line", line),
        ]
    }

    #[test]
    fn leaves_come_in_the_order_of_a_stable_sort_by_obvhs_codes_on_any_thread_count() {
        for count in [
            1,
            2,
            3,
            INSERTION_MAX,
            INSERTION_MAX + 1,
            1000,
            2 * PARALLEL_MIN + 3,
        ] {
            for (name, boxes) in cases(count) {
                let leaves = leaves_of(&boxes);
                let total = boxes.iter().fold(Aabb::empty(), |all, b| all.union(b));
                let expected = stably_sorted(&leaves, total);
                for threads in [1, 2, 3] {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(threads)
                        .build()
                        .unwrap();
                    let sorted = pool.install(|| sorted_leaves(&leaves, total));
                    let order: Vec<u32> = sorted.iter().map(|leaf| leaf.first_index).collect();
                    assert!(
                        order == expected,
                        "{name}, {count} leaves, {threads} threads: the order differs"
                    );
                    // Whole leaves, not only their indices.
                    assert!((sorted.iter().zip(&order)).all(|(leaf, &i)| {
                        let original = leaves[i as usize].aabb();
                        leaf.aabb().min == original.min && leaf.aabb().max == original.max
                    }));
                }
            }
        }
    }
}
