//! Mesh file loaders: OBJ/MTL (tobj), PLY (ply-rs-bw) and glTF 2.0 (gltf).
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

use crate::error::{Location, SceneError};
use glam::Vec3;
use std::path::{Path, PathBuf};

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
        "obj" => load_obj(path),
        "ply" => load_ply(path),
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

/// One vertex of a face, line or point statement (`v`, `v/vt`, `v//vn`,
/// `v/vt/vn`): each index given must name an element defined before it
/// (1-based, or negative from the last). Err((Some(index), count)) for one
/// out of range, Err((None, 0)) for one that is not a number.
fn check_refs(v: &str, counts: [i64; 3]) -> Result<(), (Option<i64>, usize)> {
    let parts: Vec<&str> = v.split('/').collect();
    if parts.len() > 3 || parts[0].is_empty() {
        return Err((None, 0));
    }
    for (k, idx) in parts.iter().enumerate() {
        if idx.is_empty() {
            continue;
        }
        let n = counts[k];
        let i: i64 = idx.parse().map_err(|_| (None, 0))?;
        let resolved = if i < 0 { n.saturating_add(i) } else { i - 1 };
        if i == 0 || resolved < 0 || resolved >= n {
            return Err((Some(i), n as usize));
        }
    }
    Ok(())
}

/// tobj reports what went wrong but not where, and panics or overflows on
/// some indices, so the text is first checked line by line for the errors
/// a user can make: unparsable or non-finite positions, face (line, point)
/// indices of positions, texture coordinates or normals that are malformed
/// or out of range, and missing material libraries.
/// Returns whether every face gives a normal at every vertex: only then
/// are the file's normals used (tobj makes up the missing ones).
fn validate_obj(path: &Path, text: &str) -> Result<bool, SceneError> {
    let file = || path.to_path_buf();
    // Positions, texture coordinates and normals so far: what a face may
    // refer to.
    let mut counts = [0i64; 3];
    let mut every_face_has_normals = true;
    for (i, raw) in text.lines().enumerate() {
        let loc = || Location::line(i + 1);
        let line = raw.split('#').next().unwrap_or("").trim();
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let comps: Vec<&str> = it.collect();
                if comps.len() < 3 {
                    return Err(SceneError::Syntax {
                        file: file(),
                        location: loc(),
                        message: format!("vertex needs 3 coordinates, found {}", comps.len()),
                    });
                }
                for c in &comps[..3] {
                    let x: f32 = c.parse().map_err(|_| SceneError::Syntax {
                        file: file(),
                        location: loc(),
                        message: format!("'{c}' is not a number"),
                    })?;
                    if !x.is_finite() {
                        return Err(SceneError::NonFinite {
                            file: file(),
                            location: loc(),
                            what: format!("vertex coordinate {c}"),
                        });
                    }
                }
                counts[0] += 1;
            }
            Some(kind @ ("f" | "l" | "p")) => {
                let mut count = 0;
                for v in it {
                    if kind == "f" && v.split('/').nth(2).is_none_or(str::is_empty) {
                        every_face_has_normals = false;
                    }
                    check_refs(v, counts).map_err(|(index, count)| match index {
                        Some(index) => SceneError::IndexOutOfRange {
                            file: file(),
                            location: loc(),
                            index,
                            count,
                        },
                        None => SceneError::Syntax {
                            file: file(),
                            location: loc(),
                            message: format!("{kind} vertex '{v}' is not an index"),
                        },
                    })?;
                    count += 1;
                }
                // Points and lines are skipped, but tobj reads them.
                let least = match kind {
                    "f" => 3,
                    "l" => 2,
                    _ => 1,
                };
                if count < least {
                    return Err(SceneError::Syntax {
                        file: file(),
                        location: loc(),
                        message: format!("'{kind}' needs at least {least} vertices, found {count}"),
                    });
                }
            }
            Some("vt") => counts[1] += 1,
            Some("vn") => {
                let comps: Vec<&str> = it.collect();
                finite3(&comps).map_err(|message| SceneError::Syntax {
                    file: file(),
                    location: loc(),
                    message: format!("normal {message}"),
                })?;
                counts[2] += 1;
            }
            Some("mtllib") => {
                let name = line["mtllib".len()..].trim();
                let p = path.parent().unwrap_or(Path::new(".")).join(name);
                if !p.is_file() {
                    return Err(SceneError::MissingFile {
                        file: file(),
                        location: loc(),
                        missing: p,
                    });
                }
            }
            _ => {}
        }
    }
    Ok(every_face_has_normals && counts[2] > 0)
}

