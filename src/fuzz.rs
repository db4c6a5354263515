//! Test-only support for fuzzing the readers of untrusted bytes (ONNX protobuf,
//! safetensors, `.flo`, deformation files) with proptest: random and mutated inputs, and a
//! global allocator that records the largest single allocation of the current thread, so a
//! test can check that a reader allocates in proportion to its input, never to a size the
//! input merely claims.

use proptest::prelude::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

thread_local! {
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

struct Probe;

fn record(size: usize) {
    // `try_with`: allocations while the thread's locals are torn down are not recorded.
    let _ = LARGEST.try_with(|largest| largest.set(largest.get().max(size)));
}

// SAFETY: every call is forwarded unchanged to the system allocator.
unsafe impl GlobalAlloc for Probe {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: the caller's promise to this allocator, passed on unchanged.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: the caller's promise to this allocator, passed on unchanged.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        // SAFETY: the caller's promise to this allocator, passed on unchanged.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's promise to this allocator, passed on unchanged.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Probe = Probe;

/// Runs `f` and returns its result with the largest single allocation it made on this
/// thread, in bytes.
pub(crate) fn largest_allocation<T>(f: impl FnOnce() -> T) -> (T, usize) {
    LARGEST.with(|largest| largest.set(0));
    let result = f();
    (result, LARGEST.with(Cell::get))
}

/// The most a reader may allocate at once for an input of `len` bytes: a small multiple of
/// the input (a varint byte can become an 8-byte dimension in a doubling vector; messages
/// quote what they read) plus room for fixed-size buffers.
pub(crate) fn allowance(len: usize) -> usize {
    32 * len + (256 << 10)
}

/// How many inputs each fuzz target tries: 1500, which takes seconds in CI;
/// `DEEPMORPH_FUZZ_CASES=N` for a longer campaign.
pub(crate) fn cases() -> u32 {
    std::env::var("DEEPMORPH_FUZZ_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(1500)
}

/// Arbitrary bytes.
pub(crate) fn random_bytes() -> impl Strategy<Value = Vec<u8>> {
    prop::collection::vec(any::<u8>(), 0..600)
}

/// `seed` with up to 8 bytes replaced and perhaps cut short: inputs that get past the first
/// checks of a reader.
pub(crate) fn mutated(seed: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    let edits = prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8);
    (edits, any::<prop::sample::Index>(), any::<bool>()).prop_map(move |(edits, cut, truncate)| {
        let mut bytes = seed.clone();
        for (at, value) in edits {
            let at = at.index(bytes.len());
            bytes[at] = value;
        }
        if truncate {
            bytes.truncate(cut.index(bytes.len() + 1));
        }
        bytes
    })
}

/// Runs `read` on `bytes` and checks that its largest allocation stays within
/// [`allowance`]; a panic fails the test by itself.
pub(crate) fn within_allowance<T>(bytes: &[u8], read: impl FnOnce(&[u8]) -> T) -> T {
    let (result, largest) = largest_allocation(|| read(bytes));
    assert!(
        largest <= allowance(bytes.len()),
        "{largest} bytes allocated at once for an input of {} bytes",
        bytes.len()
    );
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[should_panic(expected = "allocated at once")]
    fn a_reader_that_trusts_a_claimed_size_is_caught() {
        within_allowance(&[0xff; 8], |claimed| {
            vec![0u8; usize::from(claimed[0]) << 16]
        });
    }

    #[test]
    fn a_reader_within_its_input_passes() {
        within_allowance(&[1; 1000], <[u8]>::to_vec);
    }
}
