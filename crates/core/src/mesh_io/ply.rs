//! PLY (ASCII and binary): vertices with `x y z` and optional `nx ny nz`,
//! faces with a `vertex_indices` (or `vertex_index`) list, fanned into
//! triangles.
//!
//! ply-rs-bw reads the header, and an ASCII body into small typed records
//! ([`Vertex`], [`Face`]) rather than its default element, a map from
//! property name to value per vertex: with that, a 77 MB binary file of 4
//! million triangles took 12 s to load and held every vertex as a hash
//! map. Elements other than vertices and faces are read with the default
//! element and dropped (they must be read: the payload is in header
//! order). A binary body is read from the file's bytes by
//! [`super::ply_binary`], which takes the same values into the same
//! [`Records`] without a call per scalar or an allocation per face.

use super::MeshData;
use crate::error::{Location, SceneError};
use glam::Vec3;
use ply_rs_bw::ply::{Property, PropertyAccess, PropertyAccessResult};
use std::path::Path;

/// A vertex as read: its position and normal components, each present
/// when the file gives it as a scalar.
#[derive(Default)]
pub(super) struct Vertex {
    pub(super) at: [Option<f32>; 3],
    pub(super) normal: [Option<f32>; 3],
}

/// The vertex and face elements as read, by either reader: each face's
/// vertex list as a range of `indices` (None where the face has none).
#[derive(Default)]
pub(super) struct Records {
    pub(super) verts: Vec<Vertex>,
    pub(super) faces: Vec<Option<(usize, usize)>>,
    pub(super) indices: Vec<i64>,
}

impl Vertex {
    /// Component `k`: 0-2 the position's `x y z`, 3-5 the normal's.
    #[inline]
    pub(super) fn component(&mut self, k: usize) -> &mut Option<f32> {
        match k {
            0..3 => &mut self.at[k],
            _ => &mut self.normal[k - 3],
        }
    }
}

impl PropertyAccess for Vertex {
    fn new() -> Self {
        Self::default()
    }

    fn set_property(&mut self, name: &str, p: Property) -> PropertyAccessResult {
        let slot = match name {
            "x" => &mut self.at[0],
            "y" => &mut self.at[1],
            "z" => &mut self.at[2],
            "nx" => &mut self.normal[0],
            "ny" => &mut self.normal[1],
            "nz" => &mut self.normal[2],
            _ => return PropertyAccessResult::Ignored,
        };
        *slot = p.to_f32_lossy();
        PropertyAccessResult::Set
    }
}

/// A face as read: its vertex list under either name.
#[derive(Default)]
struct Face {
    indices: Option<Vec<i64>>,
    index: Option<Vec<i64>>,
}

impl PropertyAccess for Face {
    fn new() -> Self {
        Self::default()
    }

    fn set_property(&mut self, name: &str, p: Property) -> PropertyAccessResult {
        let slot = match name {
            "vertex_indices" => &mut self.indices,
            "vertex_index" => &mut self.index,
            _ => return PropertyAccessResult::Ignored,
        };
        *slot = match p {
            Property::ListInt(v) => Some(v.iter().map(|&x| x as i64).collect()),
            Property::ListUInt(v) => Some(v.iter().map(|&x| x as i64).collect()),
            Property::ListShort(v) => Some(v.iter().map(|&x| x as i64).collect()),
            Property::ListUShort(v) => Some(v.iter().map(|&x| x as i64).collect()),
            Property::ListChar(v) => Some(v.iter().map(|&x| x as i64).collect()),
            Property::ListUChar(v) => Some(v.iter().map(|&x| x as i64).collect()),
            _ => None,
        };
        PropertyAccessResult::Set
    }
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
    use ply_rs_bw::ply::{Encoding, PropertyType};
    let size = |t| super::ply_binary::size(t) as u64;
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

/// The vertex and face elements of an ASCII body, read by ply-rs-bw into
/// typed records from `r`, which stands after the header.
fn ascii_records(
    r: &mut ply_rs_bw::parser::Reader<&[u8]>,
    header: &ply_rs_bw::ply::Header,
) -> Result<Records, ply_rs_bw::parser::ParseError> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::DefaultElement;
    let mut records = Records::default();
    for (name, def) in header.elements.iter() {
        match name.as_str() {
            "vertex" => {
                records.verts = Parser::<Vertex>::new().read_payload_for_element(r, def, header)?
            }
            "face" => {
                let faces = Parser::<Face>::new().read_payload_for_element(r, def, header)?;
                for f in faces {
                    let list = f.indices.or(f.index).map(|l| {
                        records.indices.extend_from_slice(&l);
                        (records.indices.len() - l.len(), l.len())
                    });
                    records.faces.push(list);
                }
            }
            _ => {
                Parser::<DefaultElement>::new().read_payload_for_element(r, def, header)?;
            }
        }
    }
    Ok(records)
}

