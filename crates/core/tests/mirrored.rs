//! A mesh placed by a mirroring transform (a negative scale in the scene
//! file) keeps facing where its unmirrored self faced: its triangles'
//! winding is turned back, so their counter-clockwise normal, the side an
//! emitter emits on, agrees with the mirrored shading normals. Seen end to
//! end: a one-sided lamp facing the camera lights the image whether it is
//! mirrored across x or not, and goes dark only when mirrored through its
//! own plane, where it then faces away.

use locus_core::geometry::tri_cross;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;

/// The image's mean and the loaded lamp's geometric and shading normals'
/// z, with the lamp under `scale`.
fn lamp(scale: [f32; 3]) -> (f64, f32, f32) {
    let dir = std::env::temp_dir().join(format!(
        "locus-mirrored-{}-{}",
        std::process::id(),
        scale
            .map(|s| if s < 0.0 { 'm' } else { 'p' })
            .iter()
            .collect::<String>()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    // Counter-clockwise seen from +z, where the camera is; normals +z.
    std::fs::write(
        dir.join("lamp.obj"),
        "v -1 -1 0\nv 1 -1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n",
    )
    .unwrap();
    let toml = format!(
        "[camera]\nposition = [0.0, 0.0, 5.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 30.0\n\
         resolution = [8, 8]\n[render]\nspp = 1\n\
         [materials.lamp]\nalbedo = [0.0, 0.0, 0.0]\nemission = [1.0, 1.0, 1.0]\n\
         [[mesh]]\nfile = \"lamp.obj\"\nmaterial = \"lamp\"\n\
         transform = {{ scale = [{:?}, {:?}, {:?}] }}\n",
        scale[0], scale[1], scale[2]
    );
    std::fs::write(dir.join("s.toml"), toml).unwrap();
    let scene = Scene::load(&dir.join("s.toml")).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(scene.tris.len(), 1);
    let geometric = tri_cross(&scene.tris[0]).z;
    let shading = scene.tri_normals[0][0].z;
    let prep = Prepared::new(scene);
    let img = render(&prep, &RenderOptions::from_scene(&prep.scene), &|_, _| {}).image;
    let mean = img
        .pixels
        .iter()
        .map(|p| (p[0] + p[1] + p[2]) as f64)
        .sum::<f64>()
        / img.pixels.len() as f64;
    (mean, geometric, shading)
}

#[test]
fn mirrored_meshes_face_where_they_faced() {
    let (lit, g, s) = lamp([1.0, 1.0, 1.0]);
    assert!(lit > 0.0 && g > 0.0 && s > 0.0, "unmirrored: {lit} {g} {s}");
    // Mirrored across x (and across x and y, a rotation): still facing +z.
    for scale in [[-1.0, 1.0, 1.0], [-2.0, -1.0, 1.0], [-1.0, 1.0, 0.5]] {
        let (mean, g, s) = lamp(scale);
        assert!(g > 0.0 && s > 0.0, "{scale:?}: normals {g} {s}");
        assert!(mean > 0.0, "{scale:?}: the lamp faces away (mean {mean})");
    }
    // Mirrored through its own plane: it faces -z, away from the camera.
    let (dark, g, s) = lamp([1.0, 1.0, -1.0]);
    assert!(g < 0.0 && s < 0.0, "through z: normals {g} {s}");
    assert_eq!(dark, 0.0, "through z: the lamp should face away");
}
