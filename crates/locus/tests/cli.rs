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
    // The error it carries, read from its samples without a reference.
    let e = &report["error_estimate"];
    assert_eq!(e["samples"], 2);
    assert!(e["rel_mse"].as_f64().unwrap() > 0.0, "{e}");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("estimated error: RMSE")
            && out.contains("upper estimate with the Sobol sampler"),
        "{out}"
    );
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

/// `--irradiance` renders with the preset's irradiance cache and reports
/// its records and use, on one machine and on the embedded farm alike (the
/// same image); bad settings stop with a message that names the flag.
#[test]
fn render_with_the_irradiance_cache_reports_it() {
    let d = scratch("irradiance");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    let a = d.join("a.exr");
    let args = [
        "--spp",
        "2",
        "--threads",
        "2",
        "--preset",
        "low",
        "--irradiance",
    ];
    let o = render(&scene, &a, &args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("irradiance cache:"), "{out}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("a.json")).unwrap()).unwrap();
    let records = report["irradiance"]["records"].as_u64().unwrap();
    assert!(records > 10, "{records} records");
    let used = &report["stats"]["irradiance"];
    let (i, t) = (
        used["interpolated"].as_u64().unwrap(),
        used["traced"].as_u64().unwrap(),
    );
    assert!(i > 0 && i + t <= 256 * 256 * 2, "{used}");
    assert_eq!(report["options"]["irradiance"]["accuracy"], 0.3);
    let o = render(&scene, &a, &["--irradiance", "--irradiance-accuracy", "0"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--irradiance-accuracy"));
    // The embedded farm interpolates the same records: the same image.
    let b = d.join("b.exr");
    let farm: Vec<&str> = args.iter().copied().chain(["--workers", "2"]).collect();
    let o = render(&scene, &b, &farm);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("irradiance cache:") && out.contains("sent to the workers"),
        "{out}"
    );
    let diff = locus()
        .arg("diff")
        .arg(&a)
        .arg(&b)
        .arg("--exact")
        .output()
        .unwrap();
    assert!(
        diff.status.success(),
        "{}",
        String::from_utf8_lossy(&diff.stdout)
    );
    std::fs::remove_dir_all(&d).ok();
}

/// An embedded farm that rendered its job ends without a warning: its
/// scheduler's links drop as the farm shuts down, which a worker took for
/// a failed link, warned of and tried to register again after one
/// render in two or three. Eight renders, each printing every phase.
#[test]
fn embedded_farm_ends_quietly() {
    let d = scratch("quiet");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    for i in 0..8 {
        let o = render(
            &scene,
            &d.join("q.exr"),
            &["--workers", "2", "--spp", "1", "--threads-per-worker", "1"],
        );
        let (out, err) = (
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr),
        );
        assert!(o.status.success(), "render {i}: {err}");
        assert!(!err.contains("WARN"), "render {i} warned: {err}");
        for phase in [
            "load",
            "octree",
            "preview",
            "partition",
            "distribution",
            "render",
            "total",
        ] {
            assert!(
                out.contains(&format!(" {phase} ")),
                "render {i}: no {phase}: {out}"
            );
        }
    }
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

/// A noise target that is not a positive number is refused where the flag
/// is read, naming the flag and what it wants, before any work.
#[test]
fn a_bad_noise_target_is_refused_with_the_flag() {
    let d = scratch("bad-target");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    for bad in ["0", "-1e-3", "NaN", "abc"] {
        let o = render(
            &scene,
            &d.join("x.exr"),
            &[&format!("--target-rel-mse={bad}")],
        );
        assert!(!o.status.success(), "{bad}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("--target-rel-mse") && err.contains("such as 1e-3"),
            "{bad}: {err}"
        );
        assert!(!d.join("x.exr").exists());
    }
    std::fs::remove_dir_all(&d).ok();
}

/// `--adaptive-sampling` spreads the samples, its report counting the
/// samples each pixel got (as many in all as an even render's); the farm
/// renders the same image to the bit and counts the same, and a scene
/// file's `adaptive_sampling = true` does what the flag does.
#[test]
fn adaptive_sampling_reports_its_counts_on_one_machine_and_the_farm() {
    let d = scratch("adaptive");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    let a = d.join("a.exr");
    let o = render(
        &scene,
        &a,
        &["--spp", "16", "--threads", "2", "--adaptive-sampling"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let json = |name: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(d.join(name)).unwrap()).unwrap()
    };
    let report = json("a.json");
    let c = &report["sample_counts"];
    assert_eq!(c["mean"].as_f64(), Some(16.0), "{report}");
    assert!(
        c["min"].as_u64().unwrap() >= 8 && c["max"].as_u64().unwrap() > 16,
        "{c}"
    );
    let pixels = 256 * 256;
    assert_eq!(
        report["stats"]["samples"].as_u64(),
        Some(16 * pixels),
        "{report}"
    );
    assert_eq!(report["options"]["adaptive"].as_bool(), Some(true));
    let bits = |p: &Path| locus_core::image_io::Image::read_exr(p).unwrap().to_bits();
    // Each pixel's count, as an image beside the render: the report's
    // range and mean.
    let counts = locus_core::image_io::Image::read_exr(&d.join("a.samples.exr")).unwrap();
    let n: Vec<f32> = counts.pixels.iter().map(|p| p[0]).collect();
    assert!(counts.pixels.iter().all(|p| p[0] == p[1] && p[1] == p[2]));
    let (lo, hi) = n
        .iter()
        .fold((f32::MAX, 0f32), |(a, b), &x| (a.min(x), b.max(x)));
    assert_eq!(
        (lo as u64, hi as u64),
        (c["min"].as_u64().unwrap(), c["max"].as_u64().unwrap())
    );
    assert_eq!(n.iter().map(|&x| x as u64).sum::<u64>(), 16 * pixels);

    let b = d.join("b.exr");
    let o = render(
        &scene,
        &b,
        &["--spp", "16", "--workers", "2", "--adaptive-sampling"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("adaptive sampling:"), "{out}");
    let mean = "samples a pixel, 16.00 on average)";
    assert!(
        out.contains("estimated error: RMSE") && out.contains(mean),
        "{out}"
    );
    assert_eq!(json("b.json")["farm"]["sample_counts"], *c);
    assert_eq!(bits(&b), bits(&a), "the farm's image is one machine's");
    let samples = |name: &str| bits(&d.join(name));
    assert_eq!(samples("b.samples.exr"), samples("a.samples.exr"));
    assert!(out.contains("b.samples.exr"), "{out}");

    // The scene file's setting, with the mesh found where it lies.
    let text = std::fs::read_to_string(&scene).unwrap();
    let obj = root().join("scenes/cornell-box/cornell.obj");
    let text = text
        .replace("[render]\n", "[render]\nadaptive_sampling = true\n")
        .replace(
            "\"cornell.obj\"",
            &format!("{:?}", obj.display().to_string()),
        );
    let file = d.join("adaptive.toml");
    std::fs::write(&file, text).unwrap();
    let e = d.join("e.exr");
    let o = render(&file, &e, &["--spp", "16", "--threads", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(json("e.json")["sample_counts"], *c);
    assert_eq!(bits(&e), bits(&a));
    // An even render writes no counts.
    let f = d.join("f.exr");
    let o = render(&scene, &f, &["--spp", "2", "--threads", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!d.join("f.samples.exr").exists());
    std::fs::remove_dir_all(&d).ok();
}

/// Reads the first stdout line of a daemon ("... listening on ADDR").
fn listening_addr(child: &mut std::process::Child) -> String {
    use std::io::BufRead;
    let out = child.stdout.take().expect("piped stdout");
    let mut line = String::new();
    std::io::BufReader::new(out)
        .read_line(&mut line)
        .expect("daemon prints its address");
    line.trim().rsplit(' ').next().expect("address").to_string()
}

#[cfg(unix)]
fn sigterm(child: &std::process::Child) {
    let _ = Command::new("kill")
        .arg("-TERM")
        .arg(child.id().to_string())
        .status();
}

/// Scheduler, two workers and submit as separate processes, with the token
/// from the environment, a flag and a config file; one worker is given no
/// listen address (it listens on every interface, and its peer dials it
/// at the address it reaches the scheduler from). Under `forward`, so that
/// rays cross between them, the image is identical to `locus render` on
/// one machine, and SIGTERM stops the daemons cleanly.
#[cfg(unix)]
#[test]
fn daemons_as_processes_match_single_machine() {
    use std::process::Stdio;
    let d = scratch("daemons");
    let scene = d.join("small.toml");
    let text = std::fs::read_to_string(root().join("scenes/cornell-box/cornell.toml")).unwrap();
    let text = text.replace("resolution = [256, 256]", "resolution = [32, 24]");
    assert!(text.contains("[32, 24]"), "the test scene is small");
    std::fs::write(&scene, text).unwrap();
    for f in ["cornell.obj", "cornell.mtl"] {
        std::fs::copy(root().join("scenes/cornell-box").join(f), d.join(f)).unwrap();
    }
    let config = d.join("worker.toml");
    std::fs::write(
        &config,
        "token = \"s3cret\"\n[worker]\nlisten = \"127.0.0.1:0\"\nthreads = 1\n",
    )
    .unwrap();
    let unbound = d.join("unbound.toml");
    std::fs::write(&unbound, "token = \"s3cret\"\n[worker]\nthreads = 1\n").unwrap();
    let mut sched = locus()
        .args(["scheduler", "--listen", "127.0.0.1:0"])
        .env("LOCUS_TOKEN", "s3cret")
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let addr = listening_addr(&mut sched);
    let mut workers: Vec<_> = [&config, &unbound]
        .into_iter()
        .map(|c| {
            let mut w = locus()
                .args(["worker", "--scheduler", &addr, "--config"])
                .arg(c)
                .env_remove("LOCUS_TOKEN")
                .env("RUST_LOG", "warn")
                .stdout(Stdio::piped())
                .spawn()
                .unwrap();
            let at = listening_addr(&mut w);
            let wildcard = at.starts_with("0.0.0.0:");
            assert_eq!(wildcard, c == &unbound, "{} listens on {at}", c.display());
            w
        })
        .collect();
    let farm_out = d.join("farm.exr");
    let sub = locus()
        .args([
            "submit",
            "--scheduler",
            &addr,
            "--token",
            "s3cret",
            "--workers",
            "2",
            "--partitioner",
            "morton",
            "--fetch",
            "forward",
        ])
        .arg(&scene)
        .arg("-o")
        .arg(&farm_out)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(
        sub.status.success(),
        "{}",
        String::from_utf8_lossy(&sub.stderr)
    );
    let single = d.join("single.exr");
    let r = render(&scene, &single, &[]);
    assert!(r.status.success());
    let a = locus_core::image_io::Image::read_exr(&farm_out).unwrap();
    let b = locus_core::image_io::Image::read_exr(&single).unwrap();
    assert_eq!(
        a.to_bits(),
        b.to_bits(),
        "farm of processes = single machine"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("farm.json")).unwrap()).unwrap();
    assert_eq!(report["farm"]["workers"].as_array().unwrap().len(), 2);
    let forwarded = report["farm"]["forwarded_fraction"].as_f64().unwrap();
    assert!(forwarded > 0.0, "rays crossed between the workers");
    // The same error estimate as one machine's, to the bit.
    let one: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("single.json")).unwrap()).unwrap();
    assert!(one["error_estimate"]["rel_mse"].as_f64().unwrap() > 0.0);
    assert_eq!(report["farm"]["error_estimate"], one["error_estimate"]);
    // A submit with the wrong token is refused with a message.
    let bad = locus()
        .args(["submit", "--scheduler", &addr, "--token", "wrong"])
        .arg(&scene)
        .arg("-o")
        .arg(d.join("bad.exr"))
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("token"));
    for w in &workers {
        sigterm(w);
    }
    sigterm(&sched);
    for w in &mut workers {
        assert!(
            w.wait().unwrap().success(),
            "worker exits cleanly on SIGTERM"
        );
    }
    assert!(
        sched.wait().unwrap().success(),
        "scheduler exits cleanly on SIGTERM"
    );
}

/// `locus bench quality` end to end without Mitsuba: a reference in two
/// halves (kept, and reused by a second run), one row per sampler and
/// sample count, and errors that fall with more samples.
#[test]
fn bench_quality_measures_error_per_second() {
    let d = scratch("quality");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    let run = || {
        let o = locus()
            .args(["bench", "quality"])
            .arg(&scene)
            .args(["--spp", "1", "8", "--reference-spp", "64", "--threads", "2"])
            .args(["--no-mitsuba", "--out-dir"])
            .arg(&d)
            .env("RUST_LOG", "info")
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        o
    };
    let first = run();
    assert!(d.join("reference.exr").is_file() && d.join("quality.svg").is_file());
    let again = run();
    assert!(
        String::from_utf8_lossy(&again.stderr).contains("reusing the reference"),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    let csv = std::fs::read_to_string(d.join("quality.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 4, "{csv}");
    for sampler in ["sobol", "independent"] {
        let err = |spp: &str| -> f64 {
            let r = rows
                .iter()
                .find(|r| r[1] == sampler && r[2] == spp)
                .unwrap_or_else(|| panic!("no {sampler} {spp} row in {csv}"));
            r[4].parse().unwrap()
        };
        // 8 times the samples: the error must fall well below half (1/8
        // for independent samples, the reference's own error aside).
        assert!(err("8") < 0.5 * err("1"), "{sampler}: {csv}");
    }
    assert!(String::from_utf8_lossy(&first.stdout).contains("| locus | sobol | 8 |"));
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn radiosity_writes_the_image_the_mesh_and_the_convergence() {
    let d = scratch("radiosity");
    let scene = root().join("scenes/cornell-box/cornell.toml");
    let out = d.join("r.exr");
    let o = locus()
        .arg("radiosity")
        .arg(&scene)
        .arg("-o")
        .arg(&out)
        .args([
            "--patches",
            "1",
            "--mesh",
            "4",
            "--subdivide",
            "1",
            "--stop",
            "1e-2",
        ])
        .args(["--spp", "2", "--threads", "2"])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for ext in ["exr", "png", "json", "ply", "convergence.svg"] {
        assert!(out.with_extension(ext).is_file(), "no {ext}");
    }
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.with_extension("json")).unwrap())
            .unwrap();
    assert_eq!(r["stopped"], "converged");
    assert!(r["unshot_fraction"].as_f64().unwrap() < 1e-2);
    let l = &r["ledger"];
    for c in 0..3 {
        let f = |k: &str| l[k][c].as_f64().unwrap();
        let rel = (f("absorbed") + f("unshot") + f("escaped") - f("emitted")).abs() / f("emitted");
        assert!(rel < 1e-10, "{l}");
    }
    let conv = r["convergence"].as_array().unwrap();
    assert!(conv.len() > 5);
    let unshot: Vec<f64> = conv
        .iter()
        .map(|x| x["unshot_fraction"].as_f64().unwrap())
        .collect();
    assert!(unshot.first() > unshot.last(), "{unshot:?}");
    assert_eq!(conv.last().unwrap()["error"].as_f64(), Some(0.0));
    // One PLY vertex per element corner.
    let ply = std::fs::read(out.with_extension("ply")).unwrap();
    let header =
        String::from_utf8_lossy(&ply[..ply.windows(10).position(|w| w == b"end_header").unwrap()])
            .to_string();
    let elements = r["elements"].as_u64().unwrap();
    assert!(
        header.contains(&format!("element vertex {}\n", 3 * elements)),
        "{header}"
    );
    assert!(
        header.contains(&format!("element face {elements}\n")),
        "{header}"
    );
    let mean = locus_core::image_io::Image::read_exr(&out).unwrap().mean();
    assert!(mean.iter().all(|&c| c > 0.01), "{mean:?}");

    // Bad settings and a scene without light name what is wrong.
    let bad = locus()
        .arg("radiosity")
        .arg(&scene)
        .args(["--parts", "3"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("shooter parts"));
    let dark = d.join("dark.toml");
    std::fs::write(
        &dark,
        "[camera]\nposition = [0, 0, -3]\nlook_at = [0, 0, 0]\nfov_y = 40\nresolution = [8, 8]\n\
         [[light]]\ncorner = [0, 0, 0]\nedge_a = [1, 0, 0]\nedge_b = [0, 1, 0]\nemission = [0, 0, 0]\n",
    )
    .unwrap();
    let o = locus()
        .arg("radiosity")
        .arg(&dark)
        .arg("-o")
        .arg(d.join("dark.exr"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("dark.toml") && err.contains("emits"), "{err}");
    std::fs::remove_dir_all(&d).ok();
}