pub(super) fn load_ply(path: &Path) -> Result<MeshData, SceneError> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Encoding};
    let file = || path.to_path_buf();
    let bytes = std::fs::read(path).map_err(|source| SceneError::Io {
        file: file(),
        source,
    })?;
    let mut r = ply_rs_bw::parser::Reader::new(&bytes[..]);
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
    let header = Parser::<DefaultElement>::new()
        .read_header(&mut r)
        .map_err(ply_error)?;
    check_ply_counts(path, &header, bytes.len() as u64)?;
    let records = match header.encoding {
        Encoding::BinaryLittleEndian => super::ply_binary::read(path, &header, r.get_ref(), false)?,
        Encoding::BinaryBigEndian => super::ply_binary::read(path, &header, r.get_ref(), true)?,
        Encoding::Ascii => ascii_records(&mut r, &header).map_err(ply_error)?,
    };
    let Records {
        verts,
        faces,
        indices,
    } = records;
    let mut out = MeshData::default();
    for (i, v) in verts.iter().enumerate() {
        let mut c = [0f32; 3];
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            let x = v.at[k].ok_or_else(|| SceneError::Invalid {
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
        if let [Some(x), Some(y), Some(z)] = v.normal {
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
            .map(|(start, len)| &indices[start..start + len])
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
        for &k in idx {
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

#[cfg(test)]
mod tests {
    use super::*;
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::DefaultElement;

    /// Positions, normals (as bits) and triangles, as a reader gives them.
    type Read = (Vec<[u32; 3]>, Vec<[u32; 3]>, Vec<[u32; 3]>);

    /// What locus read before: every element as ply-rs-bw's default
    /// element (a map per vertex), the first three of `x y z`, `nx ny nz`
    /// and the face lists taken by name.
    fn by_default_element(path: &Path) -> Read {
        let f = std::fs::File::open(path).unwrap();
        let mut r = ply_rs_bw::parser::Reader::new(std::io::BufReader::new(f));
        let p = Parser::<DefaultElement>::new();
        let header = p.read_header(&mut r).unwrap();
        let payload = p.read_payload(&mut r, &header).unwrap();
        let get = |e: &DefaultElement, k: &str| e.get(k).and_then(Property::to_f32_lossy);
        let bits = |v: [Option<f32>; 3]| v.map(|x| x.unwrap().to_bits());
        let verts = &payload["vertex"];
        let pos = verts
            .iter()
            .map(|v| bits([get(v, "x"), get(v, "y"), get(v, "z")]))
            .collect();
        let nrm = verts
            .iter()
            .filter(|v| get(v, "nx").is_some())
            .map(|v| bits([get(v, "nx"), get(v, "ny"), get(v, "nz")]))
            .collect();
        let mut tris = Vec::new();
        for f in &payload["face"] {
            let idx: Vec<u32> = match f.get("vertex_indices").or_else(|| f.get("vertex_index")) {
                Some(Property::ListInt(v)) => v.iter().map(|&x| x as u32).collect(),
                Some(Property::ListUInt(v)) => v.clone(),
                Some(Property::ListUShort(v)) => v.iter().map(|&x| x as u32).collect(),
                Some(Property::ListUChar(v)) => v.iter().map(|&x| x as u32).collect(),
                other => panic!("{other:?}"),
            };
            for j in 1..idx.len() - 1 {
                tris.push([idx[0], idx[j], idx[j + 1]]);
            }
        }
        (pos, nrm, tris)
    }

    fn ours(path: &Path) -> Read {
        let m = load_ply(path).expect("loads");
        let bits = |v: &Vec3| v.to_array().map(f32::to_bits);
        assert!(m.tri_normals.is_empty() || m.tri_normals == m.triangles);
        (
            m.positions.iter().map(bits).collect(),
            m.normals.iter().map(bits).collect(),
            m.triangles,
        )
    }

    /// Typed records read what the default element read, in ASCII and both
    /// binary byte orders, with doubles, integer coordinates, normals,
    /// properties and whole elements that are skipped, quads fanned, and
    /// either name of the face list.
    #[test]
    fn typed_records_read_what_the_default_element_read() {
        let dir = std::env::temp_dir().join(format!("locus-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let ascii = "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty uchar red\n\
                     property float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
                     element edge 1\nproperty int a\nproperty int b\n\
                     element face 2\nproperty list uchar int vertex_indices\nproperty float quality\nend_header\n\
                     0 9 0 0 0 0 1\n1.5 9 0 0 0 0.6 0.8\n1 9 1 0.25 1 0 0\n0 9 1 -3e-7 0 1 0\n2 9 2 2 0 0 1\n\
                     0 1\n4 0 1 2 3 0.5\n3 2 3 4 1\n";
        let a = dir.join("a.ply");
        std::fs::write(&a, ascii).unwrap();
        // Binary: double coordinates, an int coordinate, ushort lists
        // named vertex_index, in little- and big-endian order.
        let binary = |big: bool| {
            let order = if big { "big" } else { "little" };
            let mut b = format!(
                "ply\nformat binary_{order}_endian 1.0\ncomment skipped lists and scalars around the ones read\n\
                 element vertex 4\nproperty double x\nproperty list short float weights\nproperty double y\n\
                 property int z\nelement face 2\nproperty list uchar ushort vertex_index\nproperty uchar flags\nend_header\n"
            )
            .into_bytes();
            for (i, v) in [[0.1f64, 0.2], [1.0 / 3.0, 0.0], [1.0, 1e-3], [-2.5, 7.0]]
                .iter()
                .enumerate()
            {
                for (k, x) in v.iter().enumerate() {
                    b.extend(if big {
                        x.to_be_bytes()
                    } else {
                        x.to_le_bytes()
                    });
                    if k == 0 {
                        // `i` weights after x.
                        let n = i as i16;
                        b.extend(if big {
                            n.to_be_bytes()
                        } else {
                            n.to_le_bytes()
                        });
                        for w in 0..i {
                            let w = w as f32 * 0.5;
                            b.extend(if big {
                                w.to_be_bytes()
                            } else {
                                w.to_le_bytes()
                            });
                        }
                    }
                }
                let z = i as i32 - 1;
                b.extend(if big {
                    z.to_be_bytes()
                } else {
                    z.to_le_bytes()
                });
            }
            for face in [&[0u16, 1, 2, 3][..], &[3, 2, 1]] {
                b.push(face.len() as u8);
                for k in face {
                    b.extend(if big {
                        k.to_be_bytes()
                    } else {
                        k.to_le_bytes()
                    });
                }
                b.push(7);
            }
            b
        };
        let (le, be) = (dir.join("le.ply"), dir.join("be.ply"));
        std::fs::write(&le, binary(false)).unwrap();
        std::fs::write(&be, binary(true)).unwrap();
        for p in [&a, &le, &be] {
            let (pos, nrm, tris) = ours(p);
            assert_eq!(tris.len(), 3, "{}", p.display());
            assert_eq!((pos, nrm, tris), by_default_element(p), "{}", p.display());
        }
        // A binary body cut short, or with a negative list length, is an
        // error naming the element it broke in.
        let whole = binary(false);
        let cut = dir.join("cut.ply");
        std::fs::write(&cut, &whole[..whole.len() - 4]).unwrap();
        let e = load_ply(&cut).expect_err("cut short").to_string();
        assert!(e.contains("face 1") && e.contains("ends inside"), "{e}");
        let negative = dir.join("negative.ply");
        let mut bad = whole.clone();
        let end = b"end_header\n";
        let body = bad.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        // The first vertex's weights' length: the i16 after its x.
        bad[body + 8..body + 10].copy_from_slice(&(-3i16).to_le_bytes());
        std::fs::write(&negative, &bad).unwrap();
        let e = load_ply(&negative).expect_err("negative").to_string();
        assert!(e.contains("vertex 0") && e.contains("negative (-3)"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
