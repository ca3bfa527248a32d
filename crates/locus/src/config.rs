//! Daemon configuration: a TOML file (see `configs/`), overridden by flags
//! and, for the token, the `LOCUS_TOKEN` environment variable.

use anyhow::{Context, bail};
use serde::Deserialize;
use std::path::{Path, PathBuf};

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub token: Option<String>,
    /// A file holding the token (a Compose or Kubernetes secret), read
    /// when no token is given otherwise.
    pub token_file: Option<PathBuf>,
    #[serde(default)]
    pub scheduler: SchedulerSection,
    #[serde(default)]
    pub worker: WorkerSection,
    /// TLS on every link (`cert`, `key`, `ca`, `server_name`).
    #[serde(default)]
    pub tls: locus_protocol::tls::TlsFiles,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SchedulerSection {
    pub listen: Option<String>,
    pub max_queued_jobs: Option<usize>,
    /// The read-only status page, `/status` and `/metrics`.
    pub http: Option<String>,
    /// Seconds a worker may be silent before it is lost (default 5).
    pub worker_timeout_s: Option<f64>,
    /// A directory for the job store: jobs survive a restart.
    pub state: Option<PathBuf>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorkerSection {
    pub scheduler: Option<String>,
    pub listen: Option<String>,
    pub advertise: Option<String>,
    pub threads: Option<usize>,
    /// Bytes, or a size such as "160M" or "2G" (see [`ByteSize`]).
    pub memory_budget: Option<ByteSize>,
    pub name: Option<String>,
}

/// A size in bytes, written as a number of bytes or with a binary suffix
/// (`K`, `M`, `G`, `T`: powers of 1024, optionally followed by `iB` or
/// `B`), fractions allowed: `512M`, `1.5G`, `8000000000`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ByteSize(pub u64);

impl std::str::FromStr for ByteSize {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let t = s.trim();
        let split = t
            .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '_'))
            .unwrap_or(t.len());
        let (num, unit) = t.split_at(split);
        let num: f64 = num
            .replace('_', "")
            .parse()
            .map_err(|_| format!("{s:?} is not a size (try 512M or 2G)"))?;
        let shift = match unit.trim().trim_end_matches("iB").trim_end_matches('B') {
            "" => 0,
            "K" | "k" => 10,
            "M" | "m" => 20,
            "G" | "g" => 30,
            "T" | "t" => 40,
            u => return Err(format!("{s:?}: unknown unit {u:?} (K, M, G or T)")),
        };
        let bytes = num * (1u64 << shift) as f64;
        if !(bytes.is_finite() && bytes >= 0.0 && bytes < u64::MAX as f64) {
            return Err(format!("{s:?} is out of range"));
        }
        Ok(ByteSize(bytes as u64))
    }
}

impl<'de> Deserialize<'de> for ByteSize {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Bytes(u64),
            Text(String),
        }
        match Raw::deserialize(d)? {
            Raw::Bytes(b) => Ok(ByteSize(b)),
            Raw::Text(t) => t.parse().map_err(serde::de::Error::custom),
        }
    }
}

impl Config {
    pub fn load(path: Option<&Path>) -> anyhow::Result<Self> {
        match path {
            Some(p) => load_toml(p),
            None => Ok(Self::default()),
        }
    }

    /// The cluster token, from the first of: `--token` or `LOCUS_TOKEN`
    /// (clap merges those two), `--token-file` or `LOCUS_TOKEN_FILE`, the
    /// config file's `token`, its `token_file`.
    pub fn token(
        &self,
        flag: Option<String>,
        file_flag: Option<&Path>,
        config: Option<&PathBuf>,
    ) -> anyhow::Result<String> {
        let given = if flag.is_some() {
            flag
        } else if let Some(f) = file_flag {
            Some(read_token_file(f)?)
        } else if self.token.is_some() {
            self.token.clone()
        } else {
            self.token_file
                .as_deref()
                .map(read_token_file)
                .transpose()?
        };
        match given {
            Some(t) if !t.is_empty() => Ok(t),
            _ => bail!(
                "no cluster token: pass --token or --token-file, set LOCUS_TOKEN or \
                 LOCUS_TOKEN_FILE, or put `token = \"...\"` or `token_file = \"...\"` in {}",
                config.map_or("a --config file".to_string(), |p| p.display().to_string())
            ),
        }
    }
}

