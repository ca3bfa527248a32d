//! The tools beside rendering: `diff`, `gen` and `tls-init` (the
//! benchmarks are in [`super::bench`]).

use crate::cli::*;
use anyhow::{Context, Result, bail};
use locus_core::generate::{RoomParams, write_room};
use locus_core::image_io::Image;
use locus_core::metrics::compare;
use std::path::Path;

pub(crate) fn cmd_diff(a: &Path, b: &Path, exact: bool) -> Result<()> {
    let ia = Image::read_exr(a)?;
    let ib = Image::read_exr(b)?;
    let m = compare(&ia, &ib)?;
    println!("{m}");
    if exact {
        let bits = |p: &[f32; 3]| p.map(f32::to_bits);
        let differ: Vec<usize> = (0..ia.pixels.len())
            .filter(|&i| bits(&ia.pixels[i]) != bits(&ib.pixels[i]))
            .collect();
        match differ.first() {
            None => println!("bit-identical ({} pixels)", ia.pixels.len()),
            Some(&i) => bail!(
                "{} of {} pixels differ in their bits, the first at ({}, {})",
                differ.len(),
                ia.pixels.len(),
                i % ia.width as usize,
                i / ia.width as usize
            ),
        }
    }
    Ok(())
}

pub(crate) fn cmd_gen(what: GenWhat) -> Result<()> {
    match what {
        GenWhat::Room {
            out_dir,
            name,
            chairs_per_side,
            detail,
        } => {
            let mut p = RoomParams::default();
            if let Some(c) = chairs_per_side {
                p.chairs_per_side = c;
            }
            if let Some(d) = detail {
                p.detail = d.max(1);
            }
            let (path, n) = write_room(&out_dir, &name, &p)
                .with_context(|| format!("writing {}", out_dir.display()))?;
            println!("wrote {} ({n} triangles)", path.display());
        }
    }
    Ok(())
}

/// Writes a self-signed certificate and its key into `dir` (the key
/// readable by its owner only), refusing to replace either unless `force`.
pub(crate) fn cmd_tls_init(dir: &Path, force: bool) -> Result<()> {
    let (cert, key) = locus_protocol::tls::generate().map_err(anyhow::Error::msg)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (c, k) = (dir.join("cert.pem"), dir.join("key.pem"));
    for p in [&c, &k] {
        if p.exists() && !force {
            bail!("{} exists: pass --force to replace it", p.display());
        }
    }
    std::fs::write(&c, cert).with_context(|| format!("writing {}", c.display()))?;
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create(true).truncate(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut o, 0o600);
    let mut f = o
        .open(&k)
        .with_context(|| format!("writing {}", k.display()))?;
    std::io::Write::write_all(&mut f, key.as_bytes())
        .with_context(|| format!("writing {}", k.display()))?;
    println!(
        "wrote {} and {}: give both to every scheduler and worker (--tls-cert, --tls-key), \
         the certificate to clients (--tls-ca)",
        c.display(),
        k.display()
    );
    Ok(())
}
