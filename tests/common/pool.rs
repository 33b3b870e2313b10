//! Run a closure in a rayon pool of a given size (thread-independence checks), shared by the
//! integration tests.

/// `f` run inside a fresh rayon pool of `threads` threads.
pub fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}
