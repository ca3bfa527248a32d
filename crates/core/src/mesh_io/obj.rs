//! Wavefront OBJ: one pass over the text that checks each statement where
//! it stands (the error names its line) and builds the mesh as it goes.
//!
//! It reads what tobj read for us before, with the same results on every
//! file tobj accepted (a test compares the two) but one with a comment
//! after a statement, which is cut off here (tobj refused it after a
//! position or a face, and took it for part of a `usemtl` name):
//! positions (`v x y z`, with an optional `w` that divides them or an
//! ignored `r g b`), normals (`vn`), faces fanned into triangles from
//! their first vertex, `usemtl` naming a material of the libraries
//! (`mtllib`, one or several) named before it, the later of two equal
//! names winning.
//! Points, lines, texture coordinates, groups and smoothing statements are
//! checked or counted and otherwise skipped. Checking and building in one
//! pass is what makes it fast: the check alone used to cost as much as
//! tobj's parse, and the two together about 230 instructions a byte (the
//! room's 11 MB file took 2.6 G instructions to load, more than its BVH).

use super::{FileMaterial, MeshData, NO_NORMAL, parse_mtl};
use crate::error::{Location, SceneError};
use glam::Vec3;
use std::collections::HashMap;
use std::path::Path;

/// What a statement's line is wrong with; its location and file are added
/// by the caller.
enum Fault {
    Syntax(String),
    NonFinite(String),
    Index { index: i64, count: usize },
    Missing(std::path::PathBuf),
    Io(std::path::PathBuf, std::io::Error),
    Mtl(SceneError),
}

/// The file being read: what faces may refer to, and what they built.
#[derive(Default)]
struct Reader {
    out: MeshData,
    texcoords: i64,
    /// Per triangle, its normals' indices (or [`NO_NORMAL`]).
    tri_normals: Vec<[u32; 3]>,
    /// Some face lacks a normal at some vertex: the file is shaded flat.
    face_without_normals: bool,
    /// Material names of the libraries read so far, to their index.
    names: HashMap<String, u32>,
    material: Option<u32>,
    /// A face's vertices, kept between faces so that none allocates.
    face: Vec<(u32, Option<u32>)>,
}

pub(super) fn load_obj(path: &Path) -> Result<MeshData, SceneError> {
    let text = super::read_text(path)?;
    let mut r = Reader::default();
    // A statement continued over several lines (a line ending in `\`,
    // comments aside, as the OBJ specification allows) is joined here and
    // read as one, its faults placed at its first line; every other line
    // is read where it lies.
    let mut continued = String::new();
    let mut first = 0;
    for (i, raw) in lines(&text).enumerate() {
        // Only a line ending in `\` is looked at twice.
        if raw.trim_end().ends_with('\\')
            && let Some(head) = raw
                .split('#')
                .next()
                .unwrap_or("")
                .trim_end()
                .strip_suffix('\\')
        {
            if continued.is_empty() {
                first = i;
            }
            continued.push_str(head);
            continued.push(' ');
            continue;
        }
        let (statement, at) = if continued.is_empty() {
            (raw, i)
        } else {
            continued.push_str(raw);
            (continued.as_str(), first)
        };
        r.statement(path, statement)
            .map_err(|f| fault(path, at, f))?;
        continued.clear();
    }
    if !continued.is_empty() {
        r.statement(path, &continued)
            .map_err(|f| fault(path, first, f))?;
    }
    let mut out = r.out;
    if !r.face_without_normals && !out.normals.is_empty() {
        out.tri_normals = r.tri_normals;
    } else {
        if !out.normals.is_empty() {
            tracing::info!(file = %path.display(), "some faces give no normals: the file is shaded flat");
        }
        out.normals.clear();
    }
    Ok(out)
}

