//! Every committed fuzz input, run once through its target: the corpora
//! the fuzzers grew (`fuzz/corpus/TARGET/`) and every crash they found,
//! kept as a regression (`fuzz/regressions/TARGET/`). A panic fails the
//! test and names the file.

use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz")
}

fn inputs(dir: &Path) -> Vec<PathBuf> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut v: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file())
        .collect();
    v.sort();
    v
}

fn replay(kind: &str) -> usize {
    let mut n = 0;
    for (name, target) in locus_fuzz::TARGETS {
        for p in inputs(&root().join(kind).join(name)) {
            let data = std::fs::read(&p).unwrap();
            let r = std::panic::catch_unwind(|| target(&data));
            assert!(r.is_ok(), "{name}: {} panics", p.display());
            n += 1;
        }
    }
    n
}

#[test]
fn every_corpus_input_comes_back() {
    for (name, _) in locus_fuzz::TARGETS {
        assert!(
            !inputs(&root().join("corpus").join(name)).is_empty(),
            "no corpus for {name}: fuzz/corpus/{name}/ must hold its seeds"
        );
    }
    let n = replay("corpus");
    eprintln!("{n} corpus inputs replayed");
}

#[test]
fn every_crash_found_stays_fixed() {
    let n = replay("regressions");
    eprintln!("{n} regression inputs replayed");
}
