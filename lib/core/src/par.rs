//! A raw pointer that threads share for disjoint writes into one buffer: the parallel scatters of
//! the sorts, the sorted engine and the partitioned engine, and the progressive renderer's insert.
//! One definition, so that the one `unsafe impl` and its argument live in one place.

/// A pointer into a buffer that several threads write at disjoint places.
pub struct SendPtr<T>(pub *mut T);

impl<T> Clone for SendPtr<T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for SendPtr<T> {}

// SAFETY: a `SendPtr` is only an address; sharing it between threads is harmless. Every access
// through it is `unsafe` ([`SendPtr::write`], [`SendPtr::add`]), and its caller promises that
// no two threads touch the same element, that the buffer outlives the threads and that nothing
// else borrows it meanwhile. `T: Send` because the values written cross threads.
unsafe impl<T: Send> Send for SendPtr<T> {}
// SAFETY: as for `Send`: shared references give only the address.
unsafe impl<T: Send> Sync for SendPtr<T> {}

impl<T> SendPtr<T> {
    /// Writes `v` at element `i`, without reading or dropping what was there.
    ///
    /// # Safety
    /// Element `i` is inside the buffer, and no other thread reads or writes it meanwhile.
    #[inline]
    pub unsafe fn write(&self, i: usize, v: T) {
        // SAFETY: the caller's promise above.
        unsafe { self.0.add(i).write(v) }
    }

    /// The address of element `i`.
    ///
    /// # Safety
    /// Element `i` is inside the buffer (or one past its end).
    #[inline]
    pub unsafe fn add(&self, i: usize) -> *mut T {
        // SAFETY: the caller's promise above.
        unsafe { self.0.add(i) }
    }
}

#[cfg(test)]
mod tests {
    use super::SendPtr;
    use rayon::prelude::*;

    #[test]
    fn disjoint_parallel_writes_land_where_they_were_aimed() {
        let n = 10_000usize;
        let mut v = vec![0u64; n];
        let p = SendPtr(v.as_mut_ptr());
        (0..n).into_par_iter().for_each(|i| {
            // SAFETY: each index is written by one iteration only.
            unsafe { p.write(i, (i * 3) as u64) };
        });
        assert!(v.iter().enumerate().all(|(i, &x)| x == (i * 3) as u64));
    }
}