/// The largest token file read: a token is a line, and a path mistaken for
/// the token file (a disk image, a device) must not be read whole.
const MAX_TOKEN_FILE: u64 = 4096;

/// A token file's first line, without surrounding whitespace.
fn read_token_file(p: &Path) -> anyhow::Result<String> {
    use std::io::Read;
    let f =
        std::fs::File::open(p).with_context(|| format!("reading token file {}", p.display()))?;
    let mut text = String::new();
    f.take(MAX_TOKEN_FILE + 1)
        .read_to_string(&mut text)
        .with_context(|| format!("reading token file {}", p.display()))?;
    if text.len() as u64 > MAX_TOKEN_FILE {
        bail!(
            "token file {} is over {MAX_TOKEN_FILE} bytes: is it the right file?",
            p.display()
        );
    }
    let t = text.lines().next().unwrap_or("").trim().to_string();
    if t.is_empty() {
        bail!("token file {} is empty", p.display());
    }
    Ok(t)
}

/// Reads a TOML file into `T`; errors name the file and line.
pub fn load_toml<T: serde::de::DeserializeOwned>(p: &Path) -> anyhow::Result<T> {
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    parse_toml(&text, &p.display().to_string())
}

/// Parses TOML `text` into `T`; errors name `origin` and the line.
fn parse_toml<T: serde::de::DeserializeOwned>(text: &str, origin: &str) -> anyhow::Result<T> {
    toml::from_str(text).map_err(|e| {
        let line = e
            .span()
            .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        match line {
            Some(l) => anyhow::anyhow!("{origin}:{l}: {}", e.message()),
            None => anyhow::anyhow!("{origin}: {}", e.message()),
        }
    })
}

/// A quality preset (`configs/presets/`): sampling settings plus the
/// directional cache's parameters, used when the cache is switched on.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Preset {
    pub name: String,
    pub spp: u32,
    pub max_depth: u32,
    #[serde(default)]
    pub cache: locus_core::dircache::CacheParams,
    /// Ward's irradiance cache, used when it is switched on.
    #[serde(default)]
    pub irradiance: locus_core::irradiance::IrradianceParams,
}

/// The presets built into the binary (the files in `configs/presets/`),
/// so that `--preset accurate` works from any directory and after
/// `cargo install`.
pub const BUILTIN_PRESETS: [(&str, &str); 3] = [
    (
        "accurate",
        include_str!("../../../configs/presets/accurate.toml"),
    ),
    ("fast", include_str!("../../../configs/presets/fast.toml")),
    ("low", include_str!("../../../configs/presets/low.toml")),
];

impl Preset {
    pub fn load(p: &Path) -> anyhow::Result<Self> {
        let text =
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        Self::parse(&text, &p.display().to_string())
    }

    /// A preset by file path or, when no such file exists, by the name of
    /// a built-in one.
    pub fn resolve(arg: &str) -> anyhow::Result<Self> {
        let path = Path::new(arg);
        if path.exists() {
            return Self::load(path);
        }
        match BUILTIN_PRESETS.iter().find(|(n, _)| *n == arg) {
            Some((n, text)) => Self::parse(text, &format!("built-in preset {n}")),
            None => bail!(
                "no preset {arg:?}: not a file, nor a built-in preset ({})",
                BUILTIN_PRESETS.map(|(n, _)| n).join(", ")
            ),
        }
    }

