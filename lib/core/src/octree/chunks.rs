//! Growable payloads made of immutable shared chunks (paper 004 §3.1, §3.4, figure 4).
//!
//! The paper stores a node's points or voxels in a linked list of fixed-size chunks so that the
//! list can grow while the renderer reads it. Here a node's payload is a list of `Arc<[T]>`: a
//! snapshot clones the list (reference counts, not data), the builder appends new chunks and
//! replaces tail chunks by merged copies, and what a snapshot holds never changes.
//!
//! Appending keeps the list short: new elements first top up a non-full tail chunk, and a new
//! piece is merged with tail chunks while the tail chunk is at most twice the merged size and the
//! result stays within the chunk limit. Chunks under half the limit then halve towards the tail,
//! so there are about `log2(max)` of them at most, and each element is copied `O(log max)` times.

use std::sync::Arc;

/// A payload: a sequence of elements stored as shared immutable chunks.
#[derive(Clone)]
pub struct Chunks<T> {
    chunks: Vec<Arc<[T]>>,
    len: u64,
}

impl<T> std::fmt::Debug for Chunks<T> {
    /// A summary: element and chunk counts, not the elements.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Chunks")
            .field("len", &self.len)
            .field("chunks", &self.chunks.len())
            .finish()
    }
}

impl<T> Default for Chunks<T> {
    fn default() -> Self {
        Chunks { chunks: Vec::new(), len: 0 }
    }
}

impl<T> Chunks<T> {
    /// Number of elements.
    #[inline]
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether there are no elements.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The chunks, in order; none is empty.
    #[inline]
    pub fn chunks(&self) -> &[Arc<[T]>] {
        &self.chunks
    }

    /// The elements in order.
    pub fn iter(&self) -> impl Iterator<Item = &T> + '_ {
        self.chunks.iter().flat_map(|c| c.iter())
    }

    /// The elements copied into one vector.
    pub fn to_vec(&self) -> Vec<T>
    where
        T: Clone,
    {
        let mut v = Vec::with_capacity(self.len as usize);
        for c in &self.chunks {
            v.extend_from_slice(c);
        }
        v
    }
}

impl<T: Copy> Chunks<T> {
    /// Appends `new`, merging it with small tail chunks (see the module docs); no chunk grows past
    /// `max_chunk` elements.
    pub(crate) fn append(&mut self, new: &[T], max_chunk: usize) {
        debug_assert!(max_chunk > 0);
        self.len += new.len() as u64;
        let mut rest = new;
        while !rest.is_empty() {
            // A piece that fills a non-full tail chunk exactly, if the tail may take it; a full
            // chunk (or the rest) otherwise.
            let tail = self.chunks.last().map_or(max_chunk, |c| c.len());
            let mut take = rest.len().min(max_chunk);
            if tail < max_chunk && tail <= 2 * rest.len().min(max_chunk - tail) {
                take = rest.len().min(max_chunk - tail);
            }
            let (piece, r) = rest.split_at(take);
            rest = r;
            let mut from = self.chunks.len();
            let mut total = piece.len();
            while from > 0 {
                let c = self.chunks[from - 1].len();
                if c + total <= max_chunk && c <= 2 * total {
                    total += c;
                    from -= 1;
                } else {
                    break;
                }
            }
            if from == self.chunks.len() {
                self.chunks.push(Arc::from(piece));
            } else {
                let mut merged = Vec::with_capacity(total);
                for c in &self.chunks[from..] {
                    merged.extend_from_slice(c);
                }
                merged.extend_from_slice(piece);
                self.chunks.truncate(from);
                self.chunks.push(Arc::from(merged));
            }
        }
    }

    /// Appends the chunk `new` without copying it when it would be stored as it is, otherwise
    /// like [`append`](Self::append).
    pub(crate) fn append_chunk(&mut self, new: Arc<[T]>, max_chunk: usize) {
        let n = new.len();
        let keeps = match self.chunks.last() {
            None => n <= max_chunk,
            Some(last) => {
                let c = last.len();
                let tops_up = c < max_chunk && c <= 2 * n.min(max_chunk - c);
                let merges = c + n <= max_chunk && c <= 2 * n;
                n <= max_chunk && !tops_up && !merges
            }
        };
        if keeps {
            if n > 0 {
                self.len += n as u64;
                self.chunks.push(new);
            }
        } else {
            self.append(&new, max_chunk);
        }
    }

    /// Replaces chunk `k`, or appends it when `k` is the number of chunks. The caller keeps the
    /// chunk layout consistent (used by averaged voxels, whose chunks are fixed-size ranges).
    pub(crate) fn put_chunk(&mut self, k: usize, chunk: Arc<[T]>) {
        debug_assert!(!chunk.is_empty());
        if k == self.chunks.len() {
            self.len += chunk.len() as u64;
            self.chunks.push(chunk);
        } else {
            self.len = self.len - self.chunks[k].len() as u64 + chunk.len() as u64;
            self.chunks[k] = chunk;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn append_keeps_order_and_bounds(sizes in prop::collection::vec(0usize..300, 0..60), max in 1usize..200) {
            let mut c = Chunks::<u32>::default();
            let mut expect = Vec::new();
            let mut next = 0u32;
            for s in sizes {
                let piece: Vec<u32> = (next..next + s as u32).collect();
                next += s as u32;
                let before = c.clone();
                c.append(&piece, max);
                expect.extend_from_slice(&piece);
                // the earlier view is untouched
                prop_assert_eq!(before.to_vec(), &expect[..expect.len() - s]);
                prop_assert_eq!(c.to_vec(), expect.clone());
                prop_assert_eq!(c.len(), expect.len() as u64);
                prop_assert!(c.chunks().iter().all(|k| !k.is_empty() && k.len() <= max));
                // chunks under half the limit halve towards the tail: few of them
                let small = c.chunks().iter().filter(|k| 2 * k.len() < max).count();
                prop_assert!(small <= 2 + (usize::BITS - max.leading_zeros()) as usize, "{} small chunks", small);
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn append_chunk_is_append(sizes in prop::collection::vec(0usize..300, 0..40), max in 1usize..200) {
            let mut a = Chunks::<u32>::default();
            let mut b = Chunks::<u32>::default();
            for (i, s) in sizes.into_iter().enumerate() {
                let piece: Vec<u32> = (0..s as u32).map(|v| v + 1000 * i as u32).collect();
                a.append(&piece, max);
                let shared: Arc<[u32]> = Arc::from(&piece[..]);
                b.append_chunk(shared.clone(), max);
                let sizes_a: Vec<usize> = a.chunks().iter().map(|c| c.len()).collect();
                let sizes_b: Vec<usize> = b.chunks().iter().map(|c| c.len()).collect();
                prop_assert_eq!(sizes_a, sizes_b);
                prop_assert_eq!(a.to_vec(), b.to_vec());
                prop_assert_eq!(a.len(), b.len());
            }
        }
    }

    #[test]
    fn put_chunk_replaces_and_appends() {
        let mut c = Chunks::<u8>::default();
        c.put_chunk(0, Arc::from(&[1u8, 2][..]));
        c.put_chunk(1, Arc::from(&[3u8][..]));
        c.put_chunk(1, Arc::from(&[4u8, 5][..]));
        assert_eq!(c.to_vec(), vec![1, 2, 4, 5]);
        assert_eq!(c.len(), 4);
    }
}
