//! One 3D Tiles tile as glTF 2.0 binary (`.glb`): a point primitive (mode 0) whose vertices
//! are the node's points, interleaved in one buffer view. The one definition of the layout:
//!
//! | attribute | accessor | bytes in the vertex |
//! |---|---|---|
//! | `POSITION` | `UNSIGNED_SHORT` VEC3 (`KHR_mesh_quantization`) or `FLOAT` VEC3 | 8 or 12 |
//! | `COLOR_0` (inputs with RGB) | `UNSIGNED_BYTE` VEC3 normalized (8-bit colour) or `UNSIGNED_SHORT` VEC3 normalized (16-bit) | 4 or 8 |
//! | `_INTENSITY` (inputs with intensity) | `UNSIGNED_SHORT` SCALAR | 4 |
//! | `_CLASSIFICATION` | `UNSIGNED_BYTE` SCALAR | 4 |
//!
//! Every attribute starts on 4 bytes (glTF's vertex alignment rule). `_INTENSITY` and
//! `_CLASSIFICATION` are described by `EXT_structural_metadata` property attributes (class
//! `point`), so viewers can style by them. The material is unlit (`KHR_materials_unlit`).
//!
//! Positions: the tile's points in the tileset's frame (z up) are written in glTF's frame (y up:
//! `(x, z, -y)`, which 3D Tiles turns back). Quantized positions (`q` in 0..=65535 per axis over
//! the tile's box, the mesh node's `translation` and `scale` undoing it) are used where one step
//! of the 16-bit grid is no larger than the input's own resolution (its LAS scale); elsewhere
//! (large boxes of coarse levels) positions are 32-bit floats around the box centre. The error
//! either way is at most half a step (quantized) or 2^-24 of the box (float), and is reported.

use serde_json::json;

/// What a vertex holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Attrs {
    /// 0: no colour, 1: 8-bit, 2: 16-bit.
    pub color: u8,
    pub intensity: bool,
    pub classification: bool,
}

/// How positions are stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Positions {
    /// 16-bit integers over `[lo, lo + 65535 * step]` in glTF's frame.
    Quantized { lo: [f64; 3], step: [f64; 3] },
    /// 32-bit floats around `centre` in glTF's frame.
    Float { centre: [f64; 3] },
}

/// One point of a tile: its position in the tileset's frame and its attributes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Point {
    pub p: [f64; 3],
    pub rgb: [u16; 3],
    pub intensity: u16,
    pub classification: u8,
}

/// glTF's y-up frame of a tileset-frame (z-up) position.
#[inline]
pub(crate) fn gltf_of(p: [f64; 3]) -> [f64; 3] {
    [p[0], p[2], -p[1]]
}

/// The box of a tile's points in the tileset's frame, and its glTF-frame counterpart.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Bounds {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
}

impl Bounds {
    pub(crate) const EMPTY: Bounds = Bounds { lo: [f64::INFINITY; 3], hi: [f64::NEG_INFINITY; 3] };
    pub(crate) fn add(&mut self, p: [f64; 3]) {
        for a in 0..3 {
            self.lo[a] = self.lo[a].min(p[a]);
            self.hi[a] = self.hi[a].max(p[a]);
        }
    }
    pub(crate) fn union(&mut self, o: &Bounds) {
        self.add(o.lo);
        self.add(o.hi);
    }
    fn gltf(&self) -> ([f64; 3], [f64; 3]) {
        let (a, b) = (gltf_of(self.lo), gltf_of(self.hi));
        ([0, 1, 2].map(|i| a[i].min(b[i])), [0, 1, 2].map(|i| a[i].max(b[i])))
    }
}

/// The position storage of a tile of bounds `b`: quantized when a 16-bit step is at most
/// `resolution` (the input's resolution in the tileset's units), else floats.
pub(crate) fn positions_for(b: &Bounds, resolution: f64) -> Positions {
    let (lo, hi) = b.gltf();
    let ext = [0, 1, 2].map(|a| hi[a] - lo[a]);
    let widest = ext.iter().cloned().fold(0.0, f64::max);
    if widest / 65535.0 <= resolution {
        Positions::Quantized { lo, step: ext.map(|e| if e > 0.0 { e / 65535.0 } else { 1.0 }) }
    } else {
        Positions::Float { centre: [0, 1, 2].map(|a| (lo[a] + hi[a]) / 2.0) }
    }
}