    fn parse(text: &str, origin: &str) -> anyhow::Result<Self> {
        let preset: Preset = parse_toml(text, origin)?;
        preset
            .cache
            .check()
            .map_err(|e| anyhow::anyhow!("{origin}: {e}"))?;
        preset
            .irradiance
            .check()
            .map_err(|e| anyhow::anyhow!("{origin}: [irradiance] {e}"))?;
        if preset.spp == 0 {
            bail!("{origin}: spp must be at least 1");
        }
        Ok(preset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_suffixes() {
        for (t, b) in [
            ("123", 123u64),
            ("64K", 64 << 10),
            ("160M", 160 << 20),
            ("160MiB", 160 << 20),
            ("1.5G", 3 << 29),
            ("2GB", 2 << 30),
            ("8_000_000_000", 8_000_000_000),
        ] {
            assert_eq!(t.parse::<ByteSize>(), Ok(ByteSize(b)), "{t}");
        }
        for bad in ["", "M", "12X", "-3G", "1e400"] {
            assert!(bad.parse::<ByteSize>().is_err(), "{bad}");
        }
        let c: WorkerSection = toml::from_str("memory_budget = \"1G\"").unwrap();
        assert_eq!(c.memory_budget, Some(ByteSize(1 << 30)));
        let c: WorkerSection = toml::from_str("memory_budget = 4096").unwrap();
        assert_eq!(c.memory_budget, Some(ByteSize(4096)));
    }

    #[test]
    fn example_configs_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        let s = Config::load(Some(&dir.join("scheduler.toml"))).unwrap();
        assert!(s.scheduler.listen.is_some() && s.token.is_some());
        let w = Config::load(Some(&dir.join("worker.toml"))).unwrap();
        assert!(w.worker.scheduler.is_some() && w.worker.listen.is_some());
    }

    /// The example configs' `[tls]` section, uncommented, parses; flags
    /// override it setting by setting; a misspelt key is refused.
    #[test]
    fn tls_section_and_flags() {
        let text = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/worker.toml"),
        )
        .unwrap()
        .replace("# [tls]", "[tls]")
        .replace("# cert", "cert")
        .replace("# key", "key")
        .replace("# ca", "ca");
        let c: Config = toml::from_str(&text).unwrap();
        assert_eq!(
            c.tls.cert.as_deref(),
            Some(Path::new("/etc/locus/cert.pem"))
        );
        let flags = locus_protocol::tls::TlsFiles {
            ca: Some("/flag/ca.pem".into()),
            ..Default::default()
        };
        let merged = c.tls.overridden_by(&flags);
        assert_eq!(merged.ca.as_deref(), Some(Path::new("/flag/ca.pem")));
        assert_eq!(merged.key.as_deref(), Some(Path::new("/etc/locus/key.pem")));
        assert!(
            toml::from_str::<Config>(
                "[tls]
certificate = \"x\"\n"
            )
            .is_err()
        );
    }

    #[test]
    fn bad_config_names_file_and_line() {
        let p = std::env::temp_dir().join(format!("locus-bad-config-{}.toml", std::process::id()));
        std::fs::write(&p, "token = \"x\"\n[worker]\nthreds = 2\n").unwrap();
        let e = Config::load(Some(&p)).unwrap_err().to_string();
        assert!(e.contains(&format!("{}:3", p.display())), "{e}");
        let none = Config::default()
            .token(None, None, None)
            .unwrap_err()
            .to_string();
        assert!(none.contains("LOCUS_TOKEN"));
    }