/// A statement's fault, placed at its line (`i`, from 0) of `path`.
fn fault(path: &Path, i: usize, f: Fault) -> SceneError {
    let (file, location) = (path.to_path_buf(), Location::line(i + 1));
    match f {
        Fault::Syntax(message) => SceneError::Syntax {
            file,
            location,
            message,
        },
        Fault::NonFinite(what) => SceneError::NonFinite {
            file,
            location,
            what,
        },
        Fault::Index { index, count } => SceneError::IndexOutOfRange {
            file,
            location,
            index,
            count,
        },
        Fault::Missing(missing) => SceneError::MissingFile {
            file,
            location,
            missing,
        },
        Fault::Io(file, source) => SceneError::Io { file, source },
        Fault::Mtl(e) => e,
    }
}

impl Reader {
    fn statement(&mut self, path: &Path, raw: &str) -> Result<(), Fault> {
        let line = match memchr::memchr(b'#', raw.as_bytes()) {
            // `#` is one byte in UTF-8, so a character ends before it.
            Some(k) => &raw[..k],
            None => raw,
        }
        .trim();
        // An ASCII line (every line of every exporter's file) is cut into
        // words byte by byte, at the very bytes `split_whitespace` cuts
        // at there; any other is cut at Unicode whitespace as tobj cut it.
        if line.is_ascii() {
            self.words(path, line, AsciiWords { s: line, at: 0 })
        } else {
            self.words(path, line, line.split_whitespace())
        }
    }

