//! Checking a submitted job before anything is built for it: every list
//! the scene sends agrees in length and holds finite values, and the
//! image, tiles, packets and samples in flight stay within what the farm's
//! messages and memory hold. A refusal names what to change.

use locus_protocol::control::MAX_TILE_PIXELS;
use locus_protocol::submit::{JobKind, JobRequest};

/// The largest packet a job may ask for: far below the frame limit even
/// for path queries.
pub const MAX_PACKET_ITEMS: u32 = 1 << 16;

/// The most tiles a job may have (the scheduler keeps a few dozen bytes
/// per tile).
pub const MAX_TILES: u64 = 1 << 22;

/// The most camera samples a job may keep in flight per worker: what a
/// sample in flight holds (its pending vertices and queries, a few hundred
/// bytes) times this stays far below any worker's memory.
pub const MAX_INFLIGHT: u32 = 1 << 18;

/// Rejects a request that would make tracing panic or lie.
pub fn validate(req: &JobRequest) -> Result<(), String> {
    if req.tris.len() != req.tri_material.len() {
        return Err(format!(
            "{} triangles but {} material ids",
            req.tris.len(),
            req.tri_material.len()
        ));
    }
    if !req.tri_normals.is_empty() && req.tri_normals.len() != req.tris.len() {
        return Err(format!(
            "{} triangles but {} sets of shading normals",
            req.tris.len(),
            req.tri_normals.len()
        ));
    }
    if let Some(i) = req
        .tri_normals
        .iter()
        .position(|t| t.iter().any(|n| !n.is_finite()))
    {
        return Err(format!("triangle {i} has a non-finite shading normal"));
    }
    if let Some(i) = req
        .tri_material
        .iter()
        .position(|&m| m as usize >= req.materials.len())
    {
        return Err(format!(
            "triangle {i} names material {}, beyond the {} defined",
            req.tri_material[i],
            req.materials.len()
        ));
    }
    if let Some(i) = req
        .tris
        .iter()
        .position(|t| t.iter().any(|p| !p.is_finite()))
    {
        return Err(format!("triangle {i} has a non-finite vertex"));
    }
    let c = &req.camera;
    if c.width == 0 || c.height == 0 || c.width > 1 << 15 || c.height > 1 << 15 {
        return Err(format!(
            "image size {}x{} is out of range: each side must be 1 to 32768 pixels",
            c.width, c.height
        ));
    }
    if !(c.position.is_finite() && c.look_at.is_finite() && c.up.is_finite() && c.fov_y.is_finite())
    {
        return Err("camera has a non-finite value".into());
    }
    let s = &req.settings;
    locus_core::limits::check_settings(s.spp, s.max_depth)?;
    if let Some(t) = s.target_rel_mse {
        locus_core::limits::check_target(t)?;
    }
    // The film's f64 sums (two f32 films' worth), and an image made from
    // them (a preview being encoded, or the result).
    locus_core::limits::check_film(c.width, c.height, 3, "the scheduler")?;
    let o = &req.options;
    if let JobKind::Radiosity(r) = &req.kind {
        r.params.check().map_err(|e| format!("radiosity: {e}"))?;
        locus_core::limits::check_settings(r.spp.max(1), 1)?;
        if r.ring > 64 || (r.ring > 0 && o.workers > 0 && !o.workers.is_multiple_of(r.ring)) {
            return Err(format!(
                "radiosity rings of {} cannot be cut from {} workers: the worker count must be \
                 a multiple of the ring length (1 to 64)",
                r.ring, o.workers
            ));
        }
    }
    if let Some(c) = &o.cache {
        c.check().map_err(|e| format!("cache parameters: {e}"))?;
    }
    if o.tile_size == 0 || o.tuning.packet_size == 0 || o.tuning.max_inflight == 0 {
        return Err("tile size, packet size and max in-flight must be positive".into());
    }
    let ts = o.tile_size.max(1);
    let tile_pixels = ts.min(c.width) as u64 * ts.min(c.height) as u64;
    if tile_pixels > MAX_TILE_PIXELS {
        return Err(format!(
            "a tile of {ts} pixels a side holds {tile_pixels} pixels, more than {MAX_TILE_PIXELS} \
             (a tile's result must fit one message): choose a smaller tile size"
        ));
    }
    let tiles = c.width.div_ceil(ts) as u64 * c.height.div_ceil(ts) as u64;
    if tiles > MAX_TILES {
        return Err(format!(
            "{tiles} tiles of {ts} pixels is more than {MAX_TILES}: choose a larger tile size"
        ));
    }
    if o.tuning.max_inflight > MAX_INFLIGHT {
        return Err(format!(
            "max in-flight {} is above the largest, {MAX_INFLIGHT} samples",
            o.tuning.max_inflight
        ));
    }
    if o.tuning.packet_size > MAX_PACKET_ITEMS {
        return Err(format!(
            "packet size {} is above the largest, {MAX_PACKET_ITEMS} items",
            o.tuning.packet_size
        ));
    }
    if o.tuning.shared_percent > 100 {
        return Err(format!(
            "--shared-percent {} is above 100: give the percent of the scene every worker \
             holds beside its region, 0 to 100",
            o.tuning.shared_percent
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::scene::Scene;
    use locus_protocol::submit::JobOptions;

    /// A tile whose result would not fit one message is refused when the
    /// job arrives, naming the tile size (a worker's oversized result once
    /// closed its connection, and the job retried without end); a tile
    /// size larger than the image is clamped to it.
    #[test]
    fn tiles_whose_results_would_not_fit_a_message_are_refused() {
        let mut scene = crate::cornell_box();
        scene.camera.width = 1500;
        scene.camera.height = 1500;
        let req = |scene: &Scene, tile_size: u32| {
            crate::client::request(
                scene,
                JobOptions {
                    tile_size,
                    ..Default::default()
                },
            )
        };
        let e = validate(&req(&scene, 2048)).expect_err("1500 x 1500 pixels a tile");
        assert!(
            e.contains("tile of 2048 pixels") && e.contains("smaller tile size"),
            "{e}"
        );
        const { assert!(1500 * 1500 > MAX_TILE_PIXELS && 1024 * 1024 <= MAX_TILE_PIXELS) };
        assert_eq!(validate(&req(&scene, 1024)), Ok(()));
        scene.camera.height = 400;
        assert_eq!(
            validate(&req(&scene, 4096)),
            Ok(()),
            "1500 x 400 pixels a tile"
        );
    }

    /// A share of the scene above the whole of it is refused, naming the
    /// option; the whole of it is not.
    #[test]
    fn a_shared_percent_above_100_is_refused() {
        let scene = crate::cornell_box();
        for (p, ok) in [(0, true), (100, true), (101, false)] {
            let mut o = JobOptions::default();
            o.tuning.shared_percent = p;
            let r = validate(&crate::client::request(&scene, o));
            assert_eq!(r.is_ok(), ok, "{p}: {r:?}");
            if let Err(e) = r {
                assert!(e.contains("--shared-percent 101"), "{e}");
            }
        }
    }

    /// A client's noise target that is not a positive number is refused
    /// when the job arrives (a NaN would never be met, a negative one
    /// neither).
    #[test]
    fn a_noise_target_must_be_a_positive_number() {
        let mut scene = crate::cornell_box();
        for (t, ok) in [(1e-3, true), (0.0, false), (-1.0, false), (f64::NAN, false)] {
            scene.settings.target_rel_mse = Some(t);
            let r = validate(&crate::client::request(&scene, JobOptions::default()));
            assert_eq!(r.is_ok(), ok, "{t}: {r:?}");
            if let Err(e) = r {
                assert!(e.contains("target_rel_mse"), "{e}");
            }
        }
    }
}
