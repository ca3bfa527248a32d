//! locus-core: the render core that the locus farm distributes.
//!
//! A scene file ([`scene`]) is loaded with its meshes ([`mesh_io`]) into a
//! flat list of triangles whose index is their global id everywhere in
//! locus. Two spatial structures are built over it: the [`octree`], whose
//! leaves are the unit of data ownership in the farm, and the BVH of
//! [`accel`] (obvhs CWBVH with the watertight test of [`geometry`]), which
//! answers ray queries clipped to any parameter interval; [`accel_set`]
//! traces several BVHs as one, so a build never needs more memory than a
//! budget allows, and joins them into one where nothing will be added. [`region`] is the processor map and the one routine that
//! traces a ray through what a worker holds.
//!
//! [`path`] is the path state machine, the one implementation of every
//! path vertex (trace, shade, next-event estimation, continuation,
//! directional-cache lookup, finish) for one machine and the farm alike;
//! the per-vertex physics is [`integrator`]'s `shade`. Every random number
//! comes from [`sampler`] as a pure function of (pixel, sample, dimension,
//! seed): Owen-scrambled Sobol by default, independent on request; area
//! lights are sampled from [`light`]. [`render`] runs the
//! kernel over tiles on a rayon pool, each pixel's samples in the progressive
//! [`passes`] the farm renders too, and counts work in [`stats`]; with
//! adaptive sampling, [`spread`] gives each pass's samples to the pixels
//! by their noise. Images
//! leave through [`image_io`], are compared with [`metrics`], and reports
//! are written by [`report`]; [`bulk`] is the wire form of the long lists
//! (triangles, ids, materials) a job ships. [`dircache`] is Jansen and Reinhard's directional
//! cache: per octree leaf, the radiance arriving from beyond a locality
//! radius, by direction. [`irradiance`] is Ward's irradiance cache for the
//! first vertex's diffuse interreflection, filled by an overture before
//! the render. [`radiosity`] is the second job kind, Stürzlinger,
//! Schaufler and Volkert's progressive refinement radiosity, which shares
//! the scene, the BVH and the image writers. [`generate`] writes the generated scenes (the
//! benchmarks, in the `locus` crate, use them too).

// These docs are for the crate's developers, who read them with
// `cargo doc --document-private-items`: links to private items resolve there.
#![allow(rustdoc::private_intra_doc_links)]

pub mod accel;
pub mod accel_set;
pub mod bulk;
pub mod dircache;
pub mod error;
pub mod generate;
pub mod geometry;
pub mod image_io;
pub mod integrator;
pub mod irradiance;
pub mod light;
pub mod limits;
pub mod mesh_io;
pub mod metrics;
pub mod octree;
pub mod passes;
pub mod path;
pub mod radiosity;
pub mod region;
pub mod render;
pub mod report;
pub mod sampler;
pub mod scene;
pub mod spread;
pub mod stats;
