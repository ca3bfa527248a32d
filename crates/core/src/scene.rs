//! The scene: its TOML description, and the flat triangle soup the renderer
//! and the farm work on.
//!
//! A scene file names a camera, materials, area lights, meshes (by path
//! relative to the scene file, with an optional transform) and render
//! settings; see the README for a complete example. Loading resolves every
//! mesh into global triangles with a material id each. Degenerate
//! (zero-area) triangles are dropped and counted.

use crate::accel::BvhSetting;
use crate::error::{Location, SceneError};
use crate::geometry::{FLAT, Ray, tri_area_f64};
use crate::mesh_io;
use crate::octree::OctreeParams;
use crate::sampler::Sampler;
use glam::{Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The one reflectance model locus needs for its scenes: Lambertian
/// diffuse with an optional diffuse area emission (one-sided, on the side
/// the geometric normal points to, i.e. counter-clockwise winding).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub name: String,
    pub albedo: Vec3,
    pub emission: Vec3,
}

impl Material {
    pub fn is_emissive(&self) -> bool {
        self.emission.max_element() > 0.0
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub position: Vec3,
    pub look_at: Vec3,
    pub up: Vec3,
    /// Vertical field of view in degrees.
    pub fov_y: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// The camera samples of a job of `spp` samples a pixel.
    #[inline]
    pub fn samples(&self, spp: u32) -> u64 {
        self.width as u64 * self.height as u64 * spp as u64
    }

    /// The ray through film position (x + u, y + v), with y down the image.
    #[inline]
    pub fn ray(&self, x: u32, y: u32, u: [f32; 2]) -> Ray {
        self.view().ray(x, y, u)
    }

    /// What every camera ray shares, computed once: the path kernel holds
    /// it, so a camera ray costs no normalisations or tangent of its own.
    pub fn view(&self) -> CameraView {
        let fwd = (self.look_at - self.position).normalize();
        let right = fwd.cross(self.up).normalize();
        CameraView {
            position: self.position,
            fwd,
            right,
            up: right.cross(fwd),
            tan: (self.fov_y.to_radians() * 0.5).tan(),
            aspect: self.width as f32 / self.height as f32,
            width: self.width as f32,
            height: self.height as f32,
        }
    }
}

/// A camera's frame and film, precomputed by [`Camera::view`]. Its rays are
/// [`Camera::ray`]'s to the bit: the same operations in the same order.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraView {
    position: Vec3,
    fwd: Vec3,
    right: Vec3,
    up: Vec3,
    tan: f32,
    aspect: f32,
    width: f32,
    height: f32,
}

