//! glTF 2.0 / GLB meshes, read without trusting the file: every accessor a
//! primitive uses is checked before the gltf crate's reader touches it
//! (component type, element shape, byteStride at least the element, every
//! element within its bufferView and every bufferView within its buffer),
//! the node graph must be the disjoint trees the format requires (a cycle
//! or a node with two parents would place meshes without end), material
//! colours follow the scene file's rules, and a panic inside the crate is
//! an error naming the file, not a crash. Before the crate parses the
//! document, [`gltf_check`] checks the GLB container and every index in it.

use super::{FileMaterial, MeshData, colour_problem, gltf_check};
use crate::error::{Location, SceneError};
use glam::Vec3;
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;
use std::path::{Path, PathBuf};

pub(super) fn load(path: &Path) -> Result<MeshData, SceneError> {
    // Whatever the checks miss (the crate's own validation once indexed
    // past its accessors), the crate must not take the process down.
    std::panic::catch_unwind(|| open(path)).unwrap_or_else(|_| {
        Err(SceneError::Syntax {
            file: path.to_path_buf(),
            location: Location::Element("document".into()),
            message: "the glTF reader (gltf crate) crashed on this file; check that every \
                      index it holds (accessors, buffer views, nodes) names an existing element"
                .into(),
        })
    })
}

fn open(path: &Path) -> Result<MeshData, SceneError> {
    let file = || path.to_path_buf();
    let syntax = |e: gltf::Error| SceneError::Syntax {
        file: file(),
        location: Location::Element("document".into()),
        message: e.to_string(),
    };
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        file: file(),
        source,
    })?;
    let invalid = |(element, message): (String, String)| SceneError::Invalid {
        file: file(),
        location: Location::Element(element),
        message,
    };
    let json = gltf_check::json_of(&bytes).map_err(invalid)?;
    // The crate skips what it does not read (invalid UTF-8 in a string it
    // ignores, say); the whole document must be JSON.
    let value: serde_json::Value =
        serde_json::from_slice(json).map_err(|e| SceneError::Syntax {
            file: file(),
            location: Location::Element("document".into()),
            message: format!("not valid JSON: {e}"),
        })?;
    gltf_check::check_indices(&value).map_err(invalid)?;
    drop(value);
    let doc = gltf::Gltf::from_slice(&bytes).map_err(syntax)?;
    drop(bytes);
    let base = path.parent().map(Path::to_path_buf);
    // Check external buffers up front so a missing .bin is named as such.
    for b in doc.buffers() {
        if let gltf::buffer::Source::Uri(uri) = b.source()
            && !uri.starts_with("data:")
        {
            let p: PathBuf = base.clone().unwrap_or_default().join(uri);
            if !p.is_file() {
                return Err(SceneError::MissingFile {
                    file: file(),
                    location: Location::Element(format!("buffers[{}].uri", b.index())),
                    missing: p,
                });
            }
        }
    }
    let buffers = gltf::import_buffers(&doc, base.as_deref(), doc.blob.clone()).map_err(syntax)?;
    let data: Vec<&[u8]> = buffers.iter().map(|d| &d.0[..]).collect();
    read(path, &doc, &data)
}

