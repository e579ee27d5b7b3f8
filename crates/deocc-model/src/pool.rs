//! Data-parallel loops for the custom ops, run on candle's own CPU thread pool.
//!
//! candle runs its element-wise ops on a barrier pool whose workers spin for a while after each
//! op, waiting for the next one. Work handed to rayon's pool instead has to wake rayon's sleeping
//! workers while candle's worker spins on the same two cores, and the op waits for the wake-up:
//! in a perf profile of one batch-1 forward, the bias add (a memory-bound loop) cost as much as
//! every matrix product. On candle's pool, the worker that is already spinning takes the work.

use candle_core::utils::barrier_pool;

/// A pointer shared by the pool's threads, each of which touches a disjoint part of the buffer.
struct SharedMut<T>(*mut T);

// SAFETY: the pointer is only used to build disjoint sub-slices of a buffer that outlives the
// parallel call (see `for_each_chunk_mut`), so sharing it is sharing `&mut [T]` piecewise.
unsafe impl<T: Send> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    /// A method, not a field access, so that closures capture the whole (Sync) wrapper.
    fn get(&self) -> *mut T {
        self.0
    }
}

/// Threads of candle's pool: its workers and the calling thread. (candle's `get_num_threads`
/// parses /proc/cpuinfo on every call, a tenth of a batch-1 forward when called per product.)
pub fn threads() -> usize {
    barrier_pool().n_workers() + 1
}

/// `f(i, chunk_i)` for every `chunk`-sized piece of `data` (the last may be shorter), in parallel.
pub fn for_each_chunk_mut<T: Send>(
    data: &mut [T],
    chunk: usize,
    f: impl Fn(usize, &mut [T]) + Sync,
) {
    assert!(chunk > 0, "for_each_chunk_mut: chunk must be positive");
    let len = data.len();
    let pieces = len.div_ceil(chunk);
    if pieces <= 1 {
        if pieces == 1 {
            f(0, data);
        }
        return;
    }
    let base = SharedMut(data.as_mut_ptr());
    barrier_pool().execute_chunked(pieces, |range| {
        for i in range {
            let start = i * chunk;
            let end = (start + chunk).min(len);
            // SAFETY: the pool hands out each index once, so the slices are disjoint, and
            // `data` is borrowed mutably for the whole call.
            let piece =
                unsafe { std::slice::from_raw_parts_mut(base.get().add(start), end - start) };
            f(i, piece);
        }
    });
}

/// `[f(0), f(1), ..., f(n - 1)]`, computed in parallel.
pub fn map<R: Send>(n: usize, f: impl Fn(usize) -> R + Sync) -> Vec<R> {
    let mut out: Vec<Option<R>> = (0..n).map(|_| None).collect();
    for_each_chunk_mut(&mut out, 1, |i, slot| slot[0] = Some(f(i)));
    out.into_iter()
        .map(|r| r.expect("the pool computes every index"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_chunk_is_visited_once_with_its_index() {
        let mut v = vec![0usize; 1003];
        for_each_chunk_mut(&mut v, 10, |i, c| {
            for x in c.iter_mut() {
                *x += i + 1;
            }
        });
        for (k, x) in v.iter().enumerate() {
            assert_eq!(*x, k / 10 + 1, "element {k}");
        }
        let mut empty: Vec<u8> = Vec::new();
        for_each_chunk_mut(&mut empty, 4, |_, _| panic!("no chunk in an empty slice"));
    }

    #[test]
    fn map_keeps_the_order() {
        let v = map(257, |i| i * i);
        assert_eq!(v, (0..257).map(|i| i * i).collect::<Vec<_>>());
        assert!(map(0, |i| i).is_empty());
    }
}