    /// The statement on `line`, cut into words by `it`.
    fn words<'a>(
        &mut self,
        path: &Path,
        line: &str,
        mut it: impl Iterator<Item = &'a str>,
    ) -> Result<(), Fault> {
        match it.next() {
            Some("v") => self.position(it),
            Some("vn") => {
                let v = vector3(it).map_err(|m| Fault::Syntax(format!("normal {m}")))?;
                self.out.normals.push(v);
                Ok(())
            }
            Some("vt") => {
                self.texcoords += 1;
                Ok(())
            }
            Some("f") => self.face(it),
            // Points and lines are skipped, but their vertices must exist.
            Some(kind @ ("l" | "p")) => {
                let least = if kind == "l" { 2 } else { 1 };
                let mut count = 0;
                for v in it {
                    self.vertex(kind, v)?;
                    count += 1;
                }
                enough(kind, count, least)
            }
            Some("usemtl") => {
                let name = line["usemtl".len()..].trim();
                if name.is_empty() {
                    return Err(Fault::Syntax("usemtl names no material".into()));
                }
                // A name no library defines leaves the faces without one.
                self.material = self.names.get(name).copied();
                Ok(())
            }
            Some("mtllib") => self.libraries(path, line["mtllib".len()..].trim()),
            _ => Ok(()),
        }
    }

    fn position<'a>(&mut self, it: impl Iterator<Item = &'a str>) -> Result<(), Fault> {
        let (comps, n) = tokens(it);
        if n < 3 {
            return Err(Fault::Syntax(format!(
                "vertex needs 3 coordinates, found {n}"
            )));
        }
        let mut p = [0f32; 3];
        for (c, x) in comps.iter().zip(&mut p) {
            *x = number(c)?;
            if !x.is_finite() {
                return Err(Fault::NonFinite(format!("vertex coordinate {c}")));
            }
        }
        match n {
            // A weight divides the coordinates (tobj did so too).
            4 => {
                let w = number(comps[3])?;
                if w == 0.0 {
                    return Err(Fault::Syntax("vertex weight 0 scales by zero".into()));
                }
                for x in &mut p {
                    *x /= w;
                }
                if p.iter().any(|x| !x.is_finite()) {
                    return Err(Fault::NonFinite(format!("vertex weight {}", comps[3])));
                }
            }
            // A colour, which nothing here uses.
            3 | 6 | 7 => {}
            _ => {
                return Err(Fault::Syntax(format!(
                    "vertex has {n} values: expected 3, 4 (with a weight) or 6 (with a colour)"
                )));
            }
        }
        self.out.positions.push(Vec3::from(p));
        Ok(())
    }

    /// One vertex of a statement of `kind`: its position and normal.
    fn vertex(&self, kind: &str, v: &str) -> Result<(u32, Option<u32>), Fault> {
        let malformed = || Fault::Syntax(format!("{kind} vertex '{v}' is not an index"));
        let mut parts = v.as_bytes().split(|&b| b == b'/');
        let counts = [
            self.out.positions.len() as i64,
            self.texcoords,
            self.out.normals.len() as i64,
        ];
        let mut got = [None; 3];
        for (k, slot) in got.iter_mut().enumerate() {
            match parts.next() {
                Some([]) if k > 0 => {}
                Some(idx) => {
                    let i = index(idx).ok_or_else(malformed)?;
                    let n = counts[k];
                    let resolved = if i < 0 { n.saturating_add(i) } else { i - 1 };
                    if i == 0 || resolved < 0 || resolved >= n {
                        return Err(Fault::Index {
                            index: i,
                            count: n as usize,
                        });
                    }
                    *slot = Some(resolved as u32);
                }
                None => {}
            }
        }
        if parts.next().is_some() {
            return Err(malformed());
        }
        // The position is there: an empty one failed to parse above.
        Ok((got[0].unwrap_or(0), got[2]))
    }

    fn face<'a>(&mut self, it: impl Iterator<Item = &'a str>) -> Result<(), Fault> {
        let mut face = std::mem::take(&mut self.face);
        face.clear();
        for v in it {
            face.push(self.vertex("f", v)?);
        }
        enough("f", face.len(), 3)?;
        self.face_without_normals |= face.iter().any(|v| v.1.is_none());
        for k in 2..face.len() {
            let (a, b, c) = (face[0], face[k - 1], face[k]);
            self.out.triangles.push([a.0, b.0, c.0]);
            self.out.tri_material.push(self.material);
            self.tri_normals.push(match (a.1, b.1, c.1) {
                (Some(x), Some(y), Some(z)) => [x, y, z],
                _ => NO_NORMAL,
            });
        }
        self.face = face;
        Ok(())
    }

    /// The libraries of an `mtllib` statement: the OBJ specification
    /// lets it name several, separated by spaces, and exporters write one
    /// name that may hold spaces (tobj read only that). The whole rest of
    /// the line is one library when such a file exists; otherwise each
    /// word is one, read in order.
    fn libraries(&mut self, path: &Path, rest: &str) -> Result<(), Fault> {
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut names = rest.split_whitespace();
        if names.clone().nth(1).is_none() || dir.join(rest).is_file() {
            return self.library(path, rest);
        }
        names.try_for_each(|name| self.library(path, name))
    }

    /// Reads a material library: its materials are numbered after those
    /// before it, and its names shadow theirs.
    fn library(&mut self, path: &Path, name: &str) -> Result<(), Fault> {
        let p = path.parent().unwrap_or(Path::new(".")).join(name);
        let text = std::fs::read_to_string(&p).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => Fault::Missing(p.clone()),
            _ => Fault::Io(p.clone(), e),
        })?;
        let mats: Vec<FileMaterial> = parse_mtl(&p, &text).map_err(Fault::Mtl)?;
        for m in mats {
            let index = self.out.materials.len() as u32;
            self.names.insert(m.name.clone(), index);
            self.out.materials.push(m);
        }
        Ok(())
    }
}

/// The lines of `text`, as `text.split('\n')` gives them (the piece
/// after a last newline included), found by `memchr`: `split` looks for
/// each line's end afresh, which on the room's 11 MB file cost a fifth
/// of the reader.
fn lines(text: &str) -> impl Iterator<Item = &str> {
    let mut start = 0;
    memchr::memchr_iter(b'\n', text.as_bytes())
        .map(Some)
        .chain(std::iter::once(None))
        .map(move |end| {
            let end = end.unwrap_or(text.len());
            // `\n` is one byte in UTF-8: both ends are character bounds.
            let line = &text[start..end];
            start = end + 1;
            line
        })
}

/// The words of an ASCII line: the runs between the bytes that are
/// whitespace to `char::is_whitespace` (tab, line feed, vertical tab,
/// form feed, carriage return and space; the rest of Unicode's
/// whitespace is not ASCII), as `str::split_whitespace` finds them, one
/// byte at a time instead of one decoded character.
struct AsciiWords<'a> {
    s: &'a str,
    at: usize,
}

