//! What the kernel counts about this process and thread: CPU time and
//! resident memory. Reports use these counts, never estimates.

/// CPU seconds (user + system) the calling thread has used.
pub fn thread_cpu_s() -> f64 {
    clock_s(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// CPU seconds (user + system) the whole process has used.
pub fn process_cpu_s() -> f64 {
    clock_s(libc::CLOCK_PROCESS_CPUTIME_ID)
}

fn clock_s(clock: libc::clockid_t) -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; the clock ids are
    // constants every Linux kernel locus runs on supports.
    let r = unsafe { libc::clock_gettime(clock, &mut ts) };
    if r != 0 {
        return 0.0;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// This host's name (a container's is its id, a pod's its name), the
/// default name a worker registers under.
pub fn hostname() -> Option<String> {
    let mut buf = [0u8; 256];
    // SAFETY: `buf` is writable for its length; gethostname writes at most
    // that many bytes.
    let r = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) };
    if r != 0 {
        return None;
    }
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    let name = String::from_utf8_lossy(&buf[..end]).trim().to_string();
    (!name.is_empty()).then_some(name)
}

/// Names the calling thread (Linux: the first 15 bytes show in `top -H`,
/// `perf` and `/proc`), for threads borrowed from a pool, such as the
/// engine's from tokio's blocking pool.
pub fn name_thread(name: &str) {
    #[cfg(target_os = "linux")]
    if let Ok(c) = std::ffi::CString::new(name.as_bytes()[..name.len().min(15)].to_vec()) {
        // SAFETY: PR_SET_NAME reads a NUL-terminated string of at most 16
        // bytes, which `c` is.
        unsafe {
            libc::prctl(libc::PR_SET_NAME, c.as_ptr());
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = name;
}

/// A `/proc/self/status` field in bytes (the kernel writes kB).
fn status_bytes(field: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with(field))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Resident memory of this process now, if the kernel says.
pub fn resident_bytes() -> Option<u64> {
    status_bytes("VmRSS:")
}

/// Peak resident memory of this process since it started or since the
/// last [`reset_peak`], if the kernel says.
pub fn peak_resident_bytes() -> Option<u64> {
    status_bytes("VmHWM:")
}

/// Resets the peak resident figure to the present one (Linux 4.0 and
/// later: writing 5 to `/proc/self/clear_refs`). Returns whether it took.
pub fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// Runs `cmd` to its end and returns whether it succeeded and its peak
/// resident memory in bytes (Linux: the child's own `ru_maxrss`, taken by
/// `wait4`; elsewhere unknown, 0).
pub fn run_measuring_peak(cmd: &mut std::process::Command) -> std::io::Result<(bool, u64)> {
    let mut child = cmd.spawn()?;
    #[cfg(target_os = "linux")]
    {
        let pid = child.id() as libc::pid_t;
        let mut status = 0;
        // SAFETY: an all-zero rusage is a valid value for wait4 to fill.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: `pid` is our child, not yet waited for; wait4 reaps it
        // and writes `status` and `ru`, which are valid for writes.
        let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
        if r == pid {
            let ok = libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0;
            return Ok((ok, ru.ru_maxrss as u64 * 1024));
        }
    }
    Ok((child.wait()?.success(), 0))
}

/// Makes the allocator keep freed memory for reuse, for one machine's
/// render, which has no memory budget to keep to. A BVH build allocates
/// and frees its scratch in blocks of many megabytes (obvhs's PLOC passes,
/// the wide-BVH conversion's tables), and glibc maps every block above its
/// threshold (32 MiB at most) on its own and unmaps it when freed, so the
/// next block's pages are faulted in and zeroed by the kernel again. With
/// nothing mapped apart and no heap trimmed when a block is freed, the
/// main heap's blocks are reused (a thread's arena still maps a block
/// larger than its 64 MiB heaps, and unmaps a heap it no longer uses). On
/// the 3.4-million-triangle room (`locus render`, 2 threads, five
/// alternating runs against the build before): the BVH in 1.11-1.57 s
/// where it took 1.40-2.39 s (medians 1.16 and 1.62), page faults 504,000
/// to 347,000, the peak resident 1.30 to 1.41 GB. What the build leaves
/// free is given back once it is done ([`trim_heap`]). Does nothing on
/// other C libraries.
pub fn reuse_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; it is called before
    // any large block is allocated.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
    }
}

/// Makes the allocator give freed memory back, for a worker process that
/// keeps to a memory budget and for the scheduler daemon, which lives on
/// between jobs. glibc's defaults do not: a freed large block
/// raises the threshold above which blocks are mapped on their own, so the
/// next builds' scratch lands in the heap and stays resident once freed,
/// and every thread that allocates may open an arena of its own. Fixed at
/// 256 KiB and two arenas, a part's build scratch is unmapped when freed.
/// Does nothing on other C libraries.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; it is called before
    // the worker starts any job.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 256 << 10);
        libc::mallopt(libc::M_ARENA_MAX, 2);
    }
}

/// Makes parallel work started on the calling thread (a BVH build's, under
/// obvhs's `parallel` feature) run on that thread alone, not on other
/// cores: what a worker of one thread, or a fetched-leaf merge beside busy
/// tracing threads, builds in. Returns the pool of this one thread, to be
/// kept while that should hold; None when the thread already belongs to a
/// rayon pool: rayon keeps a thread in the pool it joined until the thread
/// ends, even past the pool's drop, so a tokio blocking thread that built
/// before still builds alone (and a second pool could not be made). Call
/// it from threads of one's own, not from a pool's.
pub fn this_thread_alone() -> Option<rayon::ThreadPool> {
    if rayon::current_thread_index().is_some() {
        return None;
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .use_current_thread()
        .build()
        .map_err(|e| tracing::warn!(error = %e, "cannot keep a build on its thread; it may use the shared pool"))
        .ok()
}

/// Returns free heap memory at the top of the allocator's arenas to the
/// system (glibc), after a build has freed its scratch.
pub fn trim_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases memory the allocator holds free.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clocks_advance_and_memory_is_read() {
        let a = thread_cpu_s();
        let mut x = 0u64;
        for i in 0..5_000_000u64 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(i);
        }
        std::hint::black_box(x);
        assert!(thread_cpu_s() > a);
        assert!(process_cpu_s() >= thread_cpu_s());
        let r = resident_bytes().expect("VmRSS");
        assert!(r > 0);
        // The peak is at least the present figure.
        assert!(peak_resident_bytes().expect("VmHWM") >= r / 2);
    }

    /// A block larger than glibc's largest mmap threshold (32 MiB): with
    /// glibc's defaults it is mapped on its own (and unmapped, its pages
    /// lost, when freed); kept for reuse, it comes from an arena's heap.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn a_large_block_is_not_mapped_apart() {
        reuse_freed_memory();
        const BYTES: usize = 48 << 20;
        // SAFETY: mallinfo2 only reads the allocator's counters.
        let mapped = || unsafe { libc::mallinfo2() }.hblkhd;
        let before = mapped();
        let v: Vec<u8> = Vec::with_capacity(BYTES);
        std::hint::black_box(v.as_ptr());
        let during = mapped();
        drop(v);
        assert!(
            during.saturating_sub(before) < BYTES,
            "a {BYTES}-byte block was mapped apart ({before} bytes mapped before, {during} with it)"
        );
    }
}
