//! The sampling recursion of `sample_voxels`: the points of the update, as records ([`Rec`]),
//! are partitioned top-down, stably, by octant; the task of child octant `o` samples octant `o`
//! of its parent's grid (cells of different octants never meet) in arrival order and then goes
//! on into the child, so no grid is sampled by two threads and even the root's grid is sampled
//! by 8 tasks.

use super::node::{NodeData, Shape, NO_CHILD};
use crate::octree::cube::Cube;
use crate::octree::types::GRID_LOG2;
use crate::octree::voxels::{Sample, Sampler};

/// Sub-trees with fewer points than this are sampled on the current thread.
const PAR_MIN: usize = 1 << 12;

/// A point as the sampling partition moves it: offset from the root's minimum, colour, `tag`
/// (0 for a batch point, `level + 1` of the node that spilled it for a spilled point) and `seq`,
/// its place in the update's sequence (spill, then batch), by which a new voxel finds its point.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Rec {
    pub(super) off: [u32; 3],
    pub(super) color: u32,
    pub(super) tag: u32,
    pub(super) seq: u32,
}

/// Shared state of the sampling recursion.
pub(super) struct SampleCtx<'a> {
    pub(super) shapes: &'a [Shape],
    pub(super) data: &'a [NodeData],
    pub(super) root: Cube,
}

impl SampleCtx<'_> {
    /// Offset of node `s`'s minimum from the root's.
    #[inline]
    fn base(&self, s: &Shape) -> [u32; 3] {
        [0, 1, 2].map(|a| (s.cube.min[a] - self.root.min[a]) as u32)
    }
}

/// At inner node `node` with its points `recs` (in arrival order) and their octant counts:
/// partitions them stably by octant into `scratch`; then, one task per octant, samples that
/// octant of the node's grid and recurses into the child if it is inner (large octants in
/// parallel). `recs` becomes the children's scratch space.
pub(super) fn sample_subtree(
    ctx: &SampleCtx<'_>,
    node: u32,
    recs: &mut [Rec],
    scratch: &mut [Rec],
    counts: [usize; 8],
) {
    let shape = &ctx.shapes[node as usize];
    debug_assert_ne!(shape.first_child, NO_CHILD);
    let base = ctx.base(shape);
    let s = shape.cube.size_log2 as u32 - 1;
    let mut pos = [0usize; 8];
    for o in 1..8 {
        pos[o] = pos[o - 1] + counts[o - 1];
    }
    for r in recs.iter() {
        let l = [0, 1, 2].map(|a| r.off[a].wrapping_sub(base[a]) >> s);
        let o = (l[0] | l[1] << 1 | l[2] << 2) as usize;
        scratch[pos[o]] = *r;
        pos[o] += 1;
    }
    let vox = ctx.data[node as usize].voxels.as_deref().expect("inner nodes have voxel state");

    rayon::scope(|sc| {
        let mut rest_in: &mut [Rec] = scratch;
        let mut rest_scratch: &mut [Rec] = recs;
        for (o, &n) in counts.iter().enumerate() {
            let (child_recs, r) = std::mem::take(&mut rest_in).split_at_mut(n);
            rest_in = r;
            let (child_scratch, r) = std::mem::take(&mut rest_scratch).split_at_mut(n);
            rest_scratch = r;
            if n == 0 {
                continue;
            }
            let mut work = move || {
                let mut child_counts = [0usize; 8];
                {
                    let mut oct = vox.octant(o);
                    let oct = &mut *oct;
                    let (sampled, through) = match &mut oct.sampler {
                        Sampler::FirstCome(s) => {
                            sample_recs(shape, base, child_recs, s, &mut child_counts)
                        }
                        Sampler::Averaged(s) => {
                            sample_recs(shape, base, child_recs, s, &mut child_counts)
                        }
                    };
                    oct.sampled += sampled;
                    oct.through += through;
                }
                let child = shape.first_child + o as u32;
                if ctx.shapes[child as usize].first_child != NO_CHILD {
                    sample_subtree(ctx, child, child_recs, child_scratch, child_counts);
                }
            };
            if n >= PAR_MIN {
                sc.spawn(move |_| {
                    let mut work = work;
                    work()
                });
            } else {
                work();
            }
        }
    });
}

/// The sampling loop of one octant of a node's grid; also counts the points per octant of the
/// child (the next bit of the cell). Returns how many points sampled the node and how many of
/// those are new in its cube (spilled points passing through the node that spilled them were
/// already counted there).
#[inline]
fn sample_recs<S: Sample>(
    shape: &Shape,
    base: [u32; 3],
    recs: &[Rec],
    s: &mut S,
    child_counts: &mut [usize; 8],
) -> (u64, u64) {
    let level = shape.key.level as u32;
    let shift = (shape.cube.size_log2 - GRID_LOG2) as u32;
    let mut sampled = 0u64;
    let mut through = 0u64;
    for r in recs {
        let cell = [
            r.off[0].wrapping_sub(base[0]) >> shift,
            r.off[1].wrapping_sub(base[1]) >> shift,
            r.off[2].wrapping_sub(base[2]) >> shift,
        ];
        // bit 5 of the cell is the point's octant in the child (meaningful when the child is
        // inner, i.e. at least 128 units wide)
        child_counts[((cell[0] >> 5) & 1 | ((cell[1] >> 5) & 1) << 1 | ((cell[2] >> 5) & 1) << 2)
            as usize] += 1;
        // batch points (tag 0) and points spilled at this level or above sample here
        if r.tag <= level + 1 {
            s.sample(cell, r.color, r.seq);
            sampled += 1;
            // new in this cube unless spilled by this very node
            through += u64::from(r.tag != level + 1);
        }
    }
    (sampled, through)
}
