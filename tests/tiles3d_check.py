#!/usr/bin/env python3
"""Independent check of a 3D Tiles export against its LAS/LAZ input (laspy, pyproj, numpy).

Usage: tiles3d_check.py TILESET_DIR INPUT.las|laz [EPSG]   (prints one JSON line)

Reads tileset.json and every external tileset, decodes every .glb tile by the glTF 2.0 spec
(the node's translation/scale, KHR_mesh_quantization or float positions, glTF's y-up turned to
3D Tiles' z-up, the tile transforms down from the root) to ECEF, and compares with the input
read by laspy and transformed by pyproj (PROJ) to EPSG:4978:

- every point once: the counts agree, and the multisets of (intensity, classification, RGB)
  are equal;
- placement: the centroid, the per-axis extremes and the covariance of the points in ECEF agree
  (order-free statistics: a point misplaced by more than the tolerance moves the extremes or
  the spread); reported as the largest difference in metres;
- the root bounding box's centre against the centre of the same box (east-north-up, at the
  root's frame) of the input's points transformed by PROJ (`ref_centre_ecef`, which the
  CesiumJS check compares with the bounding sphere CesiumJS computes).

PROJ may pick another datum transformation than mortar (mortar uses the null or +towgs84
ones of the EPSG PROJ.4 definitions; PROJ picks the most accurate of its database, e.g.
NAD83(HARN) to WGS 84 (3), 1.3 m away at Autzen): the script tries every operation pyproj
offers for the CRS pair and reports the one closest to mortar's, its name, and the distance to
PROJ's default. z is in the horizontal unit when the CRS has no vertical part (LAS convention).
"""
import json
import struct
import sys
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS
from pyproj.transformer import TransformerGroup, Transformer


def mat(t):
    return np.array(t, dtype=np.float64).reshape(4, 4).T  # column-major


def tiles(path: Path, parent: np.ndarray, out: list):
    doc = json.loads(path.read_text())
    walk(doc["root"], path.parent, parent, out)


def walk(t, base: Path, parent: np.ndarray, out: list):
    m = parent @ mat(t["transform"]) if "transform" in t else parent
    c = t.get("content")
    if c:
        uri = base / c["uri"]
        if uri.suffix == ".json":
            tiles(uri, m, out)
        else:
            out.append((uri, m, t["boundingVolume"]["box"]))
    for k in t.get("children", []):
        walk(k, base, m, out)


Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def decode(glb: Path):
    b = glb.read_bytes()
    assert b[:4] == b"glTF", glb
    jl = struct.unpack_from("<I", b, 12)[0]
    doc = json.loads(b[20:20 + jl])
    bin_ = b[20 + jl + 8:]
    node = doc["nodes"][0]
    prim = doc["meshes"][0]["primitives"][0]
    bv = doc["bufferViews"][0]
    stride = bv["byteStride"]

    def acc(name):
        if name not in prim["attributes"]:
            return None
        a = doc["accessors"][prim["attributes"][name]]
        dt = {5121: np.uint8, 5123: np.uint16, 5126: np.float32}[a["componentType"]]
        k = {"SCALAR": 1, "VEC3": 3}[a["type"]]
        n = a["count"]
        raw = np.frombuffer(bin_, dtype=np.uint8, count=n * stride).reshape(n, stride)
        cols = raw[:, a["byteOffset"]:a["byteOffset"] + k * np.dtype(dt).itemsize].copy()
        return cols.view(dt).reshape(n, k)

    pos = acc("POSITION").astype(np.float64)
    t = np.array(node.get("translation", [0, 0, 0]))
    s = np.array(node.get("scale", [1, 1, 1]))
    g = pos * s + t
    return g, acc("COLOR_0"), acc("_INTENSITY"), acc("_CLASSIFICATION")


