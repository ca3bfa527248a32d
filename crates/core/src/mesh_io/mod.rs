//! Mesh file loaders: OBJ/MTL ([`obj`], our own one-pass reader), PLY
//! ([`ply`], ply-rs-bw into typed elements) and glTF 2.0 (gltf).
//!
//! Each returns a [`MeshData`]: shared vertex positions, triangles as
//! vertex indices, per-triangle file material, and the file's vertex
//! normals where it has them (OBJ `vn`, PLY `nx ny nz`, glTF `NORMAL`),
//! which become shading normals. Positions stay shared so that
//! neighbouring triangles carry bit-identical vertices, which the
//! watertight triangle test relies on. Every loader checks coordinates and
//! normals for NaN/inf and indices for range, and reports the line (OBJ,
//! ASCII PLY) or element (binary PLY, glTF) of the first offence.

mod gltf_check;
mod gltf_mesh;
mod obj;
mod ply;
mod ply_binary;

use crate::error::{Location, SceneError};
use glam::Vec3;
use std::path::Path;

/// The one rule for a material's colours, wherever they are written (scene
/// file, MTL, glTF): albedo in [0, 1], emission finite and >= 0. None when
/// they keep it, else why not.
pub(crate) fn colour_problem(albedo: [f32; 3], emission: [f32; 3]) -> Option<String> {
    if albedo.iter().any(|a| !(0.0..=1.0).contains(a)) {
        return Some(format!("albedo {albedo:?} must lie in [0, 1]"));
    }
    if emission.iter().any(|e| !(e.is_finite() && *e >= 0.0)) {
        return Some(format!("emission {emission:?} must be finite and >= 0"));
    }
    None
}

/// A material as a mesh file describes it.
#[derive(Clone, Debug, PartialEq)]
pub struct FileMaterial {
    pub name: String,
    pub albedo: Vec3,
    pub emission: Vec3,
}

#[derive(Clone, Debug, Default)]
pub struct MeshData {
    pub positions: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    /// Index into `materials` per triangle, if the file assigns one.
    pub tri_material: Vec<Option<u32>>,
    pub materials: Vec<FileMaterial>,
    /// Vertex normals as the file gives them (not normalised).
    pub normals: Vec<Vec3>,
    /// Per triangle, its vertices' indices into `normals` ([`NO_NORMAL`]
    /// for a triangle without); empty when no triangle has normals.
    pub tri_normals: Vec<[u32; 3]>,
}

/// A triangle's entry in [`MeshData::tri_normals`] when it has no normals.
pub const NO_NORMAL: [u32; 3] = [u32::MAX; 3];

/// The three components of a normal or a position, parsed and checked.
fn finite3(comps: &[&str]) -> Result<[f32; 3], String> {
    if comps.len() < 3 {
        return Err(format!("needs 3 components, found {}", comps.len()));
    }
    let mut v = [0f32; 3];
    for (c, x) in comps[..3].iter().zip(&mut v) {
        *x = c.parse().map_err(|_| format!("'{c}' is not a number"))?;
        if !x.is_finite() {
            return Err(format!("{c} is not finite"));
        }
    }
    Ok(v)
}

pub fn load(path: &Path) -> Result<MeshData, SceneError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "obj" => obj::load_obj(path),
        "ply" => ply::load_ply(path),
        "gltf" | "glb" => gltf_mesh::load(path),
        _ => Err(SceneError::Invalid {
            file: path.to_path_buf(),
            location: Location::Element("file name".into()),
            message: format!("unknown mesh format '.{ext}' (expected .obj, .ply, .gltf or .glb)"),
        }),
    }
}

fn read_text(path: &Path) -> Result<String, SceneError> {
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        file: path.to_path_buf(),
        source,
    })?;
    String::from_utf8(bytes).map_err(|e| {
        let off = e.utf8_error().valid_up_to();
        SceneError::Syntax {
            file: path.to_path_buf(),
            location: Location::Element(format!("byte {off}")),
            message: "file is not valid UTF-8 text".into(),
        }
    })
}

