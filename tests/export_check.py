"""Independent checks of `mortar export` outputs (tests/export.rs runs this).

    python export_check.py MANIFEST.json

The manifest is a list of jobs {"kind": "copc" | "potree", "out": PATH, "inputs": [PATHS]}
(or {"kind": "same", "format": "copc" | "potree", "a": PATH, "b": PATH}: two exports with the
same nodes holding the same records in the same order).
For each job the output is read with readers that are not mortar's: laspy's CopcReader (and
copclib when installed) for COPC, a walk of hierarchy.bin/octree.bin written here from the
Potree 2.0 format description for Potree. Every point of the inputs must come out exactly once
with every field (legacy records compared field by field after the LAS 1.4 mapping), node
queries must return the right subsets and every point must lie in its node's box. Prints one
JSON line per job: {"out", "ok", "problems", ...}; exits 1 if any job failed.
"""
import json
import struct
import sys

import laspy
import numpy as np

try:
    import copclib
except ImportError:  # CI installs it; locally it may be missing
    copclib = None

LEGACY_COMMON = ["intensity", "return_number", "number_of_returns", "scan_direction_flag",
                 "edge_of_flight_line", "synthetic", "key_point", "withheld", "user_data",
                 "point_source_id"]


def load_inputs(paths):
    arrs = [laspy.read(p) for p in paths]
    return arrs


def world_ints(las_list, scale, offset):
    """The inputs' coordinates on the output grid, exactly (int64)."""
    out = []
    for l in las_list:
        h = l.header
        cols = []
        for a, name in enumerate("XYZ"):
            raw = np.asarray(getattr(l, name), dtype=np.int64)
            if h.scales[a] == scale[a] and h.offsets[a] == offset[a]:
                cols.append(raw)
            else:
                w = raw * h.scales[a] + h.offsets[a]
                cols.append(np.round((w - offset[a]) / scale[a]).astype(np.int64))
        out.append(np.stack(cols, axis=1))
    return np.concatenate(out)


def field_table(las_list, out_fmt, names):
    cols = []
    for n in names:
        cols.append(np.concatenate([np.asarray(getattr(l, n)).astype(np.float64) for l in las_list]))
    return np.stack(cols, axis=1) if cols else np.zeros((sum(len(l.points) for l in las_list), 0))


def compare_points(problems, out_las_like, inputs, out_scale, out_offset, out_fmt):
    """out_las_like: dict of numpy columns of the output (X, Y, Z ints + fields)."""
    n_in = sum(len(l.points) for l in inputs)
    n_out = len(out_las_like["X"])
    if n_in != n_out:
        problems.append(f"{n_out} points out, {n_in} in")
        return
    src_xyz = world_ints(inputs, out_scale, out_offset)
    out_xyz = np.stack([out_las_like[k].astype(np.int64) for k in "XYZ"], axis=1)
    legacy = any(l.header.point_format.id < 6 for l in inputs)
    dims_in = set(inputs[0].point_format.dimension_names)
    names = list(LEGACY_COMMON)
    for n in ["gps_time", "red", "green", "blue", "nir"]:
        if all(n in l.point_format.dimension_names for l in inputs) and n in out_las_like:
            names.append(n)
    a_cols = [src_xyz.astype(np.float64)]
    b_cols = [out_xyz.astype(np.float64)]
    a_cols.append(field_table(inputs, out_fmt, names))
    b_cols.append(np.stack([out_las_like[n].astype(np.float64) for n in names], axis=1))
    # classification: legacy 5 bits; scan angle: legacy whole degrees -> 0.006 degree units
    a_cls = np.concatenate([np.asarray(l.classification).astype(np.float64) for l in inputs])
    a_cols.append(a_cls[:, None])
    b_cols.append(out_las_like["classification"].astype(np.float64)[:, None])
    if legacy:
        rank = np.concatenate([
            np.asarray(l.scan_angle_rank).astype(np.float64) if l.header.point_format.id < 6
            else np.round(np.asarray(l.scan_angle).astype(np.float64) * 0.006) for l in inputs])
        a_cols.append(rank[:, None])
        b_cols.append(np.round(out_las_like["scan_angle_raw"].astype(np.float64) * 0.006)[:, None])
    else:
        a_cols.append(np.concatenate([np.asarray(l.points.array["scan_angle"]).astype(np.float64) for l in inputs])[:, None])
        b_cols.append(out_las_like["scan_angle_raw"].astype(np.float64)[:, None])
        for n in ["scanner_channel", "overlap"]:
            if n in dims_in:
                a_cols.append(np.concatenate([np.asarray(getattr(l, n)).astype(np.float64) for l in inputs])[:, None])
                b_cols.append(out_las_like[n].astype(np.float64)[:, None])
    if "extra" in out_las_like:
        ex = np.concatenate([extra_bytes(l) for l in inputs])
        a_cols.append(ex.astype(np.float64))
        b_cols.append(out_las_like["extra"].astype(np.float64))
    A = np.concatenate(a_cols, axis=1)
    B = np.concatenate(b_cols, axis=1)
    A = A[np.lexsort(A.T[::-1])]
    B = B[np.lexsort(B.T[::-1])]
    if not np.array_equal(A, B, equal_nan=True):
        bad = np.nonzero(~np.all((A == B) | (np.isnan(A) & np.isnan(B)), axis=1))[0]
        problems.append(f"{len(bad)} of {n_in} points differ after sorting (first: in {A[bad[0]].tolist()} out {B[bad[0]].tolist()})")