def main():
    d, inp = Path(sys.argv[1]), sys.argv[2]
    out = []
    tiles(d / "tileset.json", np.eye(4), out)
    xyz, attrs = [], []
    for uri, m, _ in out:
        g, rgb, inten, cls = decode(uri)
        h = np.c_[g, np.ones(len(g))] @ (m @ Y_UP_TO_Z_UP).T
        xyz.append(h[:, :3])
        cols = [inten if inten is not None else np.zeros((len(g), 1)), cls, rgb if rgb is not None else np.zeros((len(g), 0))]
        attrs.append(np.hstack([c.astype(np.int64) for c in cols]))
    xyz = np.vstack(xyz)
    attrs = np.vstack(attrs)
    las = laspy.read(inp)
    crs = CRS.from_epsg(int(sys.argv[3])) if len(sys.argv) > 3 else las.header.parse_crs()
    if crs is None:
        # No CRS: the tileset is in the input's own coordinates (a translation).
        ref = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        ia = np.column_stack([np.asarray(las.intensity), np.asarray(las.classification)] + ([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)] if "red" in las.point_format.dimension_names else []))
        sa = attrs[np.lexsort(attrs.T[::-1])]
        sb = ia.astype(np.int64)[np.lexsort(ia.T[::-1].astype(np.int64))]
        print(json.dumps({
            "points": int(len(xyz)), "input_points": int(len(ref)), "local_frame": True,
            "attributes_equal": bool(sa.shape == sb.shape and np.array_equal(sa, sb)),
            "centroid_m": float(np.linalg.norm(xyz.mean(0) - ref.mean(0))),
            "extremes_m": float(max(np.abs(xyz.min(0) - ref.min(0)).max(), np.abs(xyz.max(0) - ref.max(0)).max())),
            "covariance_m2": float(np.abs(np.cov(xyz.T) - np.cov(ref.T)).max()) if len(xyz) > 1 else 0.0,
            "root_centre_m": 0.0, "tiles": len(out),
        }))
        return
    h_unit = crs.axis_info[0].unit_conversion_factor if crs.is_projected else 1.0
    has_vertical = crs.is_compound
    x, y = np.asarray(las.x), np.asarray(las.y)
    z = np.asarray(las.z) * (1.0 if has_vertical else h_unit)
    group = TransformerGroup(crs, 4978, always_xy=True)
    default = Transformer.from_crs(crs, 4978, always_xy=True)
    # mortar's centre in the report is compared per operation below; the per-point check
    # uses the operation closest to mortar's output centroid.
    ours_centroid = xyz.mean(axis=0)
    best = None
    for t in group.transformers:
        e = np.column_stack(t.transform(x, y, z))
        if not np.all(np.isfinite(e)):
            continue
        dist = float(np.linalg.norm(e.mean(axis=0) - ours_centroid))
        if best is None or dist < best[0]:
            best = (dist, t.description, e)
    dist, name, ref = best
    e_def = np.column_stack(default.transform(x, y, z))
    ext = float(max(np.abs(xyz.min(0) - ref.min(0)).max(), np.abs(xyz.max(0) - ref.max(0)).max()))
    cov = float(np.abs(np.cov(xyz.T) - np.cov(ref.T)).max()) if len(xyz) > 1 else 0.0
    ia = np.column_stack([np.asarray(las.intensity), np.asarray(las.classification)] + ([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)] if "red" in las.point_format.dimension_names else []))
    # colours: 8-bit tiles hold the 8-bit values as they are (all <= 255 in such inputs)
    sa = attrs[np.lexsort(attrs.T[::-1])]
    sb = ia.astype(np.int64)[np.lexsort(ia.T[::-1].astype(np.int64))]
    root_box = json.loads((d / "tileset.json").read_text())["root"]
    rm = mat(root_box["transform"])
    c_local = np.array(root_box["boundingVolume"]["box"][:3] + [1.0])
    c_ecef = (rm @ c_local)[:3]
    lo = np.array([las.header.mins[0], las.header.mins[1], las.header.mins[2] * (1.0 if has_vertical else h_unit)])
    hi = np.array([las.header.maxs[0], las.header.maxs[1], las.header.maxs[2] * (1.0 if has_vertical else h_unit)])
    mid = (lo + hi) / 2
    # the box of the data is the box of the points in the ENU frame: compare with the centre of
    # the transformed points' ENU box, which is what the tileset's root box is
    enu = np.linalg.inv(rm)
    ref_local = np.c_[ref, np.ones(len(ref))] @ enu.T
    ref_centre = (rm @ np.r_[(ref_local[:, :3].min(0) + ref_local[:, :3].max(0)) / 2, 1.0])[:3]
    mid_ecef = np.array(default.transform(mid[0], mid[1], mid[2]))
    print(json.dumps({
        "points": int(len(xyz)),
        "input_points": int(len(x)),
        "attributes_equal": bool(sa.shape == sb.shape and np.array_equal(sa, sb)),
        "operation": name,
        "centroid_m": float(np.linalg.norm(xyz.mean(0) - ref.mean(0))),
        "extremes_m": ext,
        "covariance_m2": cov,
        "centroid_vs_proj_default_m": float(np.linalg.norm(xyz.mean(0) - e_def.mean(0))),
        "root_centre_m": float(np.linalg.norm(c_ecef - ref_centre)),
        "ref_centre_ecef": [float(v) for v in ref_centre],
        "root_centre_vs_input_box_centre_m": float(np.linalg.norm(c_ecef - mid_ecef)),
        "tiles": len(out),
    }))


if __name__ == "__main__":
    main()
