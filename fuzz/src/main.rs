//! `locus-afl TARGET`: feeds AFL++'s inputs to one of locus-fuzz's targets
//! in persistent mode. Targets: scene_toml, obj, mtl, ply, gltf, glb,
//! frames.

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    let Some(target) = locus_fuzz::target(&name) else {
        let names: Vec<&str> = locus_fuzz::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("usage: locus-afl TARGET, one of {}", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| {
        target(data);
    });
}