impl<'a> Iterator for AsciiWords<'a> {
    type Item = &'a str;

    #[inline]
    fn next(&mut self) -> Option<&'a str> {
        let b = self.s.as_bytes();
        let space = |c: u8| c == b' ' || c.wrapping_sub(b'\t') < 5;
        let mut i = self.at;
        while i < b.len() && space(b[i]) {
            i += 1;
        }
        if i == b.len() {
            self.at = i;
            return None;
        }
        let start = i;
        while i < b.len() && !space(b[i]) {
            i += 1;
        }
        self.at = i;
        Some(&self.s[start..i])
    }
}

/// A vertex's index as `str::parse::<i64>` reads it (an optional sign,
/// then at least one decimal digit and nothing else, within `i64`),
/// without first checking the bytes are UTF-8 and then going over them
/// again.
fn index(b: &[u8]) -> Option<i64> {
    let (negative, digits) = match b {
        [b'-', rest @ ..] => (true, rest),
        [b'+', rest @ ..] => (false, rest),
        _ => (false, b),
    };
    if digits.is_empty() {
        return None;
    }
    let mut n: i64 = 0;
    for &c in digits {
        let d = i64::from(c.wrapping_sub(b'0'));
        if d > 9 {
            return None;
        }
        // Built on the sign's side, so that `i64::MIN` reads as std reads it.
        n = n.checked_mul(10)?;
        n = if negative {
            n.checked_sub(d)?
        } else {
            n.checked_add(d)?
        };
    }
    Some(n)
}

fn number(c: &str) -> Result<f32, Fault> {
    c.parse()
        .map_err(|_| Fault::Syntax(format!("'{c}' is not a number")))
}

fn vector3<'a>(it: impl Iterator<Item = &'a str>) -> Result<Vec3, String> {
    let (comps, n) = tokens(it);
    super::finite3(&comps[..n.min(comps.len())]).map(Vec3::from)
}

