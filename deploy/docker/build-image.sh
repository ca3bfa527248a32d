#!/usr/bin/env bash
# Builds the locus image (default tag locus:latest) from this checkout:
#   deploy/docker/build-image.sh [TAG]
# The binary is linked statically (glibc's static libc, crt-static) so the
# image is FROM scratch and needs no registry. With LOCUS_BIN=path, that
# binary is used instead; if it is dynamically linked, exactly the shared
# libraries it needs (ldd) go into the image beside it.
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
tag="${1:-locus:latest}"
ctx="$root/target/docker-context"

if [[ -z "${LOCUS_BIN:-}" ]]; then
    target="$(rustc -vV | sed -n 's/^host: //p')"
    echo "building a static locus for $target" >&2
    flags="-C target-feature=+crt-static"
    # RUSTFLAGS replaces .cargo/config.toml's flags: its target-cpu is repeated.
    if [[ "$target" == x86_64-* ]]; then
        flags="$flags -C target-cpu=x86-64-v2"
    fi
    (cd "$root" && RUSTFLAGS="$flags" \
        CARGO_TARGET_DIR="$root/target/static" \
        cargo build --release --locked --target "$target" -p locus)
    LOCUS_BIN="$root/target/static/$target/release/locus"
fi

rm -rf "$ctx"
mkdir -p "$ctx/tmp" "$ctx/var/lib/locus"
chmod 1777 "$ctx/tmp"
# The scheduler's --state directory: a named volume mounted there starts
# as this directory, writable by the image's user (no shell to chown it).
chmod 1777 "$ctx/var/lib/locus"
cp "$LOCUS_BIN" "$ctx/locus"
# Symbols stay (a panic's backtrace names its functions); the line tables
# the release profile keeps would double the image.
if command -v strip >/dev/null 2>&1; then
    strip --strip-debug "$ctx/locus"
fi
if ldd "$LOCUS_BIN" >/dev/null 2>&1; then
    # Dynamically linked: its libraries and loader, at the paths it names.
    ldd "$LOCUS_BIN" | awk '/=> \// {print $3} /^\s*\/.*ld-linux/ {print $1}' |
        while read -r lib; do
            mkdir -p "$ctx$(dirname "$lib")"
            cp -L "$lib" "$ctx$lib"
        done
fi
cp "$root/deploy/docker/Dockerfile" "$ctx/Dockerfile"
printf 'Dockerfile\n.dockerignore\n' >"$ctx/.dockerignore"
echo "image context: $(du -sh "$ctx" | cut -f1) in $ctx" >&2
docker build -q -t "$tag" -f "$ctx/Dockerfile" "$ctx" >/dev/null
echo "$tag"
