#!/usr/bin/env python3
"""Lays out the seed corpora of mortar's fuzz targets in fuzz/corpus/<target>/ (FUZZING.md).

    fuzz/seeds.py [--data ../shared/data] [--mortar target/release/mortar]

Seeds are small third-party LAS/LAZ files from the shared data folder (each under 50 KiB; their
origin is in that folder's PROVENANCE.json, keyed by the path recorded in fuzz/corpus/SOURCES.txt)
and batch files and stores that mortar builds from them. Re-running it gives the same files.
"""
import argparse
import os
import shutil
import struct
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# Chosen for variety: LAS 1.0-1.4, PDRF 0-8, LAZ v1/v2/v3 (LAS 1.4) with and without chunk
# tables, COPC, EVLRs, extra bytes (good and malformed), GeoTIFF and WKT CRS records (good and
# bad), broken LASzip files, lying VLR counts, empty files.
LAS_FILES = [
    "PDAL/test/data/las/permutations/1.2-no-points.las",
    "laz-perf/cpp/test/raw-sets/no-points-1.3.las",
    "laz-perf/cpp/test/raw-sets/no-points-1.3.laz",
    "laz-perf/cpp/test/raw-sets/point10-1.0.las",
    "laz-perf/cpp/test/raw-sets/point10-1.0.laz",
    "PDAL/test/data/las/gps-time-nan.las",
    "libLAS/test/data/bad_points_1.1.las",
    "PDAL/test/data/las/hextest.las",
    "laserchicken/testdata/5points.las",
    "libLAS/test/data/1.0_1.las",
    "libLAS/test/data/1.2_2.las",
    "PDAL/test/data/las/utm15.las",
    "laspy/tests/data/unregistered_extra_bytes.las",
    "lasR/inst/extdata/malformed_extrabytes.las",
    "PDAL/test/data/las/bad_vlr_count.las",
    "PDAL/test/data/las/test_epsg_4326_axis.las",
    "lasR/inst/extdata/Example.laz",
    "PDAL/test/data/las/spec_3.las",
    "LASzip/data/broken_coder.laz",
    "LASzip/data/broken_compressor.laz",
    "LASzip/data/broken_size.laz",
    "LASzip/data/broken_type.laz",
    "PDAL/test/data/las/bad-geotiff-keys.las",
    "PDAL/test/data/las/permutations/1.2_3.las",
    "libLAS/test/data/srs_vertcs.las",
    "LASzip/example/5points_14.las",
    "lasR/inst/extdata/example.copc.laz",
    "las-rs/tests/data/autzen.laz",
    "lasR/inst/extdata/extra_byte.las",
    "PDAL/test/data/las/100-points.las",
    "las-rs/tests/data/autzen.copc.laz",
    "laspy/tests/data/1_4_w_evlr.laz",
    "PDAL/test/data/las/1.2-empty-geotiff-vlrs.las",
    "laz-rs/tests/data/point10.laz",
    "laz-rs/tests/data/point-color.laz",
    "PDAL/test/data/las/garbage_nVariableLength.las",
    "laz-perf/cpp/test/raw-sets/point-time-1.4.las.laz",
    "laz-rs/tests/data/point-time-color.laz",
    "PDAL/test/data/laszip/laszip-generated_with2bytespadding.laz",
    "PDAL/test/data/apps/simple-laszip-compressor-version-1.2r0.laz",
    "las-rs/tests/data/extrabytes.laz",
    "PDAL/test/data/las/test1_4.las",
    "laspy/tests/data/simple_with_page.copc.laz",
    "lasR/inst/extdata/las14_pdrf6.laz",
]

# Inputs that mortar turns into batch files and stores (small, different formats).
BUILD_FROM = [
    "laserchicken/testdata/5points.las",
    "PDAL/test/data/las/100-points.las",
    "las-rs/tests/data/autzen.laz",
    "laz-rs/tests/data/point-time-color.laz",
    "lasR/inst/extdata/extra_byte.las",
    "laspy/tests/data/1_4_w_evlr.laz",
]

MAX_SEED = 50 * 1024


def header_part(b):
    """The header and VLRs of a LAS file (up to the point data), plus its EVLRs if any."""
    if len(b) < 227 or b[:4] != b"LASF":
        return b
    off = struct.unpack_from("<I", b, 96)[0]
    head = b[: min(off, len(b))]
    if b[25] >= 4 and len(b) >= 251:
        evlr_start, n = struct.unpack_from("<QI", b, 235)
        if n and 0 < evlr_start < len(b):
            # keep the pointer valid: EVLRs moved right after a truncated point section
            pts = b[off : off + 64]
            body = bytearray(head + pts)
            struct.pack_into("<Q", body, 235, len(body))
            return bytes(body) + b[evlr_start:]
    return head