def extra_bytes(l):
    rl = l.header.point_format.size
    base = {0: 20, 1: 28, 2: 26, 3: 34, 6: 30, 7: 36, 8: 38}[l.header.point_format.id]
    raw = np.frombuffer(l.points.array.tobytes(), dtype=np.uint8).reshape(-1, rl)
    return raw[:, base:]


def columns_of(pts, fmt, rl):
    raw = np.frombuffer(pts.array.tobytes(), dtype=np.uint8).reshape(-1, rl)
    base = {6: 30, 7: 36, 8: 38}[fmt]
    d = {"X": np.asarray(pts.X), "Y": np.asarray(pts.Y), "Z": np.asarray(pts.Z)}
    for n in LEGACY_COMMON + ["classification", "gps_time", "scanner_channel", "overlap"]:
        d[n] = np.asarray(getattr(pts, n))
    if fmt >= 7:
        for n in ["red", "green", "blue"]:
            d[n] = np.asarray(getattr(pts, n))
    if fmt == 8:
        d["nir"] = np.asarray(pts.nir)
    d["scan_angle_raw"] = raw[:, 18:20].copy().view("<i2")[:, 0]
    if rl > base:
        d["extra"] = raw[:, base:]
    return d


def check_copc(job):
    problems = []
    out, inputs = job["out"], load_inputs(job["inputs"])
    res = {"out": out}
    with laspy.CopcReader.open(out) as r:
        h = r.header
        fmt, rl = h.point_format.id, h.point_format.size
        if fmt not in (6, 7, 8):
            problems.append(f"point format {fmt}")
        info = r.copc_info
        pts = r.query()
        res["points"] = len(pts)
        compare_points(problems, columns_of(pts, fmt, rl), inputs, h.scales, h.offsets, fmt)
        # levels partition the points
        depth = 0
        total = 0
        for lvl in range(0, 64):
            q = r.query(level=lvl)
            total += len(q)
            if len(q) == 0 and total == len(pts):
                depth = lvl
                break
        if total != len(pts):
            problems.append(f"level queries give {total} points, the whole query {len(pts)}")
        res["depth"] = depth
        # box queries: a quarter and a corner
        x, y = np.asarray(pts.x), np.asarray(pts.y)
        for fx, fy in [(0.5, 0.5), (0.3, 0.8)]:
            mn, mx = np.array([x.min(), y.min()]), np.array([x.max(), y.max()])
            cut = mn + (mx - mn) * np.array([fx, fy])
            # a quarter grid step off the grid: no point on the box edge, where readers round differently (laspy rounds half to even)
            cut = h.offsets[:2] + h.scales[:2] * (np.floor((cut - h.offsets[:2]) / h.scales[:2]) + 0.25)
            z = np.asarray(pts.z)
            b = laspy.copc.Bounds(mins=np.array([mn[0] - 1, mn[1] - 1, z.min()]), maxs=np.array([cut[0], cut[1], z.max()]))
            q = r.query(bounds=b)
            X, Y = np.asarray(pts.X), np.asarray(pts.Y)
            lo = (mn - 1 - h.offsets[:2]) / h.scales[:2]
            up = (cut - h.offsets[:2]) / h.scales[:2]
            exp = int(((X >= lo[0]) & (X <= up[0]) & (Y >= lo[1]) & (Y <= up[1])).sum())
            if len(q) != exp:
                problems.append(f"box query {cut.tolist()}: {len(q)} points, {exp} expected")
    # the chunks read one by one against their keys' boxes
    problems += node_boxes_copc(out)
    if copclib is not None:
        fr = copclib.FileReader(out)
        nodes = fr.GetAllNodes()
        s = sum(n.point_count for n in nodes)
        if s != res["points"]:
            problems.append(f"copclib: nodes hold {s} points")
        if not fr.ValidateSpatialBounds(False):
            problems.append("copclib: ValidateSpatialBounds failed")
        res["copclib_nodes"] = len(nodes)
    else:
        res["copclib"] = "not installed"
    res["ok"] = not problems
    res["problems"] = problems
    return res


