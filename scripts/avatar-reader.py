#!/usr/bin/env python3
"""An independent reader of drape's avatar files (docs/avatar-format.md): numpy and the
standard library only, no drape code.

    python scripts/avatar-reader.py NAME.avatar [--out gaussians.npz]

Opens the archive, checks its format and version, verifies the checksum (CRC-32,
zlib's, over every .npy entry's bytes in name order), prints what the file holds, and
with --out writes each human layer's canonical Gaussians (L.means, L.quats,
L.log_scales, float32 as the file stores them) to an .npz. Exits 1 with one line naming
the file on a file it refuses.
"""

import argparse
import io
import json
import sys
import zipfile
import zlib

import numpy as np

FORMAT = "drape-avatar"
VERSION = 1
HEADER = "header.json"


class Refused(Exception):
    pass


def read(path):
    """(header, arrays by name) of the avatar file at path, its checksum verified."""
    try:
        z = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as e:
        raise Refused(f"not a readable avatar file: {e}")
    with z:
        names = z.namelist()
        if HEADER not in names:
            raise Refused(f"no {HEADER} (not an avatar file?)")
        header = json.loads(z.read(HEADER))
        if header.get("format") != FORMAT:
            raise Refused(f'format is not "{FORMAT}"')
        if header.get("format_version") != VERSION:
            raise Refused(
                f"format version {header.get('format_version')}, this reader reads {VERSION}"
            )
        crc = 0
        arrays = {}
        for name in sorted(n for n in names if n != HEADER):
            if not name.endswith(".npy"):
                raise Refused(f"entry {name} is neither {HEADER} nor an .npy")
            data = z.read(name)
            crc = zlib.crc32(data, crc)
            arrays[name[: -len(".npy")]] = np.load(io.BytesIO(data), allow_pickle=False)
        checksum = f"crc32:{crc:08x}"
        if checksum != header["checksum"]:
            raise Refused(
                f"checksum mismatch: the header says {header['checksum']}, the arrays give {checksum}"
            )
    return header, arrays


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("file")
    p.add_argument("--out", help="write the canonical Gaussians to this .npz")
    a = p.parse_args()
    try:
        header, arrays = read(a.file)
    except Refused as e:
        print(f"{a.file}: {e}", file=sys.stderr)
        return 1
    gaussians = {}
    for layer in header["layers"]:
        for k in ("means", "quats", "log_scales"):
            gaussians[f"{layer}.{k}"] = arrays[f"{layer}.{k}"]
        print(f"{layer}: {arrays[layer + '.means'].shape[0]} Gaussians, triplane "
              f"{'x'.join(map(str, arrays[layer + '.triplane'].shape))}")
    print(f"{a.file}: format {header['format']} {header['format_version']}, "
          f"{header['checksum']} verified, {len(arrays)} arrays, step {header['step']}, "
          f"default camera {header['width']}x{header['height']}")
    if a.out:
        np.savez(a.out, **gaussians)
    return 0


if __name__ == "__main__":
    sys.exit(main())