fn load_obj(path: &Path) -> Result<MeshData, SceneError> {
    let text = read_text(path)?;
    let normals = validate_obj(path, &text)?;
    if !normals && text.lines().any(|l| l.trim_start().starts_with("vn")) {
        tracing::info!(file = %path.display(), "some faces give no normals: the file is shaded flat");
    }
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    let libs = obj_materials(path, &text)?;
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    // tobj is only asked for geometry and the material *names* (so it can
    // number `usemtl` groups), taken from the libraries parsed above: its
    // own MTL parser panics on a colour with fewer than three components.
    let names_only = |p: &Path| -> tobj::MTLLoadResult {
        let full = dir.join(p);
        let (_, mats) = libs
            .iter()
            .find(|(lp, _)| *lp == full)
            .ok_or(tobj::LoadError::OpenFileFailed)?;
        let names: String = mats
            .iter()
            .map(|m| format!("newmtl {}\n", m.name))
            .collect();
        tobj::load_mtl_buf(&mut names.as_bytes())
    };
    // A panic inside the parser must not take the process down with it.
    let parsed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        tobj::load_obj_buf(&mut text.as_bytes(), &opts, names_only)
    }))
    .map_err(|_| SceneError::Syntax {
        file: path.to_path_buf(),
        location: Location::Element("file".into()),
        message: "the OBJ parser (tobj) crashed on this file; check it for malformed statements \
                  or convert it to PLY or glTF"
            .into(),
    })?;
    let (models, _) = parsed.map_err(|e| SceneError::Syntax {
        file: path.to_path_buf(),
        location: Location::Element("file".into()),
        message: e.to_string(),
    })?;
    let mut out = MeshData {
        materials: libs.into_iter().flat_map(|(_, m)| m).collect(),
        ..Default::default()
    };
    // tobj splits models per object/material; positions are per model.
    for m in models {
        let base = out.positions.len() as u32;
        for p in m.mesh.positions.chunks_exact(3) {
            out.positions.push(Vec3::new(p[0], p[1], p[2]));
        }
        let mat = m
            .mesh
            .material_id
            .map(|i| i as u32)
            .filter(|&i| (i as usize) < out.materials.len());
        let nbase = out.normals.len() as u32;
        let with_normals = normals && m.mesh.normal_indices.len() == m.mesh.indices.len();
        if with_normals {
            for n in m.mesh.normals.chunks_exact(3) {
                out.normals.push(Vec3::new(n[0], n[1], n[2]));
            }
        }
        for (k, t) in m.mesh.indices.chunks_exact(3).enumerate() {
            out.triangles.push([base + t[0], base + t[1], base + t[2]]);
            out.tri_material.push(mat);
            if normals {
                out.tri_normals.push(if with_normals {
                    let n = &m.mesh.normal_indices[3 * k..3 * k + 3];
                    [nbase + n[0], nbase + n[1], nbase + n[2]]
                } else {
                    NO_NORMAL
                });
            }
        }
    }
    Ok(out)
}

