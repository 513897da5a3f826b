//! `sample_voxels` (paper 004 §5.2): the points of the update (spilled first, then the batch)
//! become records, counted by the root's octants, and go down the inner nodes through the
//! sampling partition (`partition`).

use super::expand::{Expansion, COUNT_CHUNK};
use super::node::NO_CHILD;
use super::partition::{sample_subtree, Rec, SampleCtx};
use super::Builder;
use crate::octree::types::Point;
use rayon::prelude::*;

impl Builder {
    /// §5.2: every point of the update samples the inner nodes on its path (spilled points from
    /// the node that spilled them down).
    pub(super) fn sample_voxels(&mut self, exp: &Expansion, batch: &[Point]) {
        let root = self.shapes[0];
        if root.first_child == NO_CHILD {
            return;
        }
        // Records: spilled points first (they arrived earlier), then the batch in input order;
        // `seq` is the place in that sequence.
        let rec = |p: &Point, tag: u32, seq: usize| Rec {
            off: root.cube.offset(p.pos),
            color: p.color,
            tag,
            seq: seq as u32,
        };
        let total = exp.spill.len() + batch.len();
        let ns = exp.spill.len();
        self.work.clear();
        self.work.par_extend(
            exp.spill
                .par_iter()
                .zip(exp.spill_origin.par_iter())
                .enumerate()
                .map(|(i, (p, &o))| rec(p, o as u32 + 1, i))
                .chain(batch.par_iter().enumerate().map(|(i, p)| rec(p, 0, ns + i))),
        );
        self.scratch.clear();
        self.scratch.resize(total, Rec::default());
        let s = root.cube.size_log2 as u32 - 1;
        let counts = self
            .work
            .par_chunks(COUNT_CHUNK)
            .map(|chunk| {
                let mut c = [0usize; 8];
                for r in chunk {
                    c[((r.off[0] >> s) & 1
                        | ((r.off[1] >> s) & 1) << 1
                        | ((r.off[2] >> s) & 1) << 2) as usize] += 1;
                }
                c
            })
            .reduce(|| [0; 8], |a, b| std::array::from_fn(|o| a[o] + b[o]));
        let ctx = SampleCtx { shapes: &self.shapes, data: &self.data, root: root.cube };
        sample_subtree(&ctx, 0, &mut self.work, &mut self.scratch, counts);
    }
}
