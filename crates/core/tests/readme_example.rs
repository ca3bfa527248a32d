//! The complete scene example in the README must load (against the Cornell
//! box mesh), so the documented format cannot drift from the parser.

mod common;
use locus_core::scene::Scene;

#[test]
fn readme_scene_example_loads() {
    let readme = std::fs::read_to_string(common::repo_root().join("README.md")).unwrap();
    let start = readme.find("```toml\n").expect("README has a toml block") + 8;
    let len = readme[start..].find("```").unwrap();
    let text = &readme[start..start + len];
    let path = common::repo_root().join("scenes/cornell-box/readme-example.toml");
    let s = Scene::from_toml(&path, text).unwrap_or_else(|e| panic!("README example: {e}"));
    assert_eq!(s.settings.octree.max_leaf_tris, 512);
    assert_eq!(s.tris.len(), 32 + 2, "Cornell box plus the quad light");
    // The mesh-level material override applies to every Cornell face,
    // including the light's: only the [[light]] quad emits.
    let emitters = s
        .tri_material
        .iter()
        .filter(|&&m| s.materials[m as usize].is_emissive())
        .count();
    assert_eq!(emitters, 2);
    // The BVH setting is read, not defaulted: the example names `auto`,
    // and each other value comes back as written.
    use locus_core::accel::BvhSetting;
    assert!(text.contains("bvh = \"auto\""));
    assert_eq!(s.settings.bvh, BvhSetting::Auto);
    for b in [BvhSetting::Full, BvhSetting::Quick] {
        let t = text.replace("bvh = \"auto\"", &format!("bvh = \"{}\"", b.name()));
        let s = Scene::from_toml(&path, &t).unwrap_or_else(|e| panic!("{b:?}: {e}"));
        assert_eq!(s.settings.bvh, b);
    }
}
