//! The `locus` binary end to end: render writes EXR, PNG and JSON; a
//! reference gives error metrics; diff agrees with it; bad input exits
//! non-zero with the file named.

use std::path::{Path, PathBuf};
use std::process::Command;

fn locus() -> Command {
    Command::new(env!("CARGO_BIN_EXE_locus"))
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("locus-cli-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn render(scene: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    locus()
        .arg("render")
        .arg(scene)
        .arg("-o")
        .arg(out)
        .args(extra)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap()
}

#[test]
fn render_writes_exr_png_and_report_and_measures_error() {
    let d = scratch("render");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    let a = d.join("a.exr");
    let o = render(&scene, &a, &["--spp", "2", "--threads", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(a.is_file() && d.join("a.png").is_file());
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("a.json")).unwrap()).unwrap();
    assert_eq!(report["stats"]["samples"], 256 * 256 * 2);
    assert!(report["stats"]["camera_rays"].as_u64().unwrap() == 256 * 256 * 2);
    assert!(report["stats"]["shadow_rays"].as_u64().unwrap() > 0);
    assert!(report["times"]["render_s"].as_f64().unwrap() > 0.0);
    // Same seed, other thread count: identical image, zero error.
    let b = d.join("b.exr");
    let o = render(
        &scene,
        &b,
        &[
            "--spp",
            "2",
            "--threads",
            "1",
            "--reference",
            a.to_str().unwrap(),
        ],
    );
    assert!(o.status.success());
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("RMSE 0.000000e0"), "{out}");
    // Another seed differs, and diff reports the same metrics as render.
    let c = d.join("c.exr");
    let o = render(
        &scene,
        &c,
        &[
            "--spp",
            "2",
            "--seed",
            "9",
            "--reference",
            a.to_str().unwrap(),
        ],
    );
    let line = String::from_utf8_lossy(&o.stdout)
        .lines()
        .find(|l| l.starts_with("error vs reference"))
        .unwrap()
        .to_string();
    let diff = locus().arg("diff").arg(&c).arg(&a).output().unwrap();
    assert!(diff.status.success());
    let dl = String::from_utf8_lossy(&diff.stdout).trim().to_string();
    assert!(
        line.ends_with(&dl),
        "render says '{line}', diff says '{dl}'"
    );
    assert!(!dl.contains("RMSE 0.000000e0"));
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn bad_scene_fails_with_file_and_line() {
    let d = scratch("bad");
    let o = render(
        &root().join("tests/corpus/obj_index.toml"),
        &d.join("x.exr"),
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("obj_index.obj") && err.contains("line 5"),
        "{err}"
    );
    assert!(!d.join("x.exr").exists());
    let o = locus()
        .arg("diff")
        .arg(d.join("missing.exr"))
        .arg(d.join("other.exr"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing.exr"));
}
