//! One module per family of subcommands; `main` dispatches to them.

pub(crate) mod bench;
pub(crate) mod daemons;
pub(crate) mod radiosity;
pub(crate) mod radiosity_farm;
pub(crate) mod render;
pub(crate) mod tools;

/// Holds this process's shared rayon pool (the one a BVH build, the octree
/// and a cost preview run on when no pool of their own is installed) to
/// `threads` when it is given: a render or a worker told to use so many
/// threads uses no more in any phase. Zero leaves rayon's default, every
/// core.
pub(crate) fn limit_threads(threads: usize) {
    if threads > 0
        && let Err(e) = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
    {
        // Only a second call can fail, and the first one's limit holds.
        tracing::debug!(error = %e, "the shared thread pool was set before");
    }
}
