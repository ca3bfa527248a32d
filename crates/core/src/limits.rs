//! What a render may ask for, checked before any work: samples per pixel
//! and path length within fixed bounds, and an image whose film fits the
//! memory this machine has available (its own, or its container's limit).

/// The most samples per pixel a render may take (a million: hours per
/// pixel row on any farm; `u32::MAX` would never end).
pub const MAX_SPP: u32 = 1 << 20;

/// The longest path, in vertices (Russian roulette ends paths long before).
pub const MAX_DEPTH: u32 = 1024;

/// Bytes a film of `width` x `height` RGB f32 pixels holds.
pub fn film_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * std::mem::size_of::<[f32; 3]>() as u64
}

/// Checks samples per pixel and path length against [`MAX_SPP`] and
/// [`MAX_DEPTH`].
pub fn check_settings(spp: u32, max_depth: u32) -> Result<(), String> {
    if spp == 0 || spp > MAX_SPP {
        return Err(format!("spp {spp} is out of range (1 to {MAX_SPP})"));
    }
    if max_depth > MAX_DEPTH {
        return Err(format!(
            "max_depth {max_depth} is out of range (at most {MAX_DEPTH})"
        ));
    }
    Ok(())
}

/// Checks a noise target (the estimated relMSE at which a render stops):
/// a positive, finite number.
pub fn check_target(target: f64) -> Result<(), String> {
    if target.is_finite() && target > 0.0 {
        Ok(())
    } else {
        Err(format!(
            "target_rel_mse {target} must be a positive number (an estimated relMSE, such as 1e-3)"
        ))
    }
}

/// Refuses an image whose `copies` films (each [`film_bytes`]) would not
/// fit the memory available to this process, saying how much it needs;
/// `who` names the machine's role in the message ("the scheduler").
pub fn check_film(width: u32, height: u32, copies: u64, who: &str) -> Result<(), String> {
    let need = film_bytes(width, height).saturating_mul(copies);
    match available_memory() {
        Some(have) if need > have => Err(format!(
            "a {width}x{height} image needs {} for its film on {who} ({copies} x {}), \
             but {} of memory is available: render it smaller, or on a machine with more memory",
            gib(need),
            gib(film_bytes(width, height)),
            gib(have)
        )),
        _ => Ok(()),
    }
}

fn gib(b: u64) -> String {
    format!("{:.2} GiB", b as f64 / (1u64 << 30) as f64)
}

/// Memory this process may still take: the kernel's estimate of memory
/// available without swapping (`MemAvailable`), lowered to what is left
/// under a cgroup v2 limit (a container's); None where neither can be
/// read (then nothing is refused).
pub fn available_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok();
    let host = meminfo.as_deref().and_then(mem_available);
    let cgroup = cgroup_room();
    match (host, cgroup) {
        (Some(h), Some(c)) => Some(h.min(c)),
        (h, c) => h.or(c),
    }
}

/// `MemAvailable` of a /proc/meminfo text, in bytes.
fn mem_available(text: &str) -> Option<u64> {
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Room left under this process's cgroup v2 memory limit, if it has one.
fn cgroup_room() -> Option<u64> {
    let rel = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let path = rel.lines().find_map(|l| l.strip_prefix("0::"))?.trim();
    let dir = std::path::Path::new("/sys/fs/cgroup").join(path.trim_start_matches('/'));
    let max = std::fs::read_to_string(dir.join("memory.max")).ok()?;
    let max: u64 = max.trim().parse().ok()?; // "max": no limit
    let cur: u64 = std::fs::read_to_string(dir.join("memory.current"))
        .ok()?
        .trim()
        .parse()
        .ok()?;
    Some(max.saturating_sub(cur))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_and_films_are_bounded() {
        assert!(check_settings(1, 0).is_ok());
        assert!(check_settings(MAX_SPP, MAX_DEPTH).is_ok());
        assert!(check_settings(0, 8).unwrap_err().contains("spp 0"));
        assert!(
            check_settings(u32::MAX, 8)
                .unwrap_err()
                .contains("4294967295")
        );
        assert!(check_settings(16, 10_000).unwrap_err().contains("10000"));
        assert_eq!(film_bytes(32768, 32768), 12 << 30);
        assert_eq!(
            mem_available("MemTotal: 100 kB\nMemAvailable:    2048 kB\n"),
            Some(2 << 20)
        );
        // No machine has a zettabyte to spare; every machine a pixel.
        #[cfg(target_os = "linux")]
        assert!(available_memory().is_some_and(|b| b > 0));
        let e = check_film(32768, 32768, 1 << 40, "the scheduler").unwrap_err();
        assert!(
            e.contains("32768x32768") && e.contains("the scheduler"),
            "{e}"
        );
        assert!(check_film(1, 1, 1, "x").is_ok());
    }
}