/// Kd and Ke of every material of one MTL file, in file order, checked
/// with line numbers as they are read.
fn parse_mtl(path: &Path, text: &str) -> Result<Vec<FileMaterial>, SceneError> {
    let file = || path.to_path_buf();
    let mut out: Vec<FileMaterial> = Vec::new();
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
                let comps: Vec<&str> = it.collect();
                if comps.len() != 3 {
                    return Err(SceneError::Syntax {
                        file: file(),
                        location: Location::line(i + 1),
                        message: format!("{k} needs 3 components, found {}", comps.len()),
                    });
                }
                let mut rgb = [0f32; 3];
                for (c, v) in comps.iter().zip(&mut rgb) {
                    *v = c.parse().map_err(|_| SceneError::Syntax {
                        file: file(),
                        location: Location::line(i + 1),
                        message: format!("'{c}' is not a number"),
                    })?;
                    if !v.is_finite() {
                        return Err(SceneError::NonFinite {
                            file: file(),
                            location: Location::line(i + 1),
                            what: format!("{k} {c}"),
                        });
                    }
                }
                let problem = if k == "Kd" {
                    colour_problem(rgb, [0.0; 3])
                } else {
                    colour_problem([0.0; 3], rgb)
                };
                if let Some(why) = problem {
                    return Err(SceneError::Invalid {
                        file: file(),
                        location: Location::line(i + 1),
                        message: format!("{k}: {why}"),
                    });
                }
                // A colour before any newmtl belongs to no material.
                if let Some(m) = out.last_mut() {
                    if k == "Kd" {
                        m.albedo = Vec3::from(rgb);
                    } else {
                        m.emission = Vec3::from(rgb);
                    }
                }
            }
            _ => {}
        }
    }
    Ok(out)
}

/// Every material library the OBJ names, read once, in the order tobj
/// numbers materials (libraries in file order, materials in library order).
fn obj_materials(path: &Path, text: &str) -> Result<Vec<(PathBuf, Vec<FileMaterial>)>, SceneError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut libs = Vec::new();
    for raw in text.lines() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if let Some(name) = line.strip_prefix("mtllib") {
            let p = dir.join(name.trim());
            let t = std::fs::read_to_string(&p).map_err(|source| SceneError::Io {
                file: p.clone(),
                source,
            })?;
            let mats = parse_mtl(&p, &t)?;
            libs.push((p, mats));
        }
    }
    Ok(libs)
}

/// Refuses a PLY header whose element counts the file cannot hold (every
/// element takes at least a byte, and in a binary file at least its
/// scalars and list lengths): the parser would otherwise make elements
/// for as long as the count says, which a header of a few bytes can set
/// to trillions.
fn check_ply_counts(
    path: &Path,
    header: &ply_rs_bw::ply::Header,
    len: u64,
) -> Result<(), SceneError> {
    use ply_rs_bw::ply::{Encoding, PropertyType, ScalarType};
    let size = |t: &ScalarType| -> u64 {
        match t {
            ScalarType::Char | ScalarType::UChar => 1,
            ScalarType::Short | ScalarType::UShort => 2,
            ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
            ScalarType::Double => 8,
        }
    };
    let mut need = 0u64;
    for (name, e) in header.elements.iter() {
        let each = match header.encoding {
            // A value and its separator.
            Encoding::Ascii => 2 * e.properties.len() as u64,
            _ => e
                .properties
                .values()
                .map(|p| match &p.data_type {
                    PropertyType::Scalar(t) => size(t),
                    PropertyType::List(n, _) => size(n),
                })
                .sum(),
        };
        need = need.saturating_add((e.count as u64).saturating_mul(each.max(1)));
        if need > len {
            return Err(SceneError::Invalid {
                file: path.to_path_buf(),
                location: Location::Element(format!("element {name}")),
                message: format!(
                    "the header declares {} '{name}' elements, more than the file's {len} bytes can hold",
                    e.count
                ),
            });
        }
    }
    Ok(())
}