/// The first eight tokens of a statement, and how many it has in all:
/// no statement read here needs more, and none allocates.
fn tokens<'a>(it: impl Iterator<Item = &'a str>) -> ([&'a str; 8], usize) {
    let mut out = [""; 8];
    let mut n = 0;
    for t in it {
        if let Some(slot) = out.get_mut(n) {
            *slot = t;
        }
        n += 1;
    }
    (out, n)
}

fn enough(kind: &str, count: usize, least: usize) -> Result<(), Fault> {
    if count < least {
        return Err(Fault::Syntax(format!(
            "'{kind}' needs at least {least} vertices, found {count}"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    /// A triangle as both readers give it: its positions' and normals'
    /// bits and its material's index.
    type Tri = ([[u32; 3]; 3], Option<[[u32; 3]; 3]>, Option<u32>);

    fn bits(v: Vec3) -> [u32; 3] {
        v.to_array().map(f32::to_bits)
    }

    fn ours(path: &Path) -> (Vec<Tri>, Vec<FileMaterial>) {
        let m = load_obj(path).expect("our reader loads it");
        let tris = m
            .triangles
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let n = m.tri_normals.get(i).filter(|n| **n != NO_NORMAL);
                (
                    t.map(|v| bits(m.positions[v as usize])),
                    n.map(|n| n.map(|v| bits(m.normals[v as usize]))),
                    m.tri_material[i],
                )
            })
            .collect();
        (tris, m.materials)
    }

    /// What locus read before: tobj's models, asked for material names
    /// only, flattened model by model; normals kept only when every face
    /// gives them at every vertex (`all_normals`, which the old check
    /// decided).
    fn tobj_reads(path: &Path, all_normals: bool) -> Vec<Tri> {
        let dir = path.parent().unwrap().to_path_buf();
        let names = |p: &Path| -> tobj::MTLLoadResult {
            let full = dir.join(p);
            let text =
                std::fs::read_to_string(&full).map_err(|_| tobj::LoadError::OpenFileFailed)?;
            let mats = parse_mtl(&full, &text).map_err(|_| tobj::LoadError::MaterialParseError)?;
            let names: String = mats
                .iter()
                .map(|m| format!("newmtl {}\n", m.name))
                .collect();
            tobj::load_mtl_buf(&mut names.as_bytes())
        };
        let opts = tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ignore_points: true,
            ignore_lines: true,
        };
        let text = std::fs::read_to_string(path).unwrap();
        let (models, _) =
            tobj::load_obj_buf(&mut text.as_bytes(), &opts, names).expect("tobj loads it");
        let mut out = Vec::new();
        for m in models {
            let p = |i: u32| bits(Vec3::from_slice(&m.mesh.positions[3 * i as usize..]));
            let n = |i: u32| bits(Vec3::from_slice(&m.mesh.normals[3 * i as usize..]));
            for (k, t) in m.mesh.indices.chunks_exact(3).enumerate() {
                let normals = (all_normals && !m.mesh.normal_indices.is_empty()).then(|| {
                    let ni = &m.mesh.normal_indices[3 * k..3 * k + 3];
                    [n(ni[0]), n(ni[1]), n(ni[2])]
                });
                out.push((
                    [p(t[0]), p(t[1]), p(t[2])],
                    normals,
                    m.mesh.material_id.map(|i| i as u32),
                ));
            }
        }
        out
    }

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    /// Asserts that `p` fails to load with an error at `line` that says
    /// each of `says` (a file name, a value, what is wrong).
    fn fails_at(p: &Path, line: usize, says: &[&str]) {
        let e = load_obj(p).expect_err("a fault").to_string();
        assert!(
            e.contains(&format!("line {line}")) && says.iter().all(|w| e.contains(w)),
            "{}: expected line {line} and {says:?}, got {e}",
            p.display()
        );
    }

    /// On every file tobj read, this reader gives the same triangles, bit
    /// for bit, in the same order, with the same materials and normals:
    /// quads and polygons fanned, negative and slashed indices, weights,
    /// colours, comments, CRLF, groups, names shadowed by a later library,
    /// `usemtl` of a name no library has, and the generated room.
    #[test]
    fn reads_what_tobj_read() {
        let dir = std::env::temp_dir().join(format!("locus-obj-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        write(
            &dir,
            "a.mtl",
            "newmtl red\nKd 0.8 0.1 0.1\nnewmtl white\nKd 0.7 0.7 0.7\n",
        );
        write(
            &dir,
            "b.mtl",
            "newmtl lamp\nKd 0 0 0\nKe 4 4 4\nnewmtl red\nKd 0.5 0 0\n",
        );
        let mixed = write(
            &dir,
            "mixed.obj",
            "# comment\r\nmtllib a.mtl\r\nv 0 0 0\r\nv 1 0 0\nv 1 1 0 2\nv 0 1 0\n\
             v 0.5 1.5 0\nv -1 0.25 3.5\nvt 0 0\nvt 1 0\n\
             g first\nusemtl red\nf 1 2 3\nf 1/1 2/2 3/1 4/2\nf -6 -5 -4 -3 -2\n\
             o second\nusemtl nowhere\nf 2 3 6\nmtllib b.mtl\nusemtl red\nf 1 3 5\n\
             s 1\nusemtl lamp\nl 1 2\np 3\nf 4 5 6\nusemtl white\nf 6 5 4 3\n",
        );
        let normals = write(
            &dir,
            "normals.obj",
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nvn 0 0.6 0.8\n\
             f 1//1 2//1 3//2\nf 1//2 3//1 4//2\n",
        );
        // Separators beyond ASCII (an ideographic space, a no-break space)
        // separate tokens, as in tobj.
        let spaces = write(
            &dir,
            "spaces.obj",
            "v\u{3000}0 0 0\nv 1\u{a0}0 0\nv 1 1 0\nv 0 1 0\nf\u{3000}1 2 3\nf 1 3\u{2003}4\n",
        );
        let colours = write(
            &dir,
            "colours.obj",
            "v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 1 1 0 0 0 1\nv 0 1 0 1 1 1\nf 1 2 3 4\nf 4 3 2\n",
        );
        let (room, _) = crate::generate::write_room(
            &dir,
            "room",
            &crate::generate::RoomParams {
                detail: 2,
                ..Default::default()
            },
        )
        .unwrap();
        let room = room.with_extension("obj");
        let cornell =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/cornell-box/cornell.obj");
        for (path, all_normals) in [
            (&mixed, false),
            (&normals, true),
            (&colours, false),
            (&spaces, false),
            (&room, false),
            (&cornell, false),
        ] {
            let (tris, materials) = ours(path);
            assert!(!tris.is_empty(), "{}", path.display());
            assert_eq!(tris, tobj_reads(path, all_normals), "{}", path.display());
            if path == &mixed {
                let names: Vec<&str> = materials.iter().map(|m| m.name.as_str()).collect();
                assert_eq!(names, ["red", "white", "lamp", "red"]);
                // The later library's red, the lamp, and no material.
                assert_eq!(tris[6].2, None);
                assert_eq!(tris[7].2, Some(3));
                assert_eq!(tris[8].2, Some(2));
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The byte-level pieces read as the `str` methods they replace:
    /// `lines` as `split('\n')`, `AsciiWords` as `split_whitespace` on
    /// ASCII text (the vertical tab, which `u8::is_ascii_whitespace` does
    /// not count, included) and `index` as `parse::<i64>`, over strings
    /// built from the bytes that matter to each (digits, signs, slashes,
    /// every ASCII whitespace byte, others) and the edges of `i64`.
    #[test]
    fn the_byte_readers_read_as_std_does() {
        const BYTES: &[u8] = b"0123456789+-/ \t\n\x0b\x0c\rx#.e";
        let mut checked = 0;
        for i in 0..20_000u64 {
            let k = crate::sampler::SampleKey::independent(i, 0, 17);
            let len = (k.get1d(0) * 12.0) as u32;
            let text: String = (0..len)
                .map(|d| {
                    BYTES[(k.get1d(d + 1) * BYTES.len() as f32) as usize % BYTES.len()] as char
                })
                .collect();
            assert!(lines(&text).eq(text.split('\n')), "{text:?}");
            let words = AsciiWords { s: &text, at: 0 };
            assert!(words.eq(text.split_whitespace()), "{text:?}");
            assert_eq!(index(text.as_bytes()), text.parse::<i64>().ok(), "{text:?}");
            checked += text.parse::<i64>().is_ok() as u32;
        }
        for edge in [
            "9223372036854775807",
            "9223372036854775808",
            "-9223372036854775808",
            "-9223372036854775809",
            "+0",
            "-0",
            "+",
            "-",
            "",
            "00000000000000000000012",
            "99999999999999999999",
        ] {
            assert_eq!(index(edge.as_bytes()), edge.parse::<i64>().ok(), "{edge:?}");
        }
        // Enough of the strings were numbers for the comparison to mean
        // something on both sides.
        assert!(checked > 1000, "{checked} of the strings were indices");
    }

    /// Statements tobj crashed on or refused without a place are errors
    /// naming their line here.
    #[test]
    fn faults_name_their_line() {
        let dir = std::env::temp_dir().join(format!("locus-obj-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (text, line, what) in [
            ("v 0 0 0\nv 1 0 0 0\n", 2, "scales by zero"),
            ("v 0 0 0\n\nv 1 0 0 1 1\n", 3, "5 values"),
            (
                "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 99999999999999999999\n",
                4,
                "not an index",
            ),
            ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 -4\n", 4, "-4"),
            ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1/1 2 3\n", 4, "out of range"),
            (
                "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2/ 3//\nf 1 2\n",
                5,
                "at least 3",
            ),
            ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1/// 2 3\n", 4, "not an index"),
            ("usemtl\n", 1, "names no material"),
            ("v 1e39 0 0\n", 1, "1e39"),
            ("v 0 0 0\nv 1 0 0 1e-45\n", 2, "weight"),
        ] {
            let p = write(&dir, "bad.obj", text);
            fails_at(&p, line, &[what]);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// `mtllib` naming several libraries, or one whose name holds a space;
    /// MTL colours given as one grey value; texture maps skipped; and the
    /// faults of each named at their line.
    #[test]
    fn libraries_and_colours_as_the_specifications_write_them() {
        let dir = std::env::temp_dir().join(format!("locus-obj-mtl-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        write(&dir, "a.mtl", "newmtl red\nKd 0.8 0.1 0.1\n");
        write(
            &dir,
            "b.mtl",
            "newmtl grey\nKd 0.5\nmap_Kd grey.png\nnewmtl lamp\nKd 0\nKe 4\n",
        );
        write(&dir, "my lib.mtl", "newmtl spaced\nKd 0.2 0.3 0.4\n");
        let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        let p = write(
            &dir,
            "several.obj",
            &format!(
                "mtllib a.mtl b.mtl\n{tri}usemtl lamp\nf 1 2 3\nusemtl grey\nf 1 2 3\nusemtl red\nf 1 2 3\n"
            ),
        );
        let m = load_obj(&p).unwrap();
        let used: Vec<(Vec3, Vec3)> = m
            .tri_material
            .iter()
            .map(|t| {
                let f = &m.materials[t.expect("every face has a material") as usize];
                (f.albedo, f.emission)
            })
            .collect();
        assert_eq!(
            used,
            [
                (Vec3::ZERO, Vec3::splat(4.0)),
                (Vec3::splat(0.5), Vec3::ZERO),
                (Vec3::new(0.8, 0.1, 0.1), Vec3::ZERO),
            ]
        );
        let p = write(
            &dir,
            "spaced.obj",
            &format!("mtllib my lib.mtl\n{tri}usemtl spaced\nf 1 2 3\n"),
        );
        let m = load_obj(&p).unwrap();
        let f = &m.materials[m.tri_material[0].unwrap() as usize];
        assert_eq!(f.albedo, Vec3::new(0.2, 0.3, 0.4));
        // A missing library among several is named, at the statement.
        let p = write(
            &dir,
            "gone.obj",
            &format!("{tri}mtllib a.mtl nowhere.mtl\n"),
        );
        fails_at(&p, 4, &["nowhere.mtl"]);
        for (text, line, what) in [
            (
                "newmtl x\nKd 0.5 0.5\n",
                2,
                "3 components (or 1 for grey), found 2",
            ),
            (
                "newmtl x\n\nKe spectral x.rfl 1\n",
                3,
                "Ke spectral is not supported",
            ),
            ("newmtl x\nKd xyz 0.5 0.5 0.5\n", 2, "Kd xyz"),
            ("newmtl x\nKd 2\n", 2, "albedo"),
            ("newmtl x\nKe -1\n", 2, "Ke"),
        ] {
            write(&dir, "bad.mtl", text);
            let p = write(&dir, "bad.obj", &format!("mtllib bad.mtl\n{tri}"));
            fails_at(&p, line, &["bad.mtl", what]);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A statement continued over lines with `\` reads as one, and a
    /// fault in it is placed at its first line; a comment that ends in a
    /// backslash continues nothing.
    #[test]
    fn continued_statements_read_as_one() {
        let dir = std::env::temp_dir().join(format!("locus-obj-cont-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = write(
            &dir,
            "c.obj",
            "# exported to C:\\models\\\r\nv 0 0 \\\r\n0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 \\\n  3 \\  \n 4\n",
        );
        let m = load_obj(&p).unwrap();
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.triangles, [[0, 1, 2], [0, 2, 3]]);
        let p = write(
            &dir,
            "bad.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 \\\n2 \\\n9\nv 1 1 1\n",
        );
        fails_at(&p, 4, &["out of range"]);
        // A backslash on the last line continues into nothing.
        let p = write(&dir, "end.obj", "v 0 0 \\");
        fails_at(&p, 1, &["3 coordinates"]);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