impl CameraView {
    /// The ray through film position (x + u, y + v), with y down the image.
    #[inline]
    pub fn ray(&self, x: u32, y: u32, u: [f32; 2]) -> Ray {
        let sx = ((x as f32 + u[0]) / self.width * 2.0 - 1.0) * self.tan * self.aspect;
        let sy = (1.0 - (y as f32 + u[1]) / self.height * 2.0) * self.tan;
        Ray::new(
            self.position,
            (self.fwd + self.right * sx + self.up * sy).normalize(),
        )
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    pub sampler: Sampler,
    pub octree: OctreeParams,
    /// Stop at the end of the first pass whose estimated relMSE is at or
    /// below this ([`crate::metrics::meets_target`]); `spp` is then the
    /// most samples a pixel gets.
    pub target_rel_mse: Option<f64>,
    /// Adaptive sampling: the passes after the pilot spread their samples
    /// over the pixels by each one's noise ([`crate::spread`]); `spp` is
    /// then the mean a pixel gets.
    pub adaptive_sampling: bool,
    /// The quality of the job's BVHs ([`BvhSetting`]); `auto` unless the
    /// scene file or the command line says otherwise.
    pub bvh: BvhSetting,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            spp: 16,
            max_depth: 8,
            seed: 0,
            sampler: Sampler::default(),
            octree: OctreeParams::default(),
            target_rel_mse: None,
            adaptive_sampling: false,
            bvh: BvhSetting::Auto,
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoadStats {
    pub meshes: usize,
    pub triangles_read: usize,
    pub degenerate_dropped: usize,
    /// Triangles kept with shading normals from their mesh file.
    #[serde(default)]
    pub shaded: usize,
}

/// A loaded scene: triangles with global ids (their index here).
#[derive(Clone, Debug)]
pub struct Scene {
    pub path: PathBuf,
    pub camera: Camera,
    pub settings: RenderSettings,
    pub materials: Vec<Material>,
    pub tris: Vec<[Vec3; 3]>,
    pub tri_material: Vec<u32>,
    /// Shading normals at each triangle's vertices, from its mesh file
    /// ([`crate::geometry::FLAT`] for a triangle without); empty when no
    /// triangle has any.
    pub tri_normals: Vec<[Vec3; 3]>,
    pub load_stats: LoadStats,
}

// ---- the TOML file -------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    camera: toml::Spanned<CameraDesc>,
    #[serde(default)]
    render: RenderDesc,
    #[serde(default)]
    octree: Option<OctreeDesc>,
    #[serde(default)]
    materials: BTreeMap<String, toml::Spanned<MaterialDesc>>,
    #[serde(default)]
    light: Vec<toml::Spanned<QuadLightDesc>>,
    #[serde(default)]
    mesh: Vec<toml::Spanned<MeshDesc>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraDesc {
    position: [f32; 3],
    look_at: [f32; 3],
    #[serde(default = "default_up")]
    up: [f32; 3],
    fov_y: f32,
    resolution: [u32; 2],
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RenderDesc {
    #[serde(default = "d_spp")]
    spp: u32,
    #[serde(default = "d_depth")]
    max_depth: u32,
    #[serde(default)]
    seed: u64,
    /// "sobol" (the default) or "independent".
    #[serde(default)]
    sampler: Sampler,
    /// Stop once the estimated relMSE is at or below this.
    #[serde(default)]
    target_rel_mse: Option<f64>,
    /// Spread each pass's samples by the pixels' noise.
    #[serde(default)]
    adaptive_sampling: bool,
    /// "auto" (the default), "full" or "quick".
    #[serde(default)]
    bvh: BvhSetting,
}
fn d_spp() -> u32 {
    16
}
fn d_depth() -> u32 {
    8
}
impl Default for RenderDesc {
    fn default() -> Self {
        Self {
            spp: d_spp(),
            max_depth: d_depth(),
            seed: 0,
            sampler: Sampler::default(),
            target_rel_mse: None,
            adaptive_sampling: false,
            bvh: BvhSetting::Auto,
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct OctreeDesc {
    max_leaf_tris: Option<usize>,
    max_depth: Option<u32>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MaterialDesc {
    #[serde(default = "d_albedo")]
    albedo: [f32; 3],
    #[serde(default)]
    emission: [f32; 3],
}
fn d_albedo() -> [f32; 3] {
    [0.8, 0.8, 0.8]
}

/// A rectangular area light: the parallelogram `corner + s*edge_a +
/// t*edge_b`, emitting to the side of `edge_a x edge_b`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct QuadLightDesc {
    corner: [f32; 3],
    edge_a: [f32; 3],
    edge_b: [f32; 3],
    emission: [f32; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MeshDesc {
    file: String,
    material: Option<String>,
    #[serde(default)]
    transform: TransformDesc,
}

/// Applied as scale, then rotation, then translation.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct TransformDesc {
    translate: Option<[f32; 3]>,
    scale: Option<Scale>,
    /// Axis (x, y, z) and angle in degrees.
    rotate: Option<[f32; 4]>,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum Scale {
    Uniform(f32),
    Axes([f32; 3]),
}

impl TransformDesc {
    fn matrix(&self) -> Mat4 {
        let s = match self.scale {
            None => Vec3::ONE,
            Some(Scale::Uniform(k)) => Vec3::splat(k),
            Some(Scale::Axes(a)) => Vec3::from(a),
        };
        let r = match self.rotate {
            Some([x, y, z, deg]) => {
                Quat::from_axis_angle(Vec3::new(x, y, z).normalize(), deg.to_radians())
            }
            None => Quat::IDENTITY,
        };
        Mat4::from_scale_rotation_translation(s, r, Vec3::from(self.translate.unwrap_or([0.0; 3])))
    }
    fn values(&self) -> Vec<f32> {
        let mut v = Vec::new();
        v.extend(self.translate.iter().flatten());
        v.extend(self.rotate.iter().flatten());
        match self.scale {
            Some(Scale::Uniform(k)) => v.push(k),
            Some(Scale::Axes(a)) => v.extend(a),
            None => {}
        }
        v
    }
}

fn check_finite(
    file: &Path,
    text: &str,
    span: std::ops::Range<usize>,
    what: &str,
    vals: &[f32],
) -> Result<(), SceneError> {
    if vals.iter().all(|v| v.is_finite()) {
        return Ok(());
    }
    Err(SceneError::NonFinite {
        file: file.to_path_buf(),
        location: Location::of_offset(text, span.start),
        what: what.into(),
    })
}

impl Scene {
    /// Loads a scene file and every mesh it references.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            file: path.to_path_buf(),
            source,
        })?;
        Self::from_toml(path, &text)
    }

    /// Parses scene text; mesh paths resolve relative to `path`'s folder.
    pub fn from_toml(path: &Path, text: &str) -> Result<Scene, SceneError> {
        let file = || path.to_path_buf();
        let desc: SceneFile = toml::from_str(text).map_err(|e| SceneError::Syntax {
            file: file(),
            location: e
                .span()
                .map(|s| Location::of_offset(text, s.start))
                .unwrap_or(Location::Element("document".into())),
            message: e.message().to_string(),
        })?;
        let cam_span = desc.camera.span();
        let c = desc.camera.into_inner();
        let vals: Vec<f32> = c
            .position
            .iter()
            .chain(&c.look_at)
            .chain(&c.up)
            .chain([&c.fov_y])
            .copied()
            .collect();
        check_finite(path, text, cam_span.clone(), "camera", &vals)?;
        let invalid = |span: std::ops::Range<usize>, message: String| SceneError::Invalid {
            file: file(),
            location: Location::of_offset(text, span.start),
            message,
        };
        if c.resolution[0] == 0
            || c.resolution[1] == 0
            || c.resolution[0] > 1 << 15
            || c.resolution[1] > 1 << 15
        {
            return Err(invalid(
                cam_span,
                format!(
                    "camera resolution {:?} must be between 1 and 32768",
                    c.resolution
                ),
            ));
        }
        if !(c.fov_y > 0.0 && c.fov_y < 180.0) {
            return Err(invalid(
                cam_span,
                format!("camera fov_y {} must be in (0, 180) degrees", c.fov_y),
            ));
        }
        let fwd = Vec3::from(c.look_at) - Vec3::from(c.position);
        if fwd.length_squared() == 0.0 || fwd.cross(Vec3::from(c.up)).length_squared() == 0.0 {
            return Err(invalid(
                cam_span,
                "camera look_at must differ from position and not be parallel to up".into(),
            ));
        }
        let camera = Camera {
            position: c.position.into(),
            look_at: c.look_at.into(),
            up: c.up.into(),
            fov_y: c.fov_y,
            width: c.resolution[0],
            height: c.resolution[1],
        };
        let mut octree = OctreeParams::default();
        if let Some(o) = desc.octree {
            if let Some(m) = o.max_leaf_tris {
                octree.max_leaf_tris = m.max(1);
            }
            if let Some(d) = o.max_depth {
                octree.max_depth = d.min(16);
            }
        }
        if let Err(why) =
            crate::limits::check_settings(desc.render.spp.max(1), desc.render.max_depth)
        {
            let at = text.find("[render]").unwrap_or(0);
            return Err(invalid(at..at, why));
        }
        if let Some(Err(why)) = desc.render.target_rel_mse.map(crate::limits::check_target) {
            let at = text.find("target_rel_mse").unwrap_or(0);
            return Err(invalid(at..at, why));
        }
        let settings = RenderSettings {
            spp: desc.render.spp.max(1),
            max_depth: desc.render.max_depth,
            seed: desc.render.seed,
            sampler: desc.render.sampler,
            octree,
            target_rel_mse: desc.render.target_rel_mse,
            adaptive_sampling: desc.render.adaptive_sampling,
            bvh: desc.render.bvh,
        };

        let mut b = Builder::default();
        for (name, m) in &desc.materials {
            let span = m.span();
            let m = m.get_ref();
            let vals: Vec<f32> = m.albedo.iter().chain(&m.emission).copied().collect();
            check_finite(
                path,
                text,
                span.clone(),
                &format!("material '{name}'"),
                &vals,
            )?;
            if let Some(why) = crate::mesh_io::colour_problem(m.albedo, m.emission) {
                return Err(invalid(span, format!("material '{name}': {why}")));
            }
            b.add_material(
                Material {
                    name: name.clone(),
                    albedo: m.albedo.into(),
                    emission: m.emission.into(),
                },
                true,
            );
        }
        for (i, l) in desc.light.iter().enumerate() {
            let span = l.span();
            let l = l.get_ref();
            let vals: Vec<f32> = l
                .corner
                .iter()
                .chain(&l.edge_a)
                .chain(&l.edge_b)
                .chain(&l.emission)
                .copied()
                .collect();
            check_finite(path, text, span.clone(), &format!("light[{i}]"), &vals)?;
            if l.emission.iter().any(|&e| e < 0.0) {
                return Err(invalid(span, format!("light[{i}]: emission must be >= 0")));
            }
            let m = b.add_material(
                Material {
                    name: format!("light{i}"),
                    albedo: Vec3::ZERO,
                    emission: l.emission.into(),
                },
                false,
            );
            let (p, ea, eb) = (
                Vec3::from(l.corner),
                Vec3::from(l.edge_a),
                Vec3::from(l.edge_b),
            );
            b.add_tri([p, p + ea, p + ea + eb], m, FLAT);
            b.add_tri([p, p + ea + eb, p + eb], m, FLAT);
        }
        let dir = path.parent().unwrap_or(Path::new("."));
        for (i, m) in desc.mesh.iter().enumerate() {
            let span = m.span();
            let m = m.get_ref();
            check_finite(
                path,
                text,
                span.clone(),
                &format!("mesh[{i}].transform"),
                &m.transform.values(),
            )?;
            let mp = dir.join(&m.file);
            if !mp.is_file() {
                return Err(SceneError::MissingFile {
                    file: file(),
                    location: Location::of_offset(text, span.start),
                    missing: mp,
                });
            }
            let override_mat = match &m.material {
                Some(name) => Some(b.material_id(name).ok_or_else(|| {
                    invalid(
                        span.clone(),
                        format!("mesh[{i}]: unknown material '{name}'"),
                    )
                })?),
                None => None,
            };
            let data = mesh_io::load(&mp)?;
            let xf = m.transform.matrix();
            let file_mats: Vec<u32> = data
                .materials
                .iter()
                .map(|fm| {
                    b.add_material(
                        Material {
                            name: fm.name.clone(),
                            albedo: fm.albedo,
                            emission: fm.emission,
                        },
                        false,
                    )
                })
                .collect();
            let default_mat = b.default_material();
            let pos: Vec<Vec3> = data
                .positions
                .iter()
                .map(|&p| xf.transform_point3(p))
                .collect();
            if let Some(p) = pos.iter().find(|p| !p.is_finite()) {
                return Err(invalid(
                    span,
                    format!("mesh[{i}]: transform makes a vertex non-finite ({p})"),
                ));
            }
            // Normals go through the inverse transpose, and are kept only
            // where every one of a triangle's survives it with a length.
            let nxf = glam::Mat3::from_mat4(xf).inverse().transpose();
            let nrm: Vec<Vec3> = data
                .normals
                .iter()
                .map(|&n| (nxf * n).normalize_or_zero())
                .collect();
            // A mirroring transform (negative determinant) turns each
            // triangle's winding over, and with it the side its
            // counter-clockwise normal, and so its emission, faces: two
            // corners swap back, so a mirrored lamp still lights what it
            // faced (as glTF specifies for its nodes and pbrt does).
            let corners: [usize; 3] = if xf.determinant() < 0.0 {
                [0, 2, 1]
            } else {
                [0, 1, 2]
            };
            for (k, (t, fm)) in data.triangles.iter().zip(&data.tri_material).enumerate() {
                let mat = override_mat
                    .or(fm.map(|k| file_mats[k as usize]))
                    .unwrap_or(default_mat);
                let shading = data
                    .tri_normals
                    .get(k)
                    .and_then(|ix| {
                        let n = ix.map(|i| nrm.get(i as usize).copied().unwrap_or(Vec3::ZERO));
                        n.iter()
                            .all(|v| v.is_finite() && *v != Vec3::ZERO)
                            .then_some(n)
                    })
                    .unwrap_or(FLAT);
                b.add_tri(
                    corners.map(|c| pos[t[c] as usize]),
                    mat,
                    corners.map(|c| shading[c]),
                );
            }
            b.stats.meshes += 1;
        }
        Ok(b.finish(path, camera, settings))
    }

    /// Builds a scene from triangles already in memory (generators, tests).
    pub fn from_triangles(
        path: PathBuf,
        camera: Camera,
        settings: RenderSettings,
        materials: Vec<Material>,
        tris: Vec<([Vec3; 3], u32)>,
    ) -> Scene {
        let mut b = Builder {
            materials,
            ..Default::default()
        };
        for (t, m) in tris {
            b.add_tri(t, m, FLAT);
        }
        b.finish(&path, camera, settings)
    }

    /// The largest coordinate among geometry and camera: the magnitude that
    /// rounding errors of ray queries scale with.
    pub fn magnitude(&self) -> f32 {
        let g = self
            .tris
            .iter()
            .flatten()
            .fold(0f32, |m, p| m.max(p.abs().max_element()));
        g.max(self.camera.position.abs().max_element())
    }

    /// Applies `f` to every vertex and the camera (used by the scale tests).
    pub fn transformed(&self, m: Mat4) -> Scene {
        let mut s = self.clone();
        for t in &mut s.tris {
            for p in t.iter_mut() {
                *p = m.transform_point3(*p);
            }
        }
        let nxf = glam::Mat3::from_mat4(m).inverse().transpose();
        for t in &mut s.tri_normals {
            for n in t.iter_mut() {
                *n = (nxf * *n).normalize_or_zero();
            }
        }
        s.camera.position = m.transform_point3(s.camera.position);
        s.camera.look_at = m.transform_point3(s.camera.look_at);
        s
    }
}

#[derive(Default)]
struct Builder {
    materials: Vec<Material>,
    by_name: BTreeMap<String, u32>,
    /// Names defined in the scene file: they win over mesh-file materials of
    /// the same name, so a user can retune a model's reflectances.
    pinned: std::collections::BTreeSet<String>,
    tris: Vec<[Vec3; 3]>,
    tri_material: Vec<u32>,
    tri_normals: Vec<[Vec3; 3]>,
    stats: LoadStats,
}

impl Builder {
    fn add_material(&mut self, m: Material, pinned: bool) -> u32 {
        if let Some(&id) = self.by_name.get(&m.name) {
            if self.pinned.contains(&m.name) {
                return id;
            }
            self.materials[id as usize] = m;
            return id;
        }
        let id = self.materials.len() as u32;
        self.by_name.insert(m.name.clone(), id);
        if pinned {
            self.pinned.insert(m.name.clone());
        }
        self.materials.push(m);
        id
    }
    fn material_id(&self, name: &str) -> Option<u32> {
        self.by_name.get(name).copied()
    }
    fn default_material(&mut self) -> u32 {
        match self.material_id("default") {
            Some(id) => id,
            None => self.add_material(
                Material {
                    name: "default".into(),
                    albedo: Vec3::splat(0.8),
                    emission: Vec3::ZERO,
                },
                false,
            ),
        }
    }
    /// Adds a triangle with its shading normals ([`FLAT`] for none).
    fn add_tri(&mut self, t: [Vec3; 3], m: u32, normals: [Vec3; 3]) {
        self.stats.triangles_read += 1;
        // Zero area in f64, or a normal that does not survive f32: neither
        // can be hit or sampled meaningfully.
        let n = crate::geometry::tri_cross(&t);
        if tri_area_f64(&t) == 0.0 || !n.is_finite() || n.length_squared() == 0.0 {
            self.stats.degenerate_dropped += 1;
            return;
        }
        if normals != FLAT {
            self.stats.shaded += 1;
        }
        // Flat triangles cost nothing until the first shaded one.
        if normals != FLAT || !self.tri_normals.is_empty() {
            self.tri_normals.resize(self.tris.len(), FLAT);
            self.tri_normals.push(normals);
        }
        self.tris.push(t);
        self.tri_material.push(m);
    }
    fn finish(self, path: &Path, camera: Camera, settings: RenderSettings) -> Scene {
        if self.stats.degenerate_dropped > 0 {
            tracing::info!(file = %path.display(), dropped = self.stats.degenerate_dropped, "dropped degenerate (zero-area) triangles");
        }
        Scene {
            path: path.to_path_buf(),
            camera,
            settings,
            materials: self.materials,
            tris: self.tris,
            tri_material: self.tri_material,
            tri_normals: self.tri_normals,
            load_stats: self.stats,
        }
    }
}