fn load_ply(path: &Path) -> Result<MeshData, SceneError> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let file = || path.to_path_buf();
    let f = std::fs::File::open(path).map_err(|source| SceneError::Io {
        file: file(),
        source,
    })?;
    let len = f.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
    let parser = Parser::<DefaultElement>::new();
    let mut r = ply_rs_bw::parser::Reader::new(std::io::BufReader::new(f));
    let ply_error = |e: ply_rs_bw::parser::ParseError| {
        let msg = e.to_string();
        // ply-rs-bw prefixes ASCII errors with "Line N: ".
        let (location, message) = match msg.strip_prefix("Line ").and_then(|s| s.split_once(": ")) {
            Some((n, rest)) if n.parse::<usize>().is_ok() => {
                (Location::line(n.parse().unwrap_or(0)), rest.to_string())
            }
            _ => (Location::Element("file".into()), msg),
        };
        SceneError::Syntax {
            file: file(),
            location,
            message,
        }
    };
    let header = parser.read_header(&mut r).map_err(ply_error)?;
    check_ply_counts(path, &header, len)?;
    let payload = parser.read_payload(&mut r, &header).map_err(ply_error)?;
    let ply = ply_rs_bw::ply::Ply::<DefaultElement> { header, payload };
    let empty = Vec::new();
    let verts = ply.payload.get("vertex").unwrap_or(&empty);
    let faces = ply.payload.get("face").unwrap_or(&empty);
    let mut out = MeshData::default();
    for (i, v) in verts.iter().enumerate() {
        let mut c = [0f32; 3];
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            let x = v
                .get(*name)
                .and_then(Property::to_f32_lossy)
                .ok_or_else(|| SceneError::Invalid {
                    file: file(),
                    location: Location::Element(format!("vertex {i}")),
                    message: format!("missing scalar property '{name}'"),
                })?;
            if !x.is_finite() {
                return Err(SceneError::NonFinite {
                    file: file(),
                    location: Location::Element(format!("vertex {i}")),
                    what: format!("{name} = {x}"),
                });
            }
            c[k] = x;
        }
        out.positions.push(Vec3::from(c));
        // Normals are used when the vertices carry all three components.
        let comps: Vec<Option<f32>> = ["nx", "ny", "nz"]
            .iter()
            .map(|name| v.get(*name).and_then(Property::to_f32_lossy))
            .collect();
        if let [Some(x), Some(y), Some(z)] = comps[..] {
            let nv = Vec3::new(x, y, z);
            if !nv.is_finite() {
                return Err(SceneError::NonFinite {
                    file: file(),
                    location: Location::Element(format!("vertex {i}")),
                    what: format!("normal {nv}"),
                });
            }
            if out.normals.len() == i {
                out.normals.push(nv);
            }
        }
    }
    // All or nothing: a file whose vertices do not all carry normals is
    // shaded flat.
    if out.normals.len() != out.positions.len() {
        out.normals.clear();
    }
    let n = out.positions.len();
    for (i, f) in faces.iter().enumerate() {
        let idx = f
            .get("vertex_indices")
            .or_else(|| f.get("vertex_index"))
            .and_then(|p| match p {
                Property::ListInt(v) => Some(v.iter().map(|&x| x as i64).collect::<Vec<_>>()),
                Property::ListUInt(v) => Some(v.iter().map(|&x| x as i64).collect()),
                Property::ListShort(v) => Some(v.iter().map(|&x| x as i64).collect()),
                Property::ListUShort(v) => Some(v.iter().map(|&x| x as i64).collect()),
                Property::ListChar(v) => Some(v.iter().map(|&x| x as i64).collect()),
                Property::ListUChar(v) => Some(v.iter().map(|&x| x as i64).collect()),
                _ => None,
            })
            .ok_or_else(|| SceneError::Invalid {
                file: file(),
                location: Location::Element(format!("face {i}")),
                message: "missing integer list 'vertex_indices'".into(),
            })?;
        if idx.len() < 3 {
            return Err(SceneError::Invalid {
                file: file(),
                location: Location::Element(format!("face {i}")),
                message: format!("face has {} vertices", idx.len()),
            });
        }
        for &k in &idx {
            if k < 0 || k as usize >= n {
                return Err(SceneError::IndexOutOfRange {
                    file: file(),
                    location: Location::Element(format!("face {i}")),
                    index: k,
                    count: n,
                });
            }
        }
        for j in 1..idx.len() - 1 {
            let t = [idx[0] as u32, idx[j] as u32, idx[j + 1] as u32];
            out.triangles.push(t);
            out.tri_material.push(None);
            if !out.normals.is_empty() {
                out.tri_normals.push(t);
            }
        }
    }
    Ok(out)
}