/// Kd and Ke of every material of one MTL file, in file order, checked
/// with line numbers as they are read. A colour is `r g b`, or one value
/// for all three (the MTL specification: "g and b are optional"); its
/// `spectral` and `xyz` forms are refused by name. Texture maps are not
/// rendered: a material that has one keeps its constant colour, and the
/// file is named in a warning.
fn parse_mtl(path: &Path, text: &str) -> Result<Vec<FileMaterial>, SceneError> {
    let mut out: Vec<FileMaterial> = Vec::new();
    let mut maps: Vec<String> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        let mut it = line.split_whitespace();
        match it.next() {
            Some("newmtl") => out.push(FileMaterial {
                name: line["newmtl".len()..].trim().to_string(),
                albedo: Vec3::splat(0.8),
                emission: Vec3::ZERO,
            }),
            Some(k @ ("Kd" | "Ke")) => {
                let rgb = mtl_colour(k, it).map_err(|(kind, message)| {
                    let (file, location) = (path.to_path_buf(), Location::line(i + 1));
                    match kind {
                        ColourFault::Syntax => SceneError::Syntax {
                            file,
                            location,
                            message,
                        },
                        ColourFault::NonFinite => SceneError::NonFinite {
                            file,
                            location,
                            what: message,
                        },
                        ColourFault::Invalid => SceneError::Invalid {
                            file,
                            location,
                            message,
                        },
                    }
                })?;
                // A colour before any newmtl belongs to no material.
                if let Some(m) = out.last_mut() {
                    if k == "Kd" {
                        m.albedo = Vec3::from(rgb);
                    } else {
                        m.emission = Vec3::from(rgb);
                    }
                }
            }
            Some(k) if k.starts_with("map_") => {
                if let Some(m) = out.last()
                    && maps.last() != Some(&m.name)
                {
                    maps.push(m.name.clone());
                }
            }
            _ => {}
        }
    }
    if !maps.is_empty() {
        tracing::warn!(
            file = %path.display(),
            materials = %maps.join(", "),
            "texture maps are not rendered: these materials keep their constant Kd and Ke"
        );
    }
    Ok(out)
}

/// What is wrong with an MTL colour statement.
enum ColourFault {
    Syntax,
    NonFinite,
    Invalid,
}

/// The colour of a `Kd` or `Ke` statement (`k`) from its values.
fn mtl_colour<'a>(
    k: &str,
    it: impl Iterator<Item = &'a str>,
) -> Result<[f32; 3], (ColourFault, String)> {
    let comps: Vec<&str> = it.collect();
    if let Some(&form @ ("spectral" | "xyz")) = comps.first() {
        return Err((
            ColourFault::Syntax,
            format!("{k} {form} is not supported: give the colour as r g b"),
        ));
    }
    if comps.len() != 1 && comps.len() != 3 {
        return Err((
            ColourFault::Syntax,
            format!(
                "{k} needs 3 components (or 1 for grey), found {}",
                comps.len()
            ),
        ));
    }
    let mut rgb = [0f32; 3];
    for (c, v) in comps.iter().zip(&mut rgb) {
        *v = c
            .parse()
            .map_err(|_| (ColourFault::Syntax, format!("'{c}' is not a number")))?;
        if !v.is_finite() {
            return Err((ColourFault::NonFinite, format!("{k} {c}")));
        }
    }
    if comps.len() == 1 {
        rgb = [rgb[0]; 3];
    }
    let problem = if k == "Kd" {
        colour_problem(rgb, [0.0; 3])
    } else {
        colour_problem([0.0; 3], rgb)
    };
    match problem {
        Some(why) => Err((ColourFault::Invalid, format!("{k}: {why}"))),
        None => Ok(rgb),
    }
}
