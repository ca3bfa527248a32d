//! locus-core: the render core that the locus farm distributes.
//!
//! A scene file ([`scene`]) is loaded with its meshes ([`mesh_io`]) into a
//! flat list of triangles whose index is their global id everywhere in
//! locus. Two spatial structures are built over it: the [`octree`], whose
//! leaves are the unit of data ownership in the farm, and the BVH of
//! [`accel`] (obvhs CWBVH with the watertight test of [`geometry`]), which
//! answers ray queries clipped to any parameter interval or restricted to any
//! set of octree leaves. The path tracer of [`integrator`] draws every random
//! number from [`sampler`] as a pure function of (pixel, sample, dimension,
//! seed) and samples area lights from [`light`]; [`render`] runs it over
//! tiles on a rayon pool and counts work in [`stats`]. Images leave through
//! [`image_io`], are compared with [`metrics`], and reports are written by
//! [`report`]. [`dircache`] is paper 000's directional cache: per octree
//! leaf, the radiance arriving from beyond a locality radius, by direction. [`generate`] writes the generated conference-like room.

pub mod accel;
pub mod bench;
pub mod dircache;
pub mod error;
pub mod generate;
pub mod geometry;
pub mod image_io;
pub mod integrator;
pub mod light;
pub mod mesh_io;
pub mod metrics;
pub mod octree;
pub mod region;
pub mod render;
pub mod report;
pub mod sampler;
pub mod scene;
pub mod stats;