impl Positions {
    /// The largest distance between a point and where the tile puts it, for a tile of
    /// bounds `b` (half a step, or the float rounding around the centre).
    pub(crate) fn error_bound(&self, b: &Bounds) -> f64 {
        match self {
            Positions::Quantized { step, .. } => {
                // an axis of no extent (step 1 by convention) holds its one value exactly
                let (lo, hi) = b.gltf();
                (0..3)
                    .filter(|&a| hi[a] > lo[a])
                    .map(|a| (step[a] / 2.0) * (step[a] / 2.0))
                    .sum::<f64>()
                    .sqrt()
            }
            Positions::Float { .. } => {
                let half = [0, 1, 2].map(|a| (b.hi[a] - b.lo[a]) / 2.0);
                half.iter()
                    .map(|h| (h * f32::EPSILON as f64) * (h * f32::EPSILON as f64))
                    .sum::<f64>()
                    .sqrt()
            }
        }
    }
}

impl Attrs {
    fn pos_len(p: &Positions) -> usize {
        match p {
            Positions::Quantized { .. } => 8,
            Positions::Float { .. } => 12,
        }
    }
    /// Bytes per vertex.
    pub(crate) fn stride(&self, p: &Positions) -> usize {
        Self::pos_len(p)
            + match self.color {
                1 => 4,
                2 => 8,
                _ => 0,
            }
            + if self.intensity { 4 } else { 0 }
            + if self.classification { 4 } else { 0 }
    }
}

/// The vertices of `points`, interleaved as the module table says.
pub(crate) fn vertices(points: &[Point], attrs: Attrs, pos: &Positions) -> Vec<u8> {
    let stride = attrs.stride(pos);
    let mut out = vec![0u8; points.len() * stride];
    for (v, pt) in out.chunks_exact_mut(stride).zip(points) {
        let g = gltf_of(pt.p);
        let mut o = match pos {
            Positions::Quantized { lo, step } => {
                for a in 0..3 {
                    let q = ((g[a] - lo[a]) / step[a]).round().clamp(0.0, 65535.0) as u16;
                    v[2 * a..2 * a + 2].copy_from_slice(&q.to_le_bytes());
                }
                8
            }
            Positions::Float { centre } => {
                for a in 0..3 {
                    let f = (g[a] - centre[a]) as f32;
                    v[4 * a..4 * a + 4].copy_from_slice(&f.to_le_bytes());
                }
                12
            }
        };
        match attrs.color {
            1 => {
                for c in 0..3 {
                    v[o + c] = pt.rgb[c].min(255) as u8;
                }
                o += 4;
            }
            2 => {
                for c in 0..3 {
                    v[o + 2 * c..o + 2 * c + 2].copy_from_slice(&pt.rgb[c].to_le_bytes());
                }
                o += 8;
            }
            _ => {}
        }
        if attrs.intensity {
            v[o..o + 2].copy_from_slice(&pt.intensity.to_le_bytes());
            o += 4;
        }
        if attrs.classification {
            v[o] = pt.classification;
        }
    }
    out
}

/// The min and max of the stored positions (the accessor's `min`/`max`), from the points'
/// bounds: the stored values are monotonic in the position.
fn stored_range(b: &Bounds, pos: &Positions) -> (Vec<f64>, Vec<f64>) {
    let (lo, hi) = b.gltf();
    match pos {
        Positions::Quantized { lo: l, step } => {
            let q = |x: f64, a: usize| ((x - l[a]) / step[a]).round().clamp(0.0, 65535.0);
            ((0..3).map(|a| q(lo[a], a)).collect(), (0..3).map(|a| q(hi[a], a)).collect())
        }
        Positions::Float { centre } => {
            let f = |x: f64, a: usize| ((x - centre[a]) as f32) as f64;
            ((0..3).map(|a| f(lo[a], a)).collect(), (0..3).map(|a| f(hi[a], a)).collect())
        }
    }
}