def put(target, name, data):
    d = os.path.join(HERE, "corpus", target)
    os.makedirs(d, exist_ok=True)
    assert len(data) <= MAX_SEED, (name, len(data))
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def seed_name(rel):
    return rel.replace("/", "__")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--mortar", default=os.path.join(ROOT, "target", "release", "mortar"))
    a = ap.parse_args()
    for t in ["las_header", "vlr_records", "las_input", "laz_pointwise", "batch_file", "store", "lod_index"]:
        shutil.rmtree(os.path.join(HERE, "corpus", t), ignore_errors=True)
    sources = []
    for rel in LAS_FILES:
        b = open(os.path.join(a.data, rel), "rb").read()
        put("las_input", seed_name(rel), b)
        put("las_header", seed_name(rel), header_part(b))
        sources.append(f"{rel}  {len(b)} bytes")
    # laz_pointwise: the stream of the one pointwise (compressor 1) fixture, as its flags and
    # point count say (mortar_fuzz::pointwise_file), and with a chunk size of u32::MAX.
    pw = "PDAL/test/data/apps/simple-laszip-compressor-version-1.2r0.laz"
    b = open(os.path.join(a.data, pw), "rb").read()
    off, count = struct.unpack_from("<I", b, 96)[0], struct.unpack_from("<I", b, 107)[0]
    for flags in (3, 3 | 8, 3 | 16):
        put("laz_pointwise", f"{seed_name(pw)}.flags{flags}", bytes([flags]) + struct.pack("<I", count) + b[off:])
    # vlr_records: format, record length, then the extra-bytes and CRS payloads of real files.
    for rel in LAS_FILES:
        b = open(os.path.join(a.data, rel), "rb").read()
        eb, proj = b"", {}
        off, n, pos = struct.unpack_from("<I", b, 96)[0], struct.unpack_from("<I", b, 100)[0], struct.unpack_from("<H", b, 94)[0]
        for _ in range(n):
            if pos + 54 > off:
                break
            uid = b[pos + 2 : pos + 18].rstrip(b"\0")
            rid, ln = struct.unpack_from("<HH", b, pos + 18)
            data = b[pos + 54 : pos + 54 + ln]
            if uid == b"LASF_Spec" and rid == 4:
                eb = data
            elif uid == b"LASF_Projection":
                proj[rid] = data
            pos += 54 + ln
        if eb or proj:
            parts = [eb] + [proj.get(k, b"") for k in (34735, 34736, 34737, 2112)]
            put("vlr_records", seed_name(rel), bytes([b[104] & 0x3F]) + b[105:107] + b"|||".join(parts))
    # batch files and stores built by mortar from a few of them
    with tempfile.TemporaryDirectory() as tmp:
        for rel in BUILD_FROM:
            src = os.path.join(a.data, rel)
            stem = seed_name(rel)
            for comp in ["none", "zstd"]:
                out = os.path.join(tmp, f"{stem}.{comp}.mbat")
                subprocess.run([a.mortar, "batch", src, "-o", out, "--compress", comp], check=True, capture_output=True)
                b = open(out, "rb").read()
                if len(b) <= MAX_SEED:
                    put("batch_file", f"{stem}.{comp}.mbat", b)
            for cap in ["40", "100000"]:
                st = os.path.join(tmp, f"{stem}.{cap}.store")
                subprocess.run([a.mortar, "build", src, "-o", st, "--leaf-capacity", cap], check=True, capture_output=True)
                parts = [open(os.path.join(st, f), "rb").read() for f in ("source.las", "hierarchy.bin", "nodes.bin")]
                packed = struct.pack("<II", len(parts[0]), len(parts[1])) + b"".join(parts)
                if len(packed) <= MAX_SEED:
                    put("store", f"{stem}.leaf{cap}.store", packed)
                # lod_index: the hierarchy's keys in the target's 16-byte form
                hb = parts[1]
                (root_log2,) = struct.unpack_from("<I", hb, 72)
                node_count = struct.unpack_from("<Q", hb, 24)[0]
                recs = bytearray([root_log2 & 0xFF])
                for i in range(node_count):
                    level, kind, ix, iy, iz, _pad, count = struct.unpack_from("<IIIIIIQ", hb, 104 + 48 * i)
                    recs += struct.pack("<BBHIII", level, kind == 0, min(count, 0xFFFF), ix, iy, iz)
                if len(recs) <= MAX_SEED:
                    put("lod_index", f"{stem}.leaf{cap}.keys", bytes(recs))
    with open(os.path.join(HERE, "corpus", "SOURCES.txt"), "w") as f:
        f.write("# Third-party files under ../shared/data used as seeds (las_input whole, las_header\n")
        f.write("# cut to header + VLRs (+ EVLRs), vlr_records their extra-bytes and CRS payloads);\n")
        f.write("# origins in ../shared/data/PROVENANCE.json. batch_file, store, lod_index seeds are\n")
        f.write("# built by mortar (fuzz/seeds.py) from: " + ", ".join(BUILD_FROM) + "\n")
        f.write("\n".join(sources) + "\n")


if __name__ == "__main__":
    sys.exit(main())