def node_boxes_copc(path):
    """Each chunk's points inside its key's box (center +- halfsize / 2^level), in doubles."""
    problems = []
    with laspy.CopcReader.open(path) as r:
        info = r.copc_info
        c, hs = np.array(info.center), info.halfsize
        mins = c - hs
        # walk the hierarchy pages ourselves
        with open(path, "rb") as f:
            data = f.read()
        entries = []
        def page(off, size):
            for i in range(0, size, 32):
                lvl, x, yy, z, o, bs, pc = struct.unpack_from("<iiiiQii", data, off + i)
                if pc == -1:
                    page(o, bs)
                else:
                    entries.append((lvl, x, yy, z, o, bs, pc))
        page(info.hierarchy_root_offset, info.hierarchy_root_size)
        keys = set()
        for (lvl, x, yy, z, o, bs, pc) in entries:
            if (lvl, x, yy, z) in keys:
                problems.append(f"key {(lvl, x, yy, z)} listed twice")
            keys.add((lvl, x, yy, z))
        for (lvl, x, yy, z, o, bs, pc) in entries:
            if lvl > 0 and (lvl - 1, x // 2, yy // 2, z // 2) not in keys:
                problems.append(f"node {(lvl, x, yy, z)} has no parent entry")
        total = 0
        for (lvl, x, yy, z, o, bs, pc) in entries:
            if pc <= 0:
                continue
            total += pc
            node = laspy.copc.OctreeNode()
            node.key.level, node.key.x, node.key.y, node.key.z = lvl, x, yy, z
            node.offset, node.byte_size, node.point_count = o, bs, pc
            pts = r._fetch_and_decompress_points_of_nodes([node])
            if len(pts) != pc:
                problems.append(f"node {(lvl, x, yy, z)}: {len(pts)} points decoded, {pc} listed")
            edge = 2 * hs / (1 << lvl)
            lo = mins + np.array([x, yy, z]) * edge
            hi = lo + edge
            p = np.stack([np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)], axis=1)
            out = ~np.all((p >= lo) & (p <= hi), axis=1)
            if out.any():
                problems.append(f"node {(lvl, x, yy, z)}: {int(out.sum())} of {pc} points outside its box")
    return problems


POTREE_TYPES = {"int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2", "int32": "<i4",
                "uint32": "<u4", "int64": "<i8", "uint64": "<u8", "float": "<f4", "double": "<f8"}