/// The GLB bytes before the vertices (header, JSON chunk, BIN chunk header) of a tile of `n`
/// points, and the padding after them.
pub(crate) fn head(n: usize, b: &Bounds, attrs: Attrs, pos: &Positions) -> (Vec<u8>, usize) {
    let stride = attrs.stride(pos);
    let bin_len = n * stride;
    let bin_pad = (4 - bin_len % 4) % 4;
    let (min, max) = stored_range(b, pos);
    let mut accessors = Vec::new();
    let mut attributes = serde_json::Map::new();
    let mut at = 0usize;
    let quantized = matches!(pos, Positions::Quantized { .. });
    accessors.push(json!({
        "bufferView": 0, "byteOffset": 0, "componentType": if quantized { 5123 } else { 5126 },
        "count": n, "type": "VEC3", "min": min, "max": max,
    }));
    attributes.insert("POSITION".into(), json!(0));
    at += Attrs::pos_len(pos);
    if attrs.color != 0 {
        attributes.insert("COLOR_0".into(), json!(accessors.len()));
        accessors.push(json!({
            "bufferView": 0, "byteOffset": at, "componentType": if attrs.color == 1 { 5121 } else { 5123 },
            "normalized": true, "count": n, "type": "VEC3",
        }));
        at += if attrs.color == 1 { 4 } else { 8 };
    }
    let mut props = serde_json::Map::new();
    let mut class_props = serde_json::Map::new();
    if attrs.intensity {
        attributes.insert("_INTENSITY".into(), json!(accessors.len()));
        accessors.push(json!({"bufferView": 0, "byteOffset": at, "componentType": 5123, "count": n, "type": "SCALAR"}));
        at += 4;
        props.insert("intensity".into(), json!({"attribute": "_INTENSITY"}));
        class_props.insert(
            "intensity".into(),
            json!({"type": "SCALAR", "componentType": "UINT16", "description": "LAS intensity"}),
        );
    }
    if attrs.classification {
        attributes.insert("_CLASSIFICATION".into(), json!(accessors.len()));
        accessors.push(json!({"bufferView": 0, "byteOffset": at, "componentType": 5121, "count": n, "type": "SCALAR"}));
        props.insert("classification".into(), json!({"attribute": "_CLASSIFICATION"}));
        class_props.insert("classification".into(), json!({"type": "SCALAR", "componentType": "UINT8", "description": "LAS classification"}));
    }
    let mut used = vec!["KHR_materials_unlit"];
    let mut primitive = json!({"attributes": attributes, "mode": 0, "material": 0});
    let mut top_ext = serde_json::Map::new();
    if !props.is_empty() {
        used.push("EXT_structural_metadata");
        primitive["extensions"] = json!({"EXT_structural_metadata": {"propertyAttributes": [0]}});
        top_ext.insert(
            "EXT_structural_metadata".into(),
            json!({
                "schema": {"id": "mortar_las", "classes": {"point": {"properties": class_props}}},
                "propertyAttributes": [{"class": "point", "properties": props}],
            }),
        );
    }
    let mut node = json!({"mesh": 0});
    match pos {
        Positions::Quantized { lo, step } => {
            used.push("KHR_mesh_quantization");
            node["translation"] = json!(lo);
            node["scale"] = json!(step);
        }
        Positions::Float { centre } => node["translation"] = json!(centre),
    }
    let mut doc = json!({
        "asset": {"version": "2.0", "generator": concat!("mortar ", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": used,
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"primitives": [primitive]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}, "extensions": {"KHR_materials_unlit": {}}}],
        "accessors": accessors,
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": bin_len, "byteStride": stride, "target": 34962}],
        "buffers": [{"byteLength": bin_len + bin_pad}],
    });
    if quantized {
        doc["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    }
    if !top_ext.is_empty() {
        doc["extensions"] = serde_json::Value::Object(top_ext);
    }
    let mut text = serde_json::to_vec(&doc).expect("JSON of a tile");
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let total = 12 + 8 + text.len() + 8 + bin_len + bin_pad;
    let mut h = Vec::with_capacity(12 + 8 + text.len() + 8);
    h.extend_from_slice(b"glTF");
    h.extend_from_slice(&2u32.to_le_bytes());
    h.extend_from_slice(&(total as u32).to_le_bytes());
    h.extend_from_slice(&(text.len() as u32).to_le_bytes());
    h.extend_from_slice(b"JSON");
    h.extend_from_slice(&text);
    h.extend_from_slice(&((bin_len + bin_pad) as u32).to_le_bytes());
    h.extend_from_slice(b"BIN\0");
    (h, bin_pad)
}

/// A whole tile.
pub(crate) fn encode(points: &[Point], b: &Bounds, attrs: Attrs, pos: &Positions) -> Vec<u8> {
    let (mut out, pad) = head(points.len(), b, attrs, pos);
    out.extend_from_slice(&vertices(points, attrs, pos));
    out.resize(out.len() + pad, 0);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tile_is_a_glb_whose_positions_decode_within_the_bound() {
        let pts: Vec<Point> = (0..5)
            .map(|i| Point {
                p: [i as f64 * 1.5, -(i as f64), 100.0 + i as f64 * 0.25],
                rgb: [i, 2 * i, 255],
                intensity: 7 * i,
                classification: i as u8,
            })
            .collect();
        let mut b = Bounds::EMPTY;
        pts.iter().for_each(|p| b.add(p.p));
        let attrs = Attrs { color: 1, intensity: true, classification: true };
        for res in [1e-3, 1e-9] {
            let pos = positions_for(&b, res);
            assert_eq!(matches!(pos, Positions::Quantized { .. }), res == 1e-3);
            let g = encode(&pts, &b, attrs, &pos);
            assert_eq!(&g[0..4], b"glTF");
            assert_eq!(u32::from_le_bytes(g[8..12].try_into().unwrap()) as usize, g.len());
            assert_eq!(g.len() % 4, 0);
            let jl = u32::from_le_bytes(g[12..16].try_into().unwrap()) as usize;
            let doc: serde_json::Value = serde_json::from_slice(&g[20..20 + jl]).unwrap();
            let stride = doc["bufferViews"][0]["byteStride"].as_u64().unwrap() as usize;
            let bin = &g[20 + jl + 8..];
            let node = &doc["nodes"][0];
            let t: Vec<f64> = node["translation"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let s: Vec<f64> = node
                .get("scale")
                .map(|s| s.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect())
                .unwrap_or(vec![1.0; 3]);
            let bound = pos.error_bound(&b);
            for (k, pt) in pts.iter().enumerate() {
                let v = &bin[k * stride..];
                let q: Vec<f64> = (0..3)
                    .map(|a| {
                        if res == 1e-3 {
                            u16::from_le_bytes([v[2 * a], v[2 * a + 1]]) as f64
                        } else {
                            f32::from_le_bytes(v[4 * a..4 * a + 4].try_into().unwrap()) as f64
                        }
                    })
                    .collect();
                let gl: Vec<f64> = (0..3).map(|a| t[a] + s[a] * q[a]).collect();
                let back = [gl[0], -gl[2], gl[1]];
                let d = (0..3).map(|a| (back[a] - pt.p[a]).powi(2)).sum::<f64>().sqrt();
                assert!(d <= bound * 1.0001 + 1e-12, "{d} > {bound}");
                let o = if res == 1e-3 { 8 } else { 12 };
                assert_eq!(&v[o..o + 3], &[pt.rgb[0] as u8, pt.rgb[1] as u8, 255]);
                assert_eq!(u16::from_le_bytes([v[o + 4], v[o + 5]]), pt.intensity);
                assert_eq!(v[o + 8], pt.classification);
            }
        }
    }
}