fn read(path: &Path, doc: &gltf::Gltf, buffers: &[&[u8]]) -> Result<MeshData, SceneError> {
    let file = || path.to_path_buf();
    let invalid = |element: String, message: String| SceneError::Invalid {
        file: file(),
        location: Location::Element(element),
        message,
    };
    let mut out = MeshData::default();
    for m in doc.materials() {
        let pbr = m.pbr_metallic_roughness();
        let c = pbr.base_color_factor();
        let albedo = [c[0], c[1], c[2]];
        // KHR_materials_emissive_strength scales the factor, which the
        // core specification caps at 1: Blender writes an emission
        // strength above 1 this way, so a lamp without it is that much
        // too dim.
        let strength = m.emissive_strength().unwrap_or(1.0);
        let emission = m.emissive_factor().map(|e| e * strength);
        let element = format!("materials[{}]", m.index().unwrap_or(0));
        if let Some(why) = colour_problem(albedo, emission) {
            return Err(invalid(element, why));
        }
        out.materials.push(FileMaterial {
            name: m.name().map_or(element, str::to_string),
            albedo: Vec3::from(albedo),
            emission: Vec3::from(emission),
        });
    }
    warn_unmodelled(path, doc);
    // Meshes are placed by the node hierarchy of the default scene (or of
    // every root node when there is no scene), with each node's world
    // matrix; each node is placed once.
    let roots: Vec<gltf::Node> = match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(s) => s.nodes().collect(),
        None => {
            let mut child = vec![false; doc.nodes().len()];
            for n in doc.nodes() {
                for c in n.children() {
                    child[c.index()] = true;
                }
            }
            doc.nodes().filter(|n| !child[n.index()]).collect()
        }
    };
    let mut placed = vec![false; doc.nodes().len()];
    let mut stack: Vec<(gltf::Node, glam::Mat4)> = roots
        .into_iter()
        .map(|n| (n, glam::Mat4::IDENTITY))
        .collect();
    while let Some((node, parent)) = stack.pop() {
        if std::mem::replace(&mut placed[node.index()], true) {
            return Err(invalid(
                format!("nodes[{}]", node.index()),
                "the node is reached twice (a cycle, or a node with two parents); glTF \
                 requires its nodes to form disjoint trees"
                    .into(),
            ));
        }
        let world = parent * glam::Mat4::from_cols_array_2d(&node.transform().matrix());
        for c in node.children() {
            stack.push((c, world));
        }
        let Some(mesh) = node.mesh() else { continue };
        for prim in mesh.primitives() {
            add_primitive(path, &prim, mesh.index(), world, buffers, &mut out)?;
        }
    }
    Ok(out)
}

/// Says what of the file is not rendered, rather than rendering it
/// differently without a word.
fn warn_unmodelled(path: &Path, doc: &gltf::Gltf) {
    for why in unmodelled(doc) {
        tracing::warn!(file = %path.display(), "{why}");
    }
}

/// What of `doc` is not rendered as written: texture maps (their materials
/// keep the constant factors), metals (diffuse here) and punctual lights
/// (only surfaces emit here).
fn unmodelled(doc: &gltf::Gltf) -> Vec<String> {
    let named = |m: &gltf::Material| {
        m.name().map_or_else(
            || format!("materials[{}]", m.index().unwrap_or(0)),
            str::to_string,
        )
    };
    let list = |keep: &dyn Fn(&gltf::Material) -> bool| {
        let names: Vec<String> = doc
            .materials()
            .filter(|m| keep(m))
            .map(|m| named(&m))
            .collect();
        (!names.is_empty()).then(|| names.join(", "))
    };
    let mut out = Vec::new();
    if let Some(names) = list(&|m| {
        m.pbr_metallic_roughness().base_color_texture().is_some() || m.emissive_texture().is_some()
    }) {
        out.push(format!(
            "texture maps are not rendered: these materials keep their constant base colour and \
             emissive factors: {names}"
        ));
    }
    // glTF's metallic factor is 1 unless the file says otherwise: a
    // material that leaves it out is a metal.
    if let Some(names) = list(&|m| m.pbr_metallic_roughness().metallic_factor() > 0.0) {
        out.push(format!(
            "metallic materials are rendered as diffuse reflectors of their base colour (the \
             metallic factor is 1 where a material leaves it out): {names}"
        ));
    }
    if doc.extensions_used().any(|e| e == "KHR_lights_punctual") {
        out.push(
            "punctual lights (KHR_lights_punctual) are not modelled: only emissive surfaces and \
             the scene file's area lights emit"
                .into(),
        );
    }
    out
}