    /// A token given outright wins over a token file, a flag's file over
    /// the config's token; files give their first line, trimmed; an empty,
    /// missing or oversized file is an error that names it.
    #[test]
    fn token_sources_in_order_and_bad_files_named() {
        let dir = std::env::temp_dir().join(format!("locus-token-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (good, empty, big) = (dir.join("good"), dir.join("empty"), dir.join("big"));
        std::fs::write(&good, "  s3cret \nsecond line\n").unwrap();
        std::fs::write(&empty, "\n").unwrap();
        std::fs::write(&big, vec![b'x'; 5000]).unwrap();
        let cfg = Config {
            token: Some("from-config".into()),
            token_file: Some(empty.clone()),
            ..Config::default()
        };
        let t = |flag: Option<&str>, file: Option<&Path>, c: &Config| {
            c.token(flag.map(String::from), file, None)
        };
        assert_eq!(t(Some("flag"), Some(&good), &cfg).unwrap(), "flag");
        assert_eq!(t(None, Some(&good), &cfg).unwrap(), "s3cret");
        assert_eq!(t(None, None, &cfg).unwrap(), "from-config");
        let only_file = Config {
            token_file: Some(good.clone()),
            ..Config::default()
        };
        assert_eq!(t(None, None, &only_file).unwrap(), "s3cret");
        for bad in [&empty, &big, &dir.join("missing")] {
            let e = format!("{:#}", t(None, Some(bad), &Config::default()).unwrap_err());
            assert!(e.contains(&bad.display().to_string()), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn quality_presets_parse_and_order_by_effort() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/presets");
        let p: Vec<Preset> = ["accurate", "fast", "low"]
            .iter()
            .map(|n| Preset::load(&dir.join(format!("{n}.toml"))).unwrap())
            .collect();
        assert_eq!(p[0].name, "accurate");
        // More effort and finer cache cells, from accurate to low.
        assert!(p[0].spp > p[1].spp && p[1].spp > p[2].spp);
        let c: Vec<_> = p.iter().map(|p| p.cache).collect();
        assert!(c[0].fine_solid_angle < c[1].fine_solid_angle);
        assert!(c[1].fine_solid_angle < c[2].fine_solid_angle);
        assert!(c[0].max_depth > c[1].max_depth && c[1].max_depth > c[2].max_depth);
        let a: Vec<_> = p.iter().map(|p| p.irradiance).collect();
        assert!(a[0].accuracy < a[1].accuracy && a[1].accuracy < a[2].accuracy);
        assert!(a[0].divisions > a[1].divisions && a[1].divisions > a[2].divisions);
    }

    /// Built-in presets are the files, byte for byte parsed alike, and
    /// resolve by name from any directory; an unknown name lists them.
    #[test]
    fn built_in_presets_resolve_by_name() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/presets");
        for (n, _) in BUILTIN_PRESETS {
            let b = Preset::resolve(n).unwrap();
            let f = Preset::load(&dir.join(format!("{n}.toml"))).unwrap();
            assert_eq!(
                (b.name.as_str(), b.spp, b.max_depth),
                (n, f.spp, f.max_depth)
            );
            assert_eq!(format!("{:?}", b.cache), format!("{:?}", f.cache));
            assert_eq!(b.irradiance, f.irradiance);
        }
        let by_path = Preset::resolve(dir.join("fast.toml").to_str().unwrap()).unwrap();
        assert_eq!(by_path.name, "fast");
        let e = Preset::resolve("ultra").unwrap_err().to_string();
        assert!(e.contains("accurate, fast, low"), "{e}");
    }

    #[test]
    fn bad_preset_names_file_and_line() {
        let p = std::env::temp_dir().join(format!("locus-bad-preset-{}.toml", std::process::id()));
        std::fs::write(
            &p,
            "name = \"x\"\nspp = 4\nmax_depth = 3\n[cache]\nradios = 2\n",
        )
        .unwrap();
        let e = Preset::load(&p).unwrap_err().to_string();
        assert!(e.contains(&format!("{}:5", p.display())), "{e}");
        std::fs::write(
            &p,
            "name = \"x\"\nspp = 4\nmax_depth = 3\n[cache]\nradius = -1\n",
        )
        .unwrap();
        let e = Preset::load(&p).unwrap_err().to_string();
        assert!(e.contains("radius"), "{e}");
    }
}
