//! What a radiosity solution looks like: an image from the scene's camera
//! (each pixel's camera rays look the radiosity up where they hit,
//! interpolated across the element, with the same pixel sampling as the
//! path tracer so that the two images compare pixel for pixel) and the
//! meshed solution as a PLY with vertex colours.

use super::Solver;
use crate::accel::Accel;
use crate::image_io::Image;
use crate::integrator::DIM_PIXEL;
use crate::sampler::{SampleKey, Sampler};
use crate::scene::Camera;
use crate::stats::TraceStats;
use glam::Vec3;
use std::f32::consts::PI;
use std::io::Write;
use std::path::Path;

/// Radiance leaving a diffuse surface along `dir` where it hits.
pub fn radiance(
    solver: &Solver,
    accel: &Accel,
    ray: &crate::geometry::Ray,
    stats: &mut TraceStats,
) -> Vec3 {
    let Some(h) = accel.intersect(ray, 0.0, f32::INFINITY, stats) else {
        return Vec3::ZERO;
    };
    let (patch, b1, b2) = solver.locate_patch(h.tri, h.b1, h.b2);
    let p = &solver.patches[patch as usize];
    let side = if p.normal.dot(ray.dir) <= 0.0 { 0 } else { 1 };
    let (e, w) = p.locate(b1, b2);
    p.radiosity_at(e, w, side) / PI
}

/// The solution seen from `camera`, `spp` camera rays per pixel.
pub fn render_image(
    solver: &Solver,
    accel: &Accel,
    camera: &Camera,
    spp: u32,
    seed: u64,
    sampler: Sampler,
) -> (Image, TraceStats) {
    use rayon::prelude::*;
    let w = camera.width;
    let rows: Vec<(Vec<[f32; 3]>, TraceStats)> = (0..camera.height)
        .into_par_iter()
        .map(|y| {
            let mut st = TraceStats::default();
            let row = (0..w)
                .map(|x| {
                    let mut sum = Vec3::ZERO;
                    for s in 0..spp {
                        let key = SampleKey::new(y as u64 * w as u64 + x as u64, s, seed, sampler);
                        let ray = camera.ray(x, y, key.get2d(DIM_PIXEL));
                        st.camera_rays += 1;
                        sum += radiance(solver, accel, &ray, &mut st);
                    }
                    (sum / spp.max(1) as f32).to_array()
                })
                .collect();
            (row, st)
        })
        .collect();
    let mut image = Image::new(camera.width, camera.height);
    let mut stats = TraceStats::default();
    for (y, (row, st)) in rows.into_iter().enumerate() {
        let at = y * w as usize;
        image.pixels[at..at + w as usize].copy_from_slice(&row);
        stats += st;
    }
    (image, stats)
}

fn srgb8(linear: f32) -> u8 {
    let c = linear.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// A corner of the meshed solution: its position and the radiance
/// (W/sr/m^2) of the element's brighter side there.
pub type MeshCorner = (Vec3, Vec3);

/// Every element as a triangle of its own three corners (so an element
/// beside a finer neighbour keeps its own interpolation): what the PLY
/// holds, and what a farm sends its client.
pub fn mesh_triangles(solver: &Solver) -> Vec<[MeshCorner; 3]> {
    let mut tris: Vec<[MeshCorner; 3]> = Vec::new();
    for p in &solver.patches {
        for e in p.leaves() {
            let c = p.elements[e as usize].corners;
            let side = if (0..3)
                .map(|k| p.vertices[c[k] as usize].b[1].element_sum())
                .sum::<f32>()
                > (0..3)
                    .map(|k| p.vertices[c[k] as usize].b[0].element_sum())
                    .sum::<f32>()
            {
                1
            } else {
                0
            };
            tris.push(c.map(|v| {
                let v = &p.vertices[v as usize];
                (v.pos, v.b[side] / PI)
            }));
        }
    }
    tris
}

/// Writes the solution's [`mesh_triangles`] with the radiance as float
/// properties and, scaled by `exposure`, as sRGB vertex colours.
pub fn write_ply(solver: &Solver, path: &Path, exposure: f32) -> std::io::Result<()> {
    write_mesh_ply(&mesh_triangles(solver), path, exposure)
}

/// Writes triangles of [`MeshCorner`]s as a binary PLY.
pub fn write_mesh_ply(tris: &[[MeshCorner; 3]], path: &Path, exposure: f32) -> std::io::Result<()> {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment locus radiosity solution: radiance (W/sr/m^2) per vertex\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property float radiance_r\nproperty float radiance_g\nproperty float radiance_b\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        tris.len() * 3,
        tris.len()
    )?;
    for t in tris {
        for (pos, l) in t {
            for x in pos.to_array().into_iter().chain(l.to_array()) {
                out.write_all(&x.to_le_bytes())?;
            }
            out.write_all(&l.to_array().map(|x| srgb8(x * exposure)))?;
        }
    }
    for i in 0..tris.len() as u32 {
        out.write_all(&[3])?;
        for k in 0..3 {
            out.write_all(&(3 * i + k).to_le_bytes())?;
        }
    }
    out.flush()
}
