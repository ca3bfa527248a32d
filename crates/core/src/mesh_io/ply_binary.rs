//! The body of a binary PLY file, read straight from its bytes.
//!
//! ply-rs-bw reads the header; its reader for a binary body went through
//! `Read::read_exact` for every scalar and allocated a `Vec` for every
//! face's list (the Country Kitchen's 295 files: 3.06 G instructions to
//! load, a fifth of them in `malloc` and `free`). Here each element's
//! properties become a plan once ([`Step`]) and the records are read by
//! it from the file's bytes, each face's indices appended to one list.
//! What is taken is what [`super::ply`]'s typed records take through
//! ply-rs-bw: a vertex's scalar `x y z` and `nx ny nz` as `f32` (a list of
//! that name leaves the component missing), a face's integer list
//! `vertex_indices` or `vertex_index` (a list of floats, or a scalar, of
//! that name counts as none).

use super::ply::{Records, Vertex};
use crate::error::{Location, SceneError};
use ply_rs_bw::ply::{ElementDef, Header, PropertyType};
use std::path::Path;

/// A scalar type of the header, copied into the plan: a plan that pointed
/// at the header's (not `Copy`) types read 9% more instructions on the
/// Country Kitchen.
#[derive(Clone, Copy)]
enum ScalarType {
    Char,
    UChar,
    Short,
    UShort,
    Int,
    UInt,
    Float,
    Double,
}

impl From<&ply_rs_bw::ply::ScalarType> for ScalarType {
    fn from(t: &ply_rs_bw::ply::ScalarType) -> Self {
        use ply_rs_bw::ply::ScalarType as S;
        match t {
            S::Char => Self::Char,
            S::UChar => Self::UChar,
            S::Short => Self::Short,
            S::UShort => Self::UShort,
            S::Int => Self::Int,
            S::UInt => Self::UInt,
            S::Float => Self::Float,
            S::Double => Self::Double,
        }
    }
}

/// One property of an element, as the reader treats it.
#[derive(Clone, Copy)]
enum Step {
    /// A scalar nothing here uses.
    Skip(ScalarType),
    /// A list nothing here uses: its length's type and its items'.
    SkipList(ScalarType, ScalarType),
    /// Vertex component `k` ([`Vertex::component`]) from a scalar.
    Component(usize, ScalarType),
    /// Vertex component `k` named by a list: read past, left missing.
    NoComponent(usize, ScalarType, ScalarType),
    /// A face's vertex list (`which`: 0 `vertex_indices`, 1
    /// `vertex_index`) of integers.
    Indices(usize, ScalarType, ScalarType),
}

/// Bytes a scalar of the header's type `t` takes in a binary body.
pub(super) fn size(t: &ply_rs_bw::ply::ScalarType) -> usize {
    ScalarType::from(t).size()
}

impl ScalarType {
    fn size(self) -> usize {
        match self {
            Self::Char | Self::UChar => 1,
            Self::Short | Self::UShort => 2,
            Self::Int | Self::UInt | Self::Float => 4,
            Self::Double => 8,
        }
    }
}

/// The plan of element `def`: `kind` 0 vertex, 1 face, 2 anything else.
fn plan(def: &ElementDef, kind: u8) -> Vec<Step> {
    const COMPONENTS: [&str; 6] = ["x", "y", "z", "nx", "ny", "nz"];
    const LISTS: [&str; 2] = ["vertex_indices", "vertex_index"];
    def.properties
        .values()
        .map(|p| {
            let component = COMPONENTS.iter().position(|c| *c == p.name);
            let list = LISTS.iter().position(|c| *c == p.name);
            let (n, t) = match &p.data_type {
                PropertyType::Scalar(t) => (None, t.into()),
                PropertyType::List(n, t) => (Some(n.into()), t.into()),
            };
            let float = matches!(t, ScalarType::Float | ScalarType::Double);
            match (n, kind, component, list) {
                (None, 0, Some(k), _) => Step::Component(k, t),
                (Some(n), 0, Some(k), _) => Step::NoComponent(k, n, t),
                (Some(n), 1, _, Some(w)) if !float => Step::Indices(w, n, t),
                (None, ..) => Step::Skip(t),
                (Some(n), ..) => Step::SkipList(n, t),
            }
        })
        .collect()
}

/// The body's bytes and where the reading stands.
struct Bytes<'a> {
    b: &'a [u8],
    at: usize,
    big: bool,
}