def walk_potree(d):
    meta = json.load(open(f"{d}/metadata.json"))
    hier = open(f"{d}/hierarchy.bin", "rb").read()
    nodes = []

    def chunk(off, size, first_key):
        recs = [struct.unpack_from("<BBIQQ", hier, off + i) for i in range(0, size, 22)]
        keys = [first_key]
        k = 0
        for (ty, mask, n, bo, bs) in recs:
            key = keys[k]
            k += 1
            if ty == 2:
                chunk(bo, bs, key)
                continue
            nodes.append((key, ty, mask, n, bo, bs))
            for c in range(8):
                if mask >> c & 1:
                    lvl, x, y, z = key
                    keys.append((lvl + 1, 2 * x + (c >> 2 & 1), 2 * y + (c >> 1 & 1), 2 * z + (c & 1)))
        if k != len(keys):
            raise ValueError(f"chunk at {off}: {len(keys)} nodes named, {k} records")
    chunk(0, meta["hierarchy"]["firstChunkSize"], (0, 0, 0, 0))
    return meta, nodes


def check_potree(job):
    problems = []
    d, inputs = job["out"], load_inputs(job["inputs"])
    res = {"out": d}
    meta, nodes = walk_potree(d)
    octree = np.fromfile(f"{d}/octree.bin", dtype=np.uint8)
    attrs = meta["attributes"]
    dt = np.dtype([(a["name"], POTREE_TYPES[a["type"]], (a["numElements"],)) for a in attrs])
    keys = [n[0] for n in nodes]
    if len(set(keys)) != len(keys):
        problems.append("a node is listed twice")
    total = sum(n[3] for n in nodes)
    res["points"], res["nodes"] = total, len(nodes)
    if total != meta["points"]:
        problems.append(f"hierarchy holds {total} points, metadata.json says {meta['points']}")
    bmin = np.array(meta["boundingBox"]["min"])
    edge0 = np.array(meta["boundingBox"]["max"]) - bmin
    scale, offset = np.array(meta["scale"]), np.array(meta["offset"])
    parts = []
    used = np.zeros(len(octree), dtype=bool)
    for (key, ty, mask, n, bo, bs) in nodes:
        if bs != n * dt.itemsize:
            problems.append(f"node {key}: {bs} bytes for {n} points of {dt.itemsize}")
            continue
        if n == 0:
            continue
        if used[bo:bo + bs].any():
            problems.append(f"node {key}: bytes shared with another node")
        used[bo:bo + bs] = True
        a = np.frombuffer(octree[bo:bo + bs].tobytes(), dtype=dt)
        lvl, x, y, z = key
        e = edge0 / (1 << lvl)
        lo = bmin + np.array([x, y, z]) * e
        w = a["position"].astype(np.float64) * scale + offset
        outside = ~np.all((w >= lo) & (w <= lo + e), axis=1)
        if outside.any():
            problems.append(f"node {key}: {int(outside.sum())} of {n} points outside its box")
        parts.append(a)
    if used.sum() != len(octree):
        problems.append(f"{len(octree) - int(used.sum())} bytes of octree.bin belong to no node")
    allp = np.concatenate(parts) if parts else np.zeros(0, dtype=dt)
    cols = {"X": allp["position"][:, 0], "Y": allp["position"][:, 1], "Z": allp["position"][:, 2]}
    names = {"intensity": "intensity", "return number": "return_number", "number of returns": "number_of_returns",
             "scan direction flag": "scan_direction_flag", "edge of flight line": "edge_of_flight_line",
             "user data": "user_data", "point source id": "point_source_id", "classification": "classification",
             "gps-time": "gps_time", "nir": "nir", "scanner channel": "scanner_channel"}
    for a in attrs:
        if a["name"] in names:
            cols[names[a["name"]]] = allp[a["name"]][:, 0]
    flags = allp["classification flags"][:, 0]
    cols["synthetic"], cols["key_point"], cols["withheld"], cols["overlap"] = flags & 1, flags >> 1 & 1, flags >> 2 & 1, flags >> 3 & 1
    cols["scan_angle_raw"] = allp["scan angle"][:, 0]
    if "rgb" in allp.dtype.names:
        cols["red"], cols["green"], cols["blue"] = (allp["rgb"][:, i] for i in range(3))
    if "extra bytes" in allp.dtype.names:
        cols["extra"] = allp["extra bytes"]
    fmt = 8 if "nir" in cols else 7 if "red" in cols else 6
    compare_points(problems, cols, inputs, scale, offset, fmt)
    res["ok"] = not problems
    res["problems"] = problems
    return res