fn add_primitive(
    path: &Path,
    prim: &gltf::Primitive,
    mesh: usize,
    world: glam::Mat4,
    buffers: &[&[u8]],
    out: &mut MeshData,
) -> Result<(), SceneError> {
    let file = || path.to_path_buf();
    let elem = || format!("meshes[{mesh}].primitives[{}]", prim.index());
    let invalid = |element: String, message: String| SceneError::Invalid {
        file: file(),
        location: Location::Element(element),
        message,
    };
    let mode = prim.mode();
    if !matches!(
        mode,
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
    ) {
        tracing::warn!(file = %path.display(), element = elem(), ?mode, "skipping a primitive of points or lines");
        return Ok(());
    }
    let positions = prim
        .get(&gltf::Semantic::Positions)
        .ok_or_else(|| invalid(elem(), "no POSITION attribute".into()))?;
    check_accessor(&positions, &[DataType::F32], Dimensions::Vec3, buffers)
        .map_err(|why| invalid(format!("{} POSITION", elem()), why))?;
    let indices = prim.indices();
    if let Some(a) = &indices {
        let ints = [DataType::U8, DataType::U16, DataType::U32];
        check_accessor(a, &ints, Dimensions::Scalar, buffers)
            .map_err(|why| invalid(format!("{} indices", elem()), why))?;
    }
    let reader = prim.reader(|b| buffers.get(b.index()).copied());
    let pos: Vec<Vec3> = reader
        .read_positions()
        .ok_or_else(|| invalid(elem(), "POSITION cannot be read".into()))?
        .map(|p| world.transform_point3(Vec3::from(p)))
        .collect();
    for (i, p) in pos.iter().enumerate() {
        if !p.is_finite() {
            return Err(SceneError::NonFinite {
                file: file(),
                location: Location::Element(format!("{} POSITION[{i}]", elem())),
                what: format!("{p}"),
            });
        }
    }
    // Normals, when the primitive has them: one per position, through the
    // inverse transpose of the node's matrix.
    let normals: Option<Vec<Vec3>> = match prim.get(&gltf::Semantic::Normals) {
        None => None,
        Some(a) => {
            check_accessor(&a, &[DataType::F32], Dimensions::Vec3, buffers)
                .map_err(|why| invalid(format!("{} NORMAL", elem()), why))?;
            if a.count() != pos.len() {
                return Err(invalid(
                    format!("{} NORMAL", elem()),
                    format!("{} normals for {} positions", a.count(), pos.len()),
                ));
            }
            let nxf = glam::Mat3::from_mat4(world).inverse().transpose();
            let n: Vec<Vec3> = reader
                .read_normals()
                .ok_or_else(|| invalid(elem(), "NORMAL cannot be read".into()))?
                .map(Vec3::from)
                .collect();
            if let Some((i, v)) = n.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(SceneError::NonFinite {
                    file: file(),
                    location: Location::Element(format!("{} NORMAL[{i}]", elem())),
                    what: format!("{v}"),
                });
            }
            Some(n.into_iter().map(|v| nxf * v).collect())
        }
    };
    let idx: Vec<u32> = match (indices, reader.read_indices()) {
        (None, _) => (0..pos.len() as u32).collect(),
        (Some(_), Some(r)) => r.into_u32().collect(),
        (Some(_), None) => return Err(invalid(elem(), "indices cannot be read".into())),
    };
    let base = out.positions.len() as u32;
    let nbase = out.normals.len() as u32;
    if normals.is_some() && out.tri_normals.len() < out.triangles.len() {
        // Earlier primitives had none.
        out.tri_normals
            .resize(out.triangles.len(), super::NO_NORMAL);
    }
    if let Some((k, &i)) = idx
        .iter()
        .enumerate()
        .find(|(_, i)| **i as usize >= pos.len())
    {
        return Err(SceneError::IndexOutOfRange {
            file: file(),
            location: Location::Element(format!("{} indices[{k}]", elem())),
            index: i as i64,
            count: pos.len(),
        });
    }
    // A node whose world matrix mirrors (negative determinant) winds its
    // triangles clockwise (glTF 2.0, 3.7.2.1): two corners swap back, so
    // the counter-clockwise normal, and the emitting side, face as meant.
    let mirrored = world.determinant() < 0.0;
    for t in triangles(mode, &idx) {
        let t = if mirrored { [t[0], t[2], t[1]] } else { t };
        out.triangles.push(t.map(|i| base + i));
        out.tri_material
            .push(prim.material().index().map(|i| i as u32));
        if normals.is_some() {
            out.tri_normals
                .push([nbase + t[0], nbase + t[1], nbase + t[2]]);
        } else if !out.tri_normals.is_empty() {
            out.tri_normals.push(super::NO_NORMAL);
        }
    }
    out.positions.extend(pos);
    out.normals.extend(normals.unwrap_or_default());
    Ok(())
}

/// The triangles of a primitive's vertex list `v` in `mode`, each
/// counter-clockwise as glTF 2.0 (3.7.2.1) orders them: a list in threes;
/// a strip's triangle i as (v_i, v_{i+1}, v_{i+2}) when i is even and
/// (v_i, v_{i+2}, v_{i+1}) when it is odd; a fan's as (v_{i+1}, v_{i+2},
/// v_0).
fn triangles(mode: Mode, v: &[u32]) -> Vec<[u32; 3]> {
    match mode {
        Mode::TriangleStrip => v
            .windows(3)
            .enumerate()
            .map(|(i, w)| {
                if i % 2 == 0 {
                    [w[0], w[1], w[2]]
                } else {
                    [w[0], w[2], w[1]]
                }
            })
            .collect(),
        Mode::TriangleFan => v
            .get(1..)
            .unwrap_or_default()
            .windows(2)
            .map(|w| [w[0], w[1], v[0]])
            .collect(),
        _ => v.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect(),
    }
}