impl Bytes<'_> {
    /// The next `N` bytes in little-endian order.
    #[inline]
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let mut v: [u8; N] = self.b.get(self.at..self.at + N)?.try_into().ok()?;
        self.at += N;
        if self.big {
            v.reverse();
        }
        Some(v)
    }

    /// A scalar as `f32`, as ply-rs-bw's `Property::to_f32_lossy` gives it.
    #[inline]
    fn f32(&mut self, t: ScalarType) -> Option<f32> {
        Some(match t {
            ScalarType::Float => f32::from_le_bytes(self.take()?),
            ScalarType::Double => f64::from_le_bytes(self.take()?) as f32,
            t => self.int(t)? as f32,
        })
    }

    /// An integer scalar (None for a float, or past the end).
    #[inline]
    fn int(&mut self, t: ScalarType) -> Option<i64> {
        Some(match t {
            ScalarType::Char => i8::from_le_bytes(self.take()?).into(),
            ScalarType::UChar => u8::from_le_bytes(self.take()?).into(),
            ScalarType::Short => i16::from_le_bytes(self.take()?).into(),
            ScalarType::UShort => u16::from_le_bytes(self.take()?).into(),
            ScalarType::Int => i32::from_le_bytes(self.take()?).into(),
            ScalarType::UInt => u32::from_le_bytes(self.take()?).into(),
            ScalarType::Float | ScalarType::Double => return None,
        })
    }

    #[inline]
    fn skip(&mut self, n: usize) -> Option<()> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.b.len())?;
        self.at = end;
        Some(())
    }

    /// Past a list of `t` whose length (of type `n`) comes first.
    #[inline]
    fn skip_list(&mut self, n: ScalarType, t: ScalarType) -> Result<(), Fault> {
        let len = self.length(n)?;
        self.skip(len.saturating_mul(t.size())).ok_or(Fault::End)
    }

    /// A list's length (of integer type `n`).
    #[inline]
    fn length(&mut self, n: ScalarType) -> Result<usize, Fault> {
        let v = self.int(n).ok_or(Fault::End)?;
        usize::try_from(v).map_err(|_| Fault::NegativeLength(v))
    }
}

/// Why an element could not be read.
enum Fault {
    End,
    NegativeLength(i64),
}

/// Reads one record of an element by its plan into `vertex` (a vertex)
/// or `indices` (a face's lists: `lists[which]` their ranges).
fn record(
    r: &mut Bytes,
    steps: &[Step],
    vertex: &mut Vertex,
    indices: &mut Vec<i64>,
    lists: &mut [Option<(usize, usize)>; 2],
) -> Result<(), Fault> {
    for s in steps {
        match *s {
            Step::Skip(t) => r.skip(t.size()).ok_or(Fault::End)?,
            Step::SkipList(n, t) => r.skip_list(n, t)?,
            Step::Component(k, t) => *vertex.component(k) = Some(r.f32(t).ok_or(Fault::End)?),
            Step::NoComponent(k, n, t) => {
                r.skip_list(n, t)?;
                *vertex.component(k) = None;
            }
            Step::Indices(which, n, t) => {
                let len = r.length(n)?;
                let start = indices.len();
                for _ in 0..len {
                    indices.push(r.int(t).ok_or(Fault::End)?);
                }
                lists[which] = Some((start, len));
            }
        }
    }
    Ok(())
}

/// The vertices and faces of a binary body `b` (`big`: big-endian), its
/// elements in `header`'s order; errors name the element that failed.
pub(super) fn read(
    path: &Path,
    header: &Header,
    b: &[u8],
    big: bool,
) -> Result<Records, SceneError> {
    let mut r = Bytes { b, at: 0, big };
    let mut out = Records::default();
    for (name, def) in header.elements.iter() {
        let kind = match name.as_str() {
            "vertex" => 0,
            "face" => 1,
            _ => 2,
        };
        let steps = plan(def, kind);
        // The counts were checked against the file's size.
        match kind {
            0 => out.verts.reserve(def.count),
            1 => out.faces.reserve(def.count),
            _ => {}
        }
        for i in 0..def.count {
            let mut v = Vertex::default();
            let mut lists = [None; 2];
            record(&mut r, &steps, &mut v, &mut out.indices, &mut lists).map_err(|f| {
                SceneError::Invalid {
                    file: path.to_path_buf(),
                    location: Location::Element(format!("{name} {i}")),
                    message: match f {
                        Fault::End => "the file ends inside this element: it is shorter than \
                                       its header says (cut off while copying?)"
                            .into(),
                        Fault::NegativeLength(v) => format!("a list's length is negative ({v})"),
                    },
                }
            })?;
            match kind {
                0 => out.verts.push(v),
                1 => out.faces.push(lists[0].or(lists[1])),
                _ => {}
            }
        }
    }
    Ok(out)
}