def raster(job):
    """Pixels a 1-pixel top view of the inputs covers, with the browser check's camera fit."""
    inputs = load_inputs(job["inputs"])
    x = np.concatenate([np.asarray(l.x) for l in inputs])
    y = np.concatenate([np.asarray(l.y) for l in inputs])
    W, H = job.get("width", 800), job.get("height", 600)
    cx, cy = (x.min() + x.max()) / 2, (y.min() + y.max()) / 2
    hw, hh = max(x.max() - x.min(), 1e-9) / 2, max(y.max() - y.min(), 1e-9) / 2
    if hw / hh > W / H:
        hh = hw * H / W
    else:
        hw = hh * W / H
    px = np.clip(np.floor((x - (cx - hw)) / (2 * hw) * W), 0, W - 1).astype(np.int64)
    py = np.clip(np.floor(((cy + hh) - y) / (2 * hh) * H), 0, H - 1).astype(np.int64)
    return {"out": job.get("out"), "ok": True, "problems": [], "covered_pixels": int(len(np.unique(py * W + px)))}


def copc_nodes(path):
    """{key: raw records of the node, in its order}, from a walk of the hierarchy pages."""
    out = {}
    with laspy.CopcReader.open(path) as r:
        info = r.copc_info
        rl = r.header.point_format.size
        with open(path, "rb") as f:
            data = f.read()

        def page(off, size):
            for i in range(0, size, 32):
                lvl, x, yy, z, o, bs, pc = struct.unpack_from("<iiiiQii", data, off + i)
                if pc == -1:
                    page(o, bs)
                    continue
                raw = b""
                if pc > 0:
                    node = laspy.copc.OctreeNode()
                    node.key.level, node.key.x, node.key.y, node.key.z = lvl, x, yy, z
                    node.offset, node.byte_size, node.point_count = o, bs, pc
                    raw = r._fetch_and_decompress_points_of_nodes([node]).array.tobytes()
                out[(lvl, x, yy, z)] = raw
        page(info.hierarchy_root_offset, info.hierarchy_root_size)
    return out


def potree_nodes(d):
    meta, nodes = walk_potree(d)
    octree = open(f"{d}/octree.bin", "rb").read()
    return {key: octree[bo:bo + bs] for (key, ty, mask, n, bo, bs) in nodes}


def same(job):
    """Two exports of the same input (in memory and through run files): the same nodes, each
    with the same records in the same order; the files may place the nodes differently."""
    problems = []
    read = copc_nodes if job["format"] == "copc" else potree_nodes
    a, b = read(job["a"]), read(job["b"])
    if set(a) != set(b):
        problems.append(f"nodes differ: {len(set(a) - set(b))} only in a, {len(set(b) - set(a))} only in b")
    differ = [k for k in set(a) & set(b) if a[k] != b[k]]
    if differ:
        problems.append(f"{len(differ)} nodes hold other records, e.g. {sorted(differ)[0]}")
    return {"out": job["b"], "ok": not problems, "problems": problems, "nodes": len(a),
            "bytes": sum(len(v) for v in a.values())}


def main():
    jobs = json.load(open(sys.argv[1]))
    bad = False
    for job in jobs:
        try:
            r = {"copc": check_copc, "potree": check_potree, "raster": raster, "same": same}[job["kind"]](job)
        except Exception as e:  # a reader that fails is a failed check
            r = {"out": job.get("out"), "ok": False, "problems": [f"{type(e).__name__}: {e}"]}
        bad |= not r["ok"]
        print(json.dumps(r), flush=True)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