/// Checks that `a` holds elements of one of `types` shaped `dims`, read
/// from a bufferView whose stride is at least an element and which holds
/// every element, inside a buffer that holds the view.
fn check_accessor(
    a: &gltf::Accessor,
    types: &[DataType],
    dims: Dimensions,
    buffers: &[&[u8]],
) -> Result<(), String> {
    if !types.contains(&a.data_type()) || a.dimensions() != dims {
        return Err(format!(
            "accessor {} is {:?} {:?}; expected {dims:?} of {types:?}",
            a.index(),
            a.dimensions(),
            a.data_type()
        ));
    }
    if a.sparse().is_some() {
        return Err(format!(
            "accessor {} is sparse, which is not supported",
            a.index()
        ));
    }
    let Some(view) = a.view() else {
        return Err(format!("accessor {} has no bufferView", a.index()));
    };
    let elem = a.size();
    let stride = view.stride().unwrap_or(elem);
    if stride < elem {
        return Err(format!(
            "bufferView {} has byteStride {stride}, smaller than its {elem}-byte elements",
            view.index()
        ));
    }
    let end = match a.count() {
        // The crate's reader takes `count - 1`.
        0 => return Err(format!("accessor {} has no elements", a.index())),
        n => (n - 1)
            .checked_mul(stride)
            .and_then(|s| s.checked_add(a.offset()))
            .and_then(|s| s.checked_add(elem)),
    };
    if end.is_none_or(|e| e > view.length()) {
        return Err(format!(
            "accessor {} ({} elements) reaches past the {} bytes of bufferView {}",
            a.index(),
            a.count(),
            view.length(),
            view.index()
        ));
    }
    let buffer = buffers.get(view.buffer().index()).map_or(0, |b| b.len());
    if view
        .offset()
        .checked_add(view.length())
        .is_none_or(|e| e > buffer)
    {
        return Err(format!(
            "bufferView {} ends past the {buffer} bytes of buffer {}",
            view.index(),
            view.buffer().index()
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A triangle whose one material emits `factor` scaled by
    /// `strength` through KHR_materials_emissive_strength, the extension
    /// used and, if `required`, required.
    fn emissive(factor: [f32; 3], strength: f32, required: bool) -> String {
        let mut g = serde_json::json!({
            "asset": {"version": "2.0"},
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]}],
            "materials": [{
                "emissiveFactor": factor,
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": strength}}
            }],
            "buffers": [{"byteLength": 36, "uri": "data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]}],
            "extensionsUsed": ["KHR_materials_emissive_strength"]
        });
        if required {
            g["extensionsRequired"] = serde_json::json!(["KHR_materials_emissive_strength"]);
        }
        g.to_string()
    }

    #[test]
    fn emissive_strength_scales_the_emission() {
        let dir = std::env::temp_dir().join(format!("locus-gltf-strength-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("lamp.gltf");
        for required in [false, true] {
            std::fs::write(&p, emissive([1.0, 0.5, 0.25], 8.0, required)).unwrap();
            let m = load(&p).unwrap_or_else(|e| panic!("required {required}: {e}"));
            assert_eq!(m.materials[0].emission, Vec3::new(8.0, 4.0, 2.0));
        }
        // The product keeps the rule of every emission: finite, >= 0.
        for strength in [-1.0, 1e30] {
            std::fs::write(&p, emissive([1e10, 0.0, 0.0], strength, false)).unwrap();
            let e = load(&p).expect_err("refused").to_string();
            assert!(e.contains("materials[0]") && e.contains("emission"), "{e}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Metals, texture maps and punctual lights are named, each once; a
    /// material that leaves its metallic factor out is a metal (glTF's
    /// default is 1), one that says 0 is not.
    #[test]
    fn what_is_not_rendered_is_named() {
        let g = serde_json::json!({
            "asset": {"version": "2.0"},
            "extensionsUsed": ["KHR_lights_punctual"],
            "materials": [
                {"name": "paint", "pbrMetallicRoughness": {"metallicFactor": 0.0}},
                {"name": "steel"},
                {"name": "gold", "pbrMetallicRoughness": {"metallicFactor": 0.8}},
                {"name": "wood", "pbrMetallicRoughness": {"metallicFactor": 0.0,
                    "baseColorTexture": {"index": 0}}}
            ],
            "textures": [{"source": 0}],
            "images": [{"uri": "wood.png"}]
        });
        let doc = gltf::Gltf::from_slice(g.to_string().as_bytes()).unwrap();
        let why = unmodelled(&doc);
        assert_eq!(why.len(), 3, "{why:?}");
        assert!(
            why[0].starts_with("texture maps") && why[0].ends_with(": wood"),
            "{why:?}"
        );
        assert!(
            why[1].starts_with("metallic") && why[1].ends_with(": steel, gold"),
            "{why:?}"
        );
        assert!(why[2].contains("KHR_lights_punctual"), "{why:?}");
    }

    /// A quad of four vertices in the plane z = 0, counter-clockwise seen
    /// from +z, as one primitive of `mode` (4 TRIANGLES, 5 STRIP, 6 FAN)
    /// with `indices`, under a node of `scale`; its buffer beside it.
    fn quad(dir: &Path, name: &str, mode: u32, indices: &[u16], scale: [f32; 3]) -> PathBuf {
        let pos: [[f32; 3]; 4] = [[0., 0., 0.], [1., 0., 0.], [1., 1., 0.], [0., 1., 0.]];
        let mut bytes: Vec<u8> = pos.iter().flatten().flat_map(|f| f.to_le_bytes()).collect();
        bytes.extend(indices.iter().flat_map(|i| i.to_le_bytes()));
        std::fs::write(dir.join(format!("{name}.bin")), &bytes).unwrap();
        let g = serde_json::json!({
            "asset": {"version": "2.0"},
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "scale": scale}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": mode}]}],
            "buffers": [{"byteLength": bytes.len(), "uri": format!("{name}.bin")}],
            "bufferViews": [
                {"buffer": 0, "byteLength": 48},
                {"buffer": 0, "byteOffset": 48, "byteLength": 2 * indices.len()}
            ],
            "accessors": [
                {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                 "min": [0, 0, 0], "max": [1, 1, 0]},
                {"bufferView": 1, "componentType": 5123, "count": indices.len(), "type": "SCALAR"}
            ]
        });
        let p = dir.join(format!("{name}.gltf"));
        std::fs::write(&p, g.to_string()).unwrap();
        p
    }

    /// Strips and fans are read as glTF orders their triangles, each
    /// counter-clockwise like the list's; a mirroring node keeps every
    /// triangle facing where the unmirrored one faced (its normal's z
    /// above zero), as the specification's winding rule says.
    #[test]
    fn strips_fans_and_mirrors_keep_their_facing() {
        let dir = std::env::temp_dir().join(format!("locus-gltf-modes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // (name, mode, indices, the triangles glTF makes of them)
        type Case<'a> = (&'a str, u32, &'a [u16], [[u32; 3]; 2]);
        let cases: [Case; 3] = [
            ("list", 4, &[0, 1, 2, 0, 2, 3], [[0, 1, 2], [0, 2, 3]]),
            ("strip", 5, &[0, 1, 3, 2], [[0, 1, 3], [1, 2, 3]]),
            ("fan", 6, &[0, 1, 2, 3], [[1, 2, 0], [2, 3, 0]]),
        ];
        for (name, mode, indices, want) in cases {
            for scale in [[1.0, 1.0, 1.0], [-1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]] {
                let m = load(&quad(&dir, name, mode, indices, scale)).unwrap();
                let mirrored = scale.iter().product::<f32>() < 0.0;
                let expect: Vec<[u32; 3]> = want
                    .iter()
                    .map(|&[a, b, c]| if mirrored { [a, c, b] } else { [a, b, c] })
                    .collect();
                assert_eq!(m.triangles, expect, "{name}, scale {scale:?}");
                for t in &m.triangles {
                    let v = t.map(|i| m.positions[i as usize]);
                    let n = crate::geometry::tri_cross(&v);
                    // Mirrored through z too, the quad faces -z as a whole.
                    let facing = if scale[2] < 0.0 { -n.z } else { n.z };
                    assert!(facing > 0.0, "{name}, scale {scale:?}: normal {n}");
                }
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
