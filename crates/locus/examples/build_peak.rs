//! What one BVH build over a whole scene holds at its peak, per triangle:
//! the figure behind `locus_core::accel::BUILD_BYTES_PER_TRIANGLE`, which
//! the memory plans charge a build. Linux only (it reads and resets the
//! process's peak in /proc).
//!
//!     cargo run --release -p locus --example build_peak -- scenes/generated/room.toml

use locus_core::accel::Accel;
use locus_core::scene::Scene;

/// A `/proc/self/status` field in bytes.
fn status(key: &str) -> u64 {
    let s = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let line = s.lines().find(|l| l.starts_with(key)).expect(key);
    let kib: u64 = line
        .split_whitespace()
        .nth(1)
        .and_then(|v| v.parse().ok())
        .expect("a number of kB");
    kib * 1024
}

fn main() -> anyhow::Result<()> {
    let path = std::env::args()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: build_peak SCENE.toml"))?;
    let scene = Scene::load(std::path::Path::new(&path))?;
    let ids: Vec<u32> = (0..scene.tris.len() as u32).collect();
    // Writing 5 resets the peak (VmHWM) to what is resident now.
    std::fs::write("/proc/self/clear_refs", "5")?;
    let before = status("VmRSS:");
    let t = std::time::Instant::now();
    let accel = Accel::build(&scene.tris, &ids, scene.magnitude());
    let secs = t.elapsed().as_secs_f64();
    let (peak, after) = (status("VmHWM:"), status("VmRSS:"));
    let n = scene.tris.len().max(1) as f64;
    println!(
        "{} triangles: build {secs:.2} s on {} threads; peak above the start {:.0} bytes a triangle, \
         kept {:.0} (the BVH counts {:.0})",
        scene.tris.len(),
        rayon::current_num_threads(),
        peak.saturating_sub(before) as f64 / n,
        after.saturating_sub(before) as f64 / n,
        accel.bytes() as f64 / n
    );
    Ok(())
}
