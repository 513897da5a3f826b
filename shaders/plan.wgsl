// Pass "plan" (paper 003 §3.2-3.3: each batch's bounding box decides culling and precision on
// the GPU): one thread per batch computes what mortar_core::render::plan::plan_batch computes on
// the CPU, operation for operation (every product kept apart from the sum after it by opaque(),
// so that no FMA rounds differently), and writes the batch's DrawRecord (count 0: culled or
// empty) for the draw passes, which read it as if the host had planned. Counts culled and drawn
// batches and the points drawn per number of words. KEEP IN SYNC with lib/core/src/render/plan.rs.

@group(0) @binding(0) var<uniform> u: PlanUniforms;
@group(0) @binding(1) var<storage, read> plan_batches: array<PlanBatch>;
@group(0) @binding(2) var<storage, read_write> out_records: array<DrawRecord>;
@group(0) @binding(3) var<storage, read_write> plan_counters: array<atomic<u32>, 8>;

// Grid units from the eye beyond which a batch keeps a batch-local anchor: 2^30.
// KEEP IN SYNC with mortar_core::render::plan::FAR_UNITS (tested by mortar-render's shader test).
const FAR_UNITS: f32 = 1073741824.0;

fn o(v: f32) -> f32 {
    return opaque(v, u.zero);
}

fn eye_offset(p: i32, e: i32) -> f32 {
    let high = o(f32((p >> 16u) - (e >> 16u)) * 65536.0);
    let low = f32((p & 0xffff) - (e & 0xffff));
    return o(high + low);
}

fn div_plan(x: f32, d: f32) -> f32 {
    if u.division == 1u {
        return div_rn(x, d, u.zero);
    }
    return o(x / d);
}

fn dot3(a: vec4<f32>, v: vec3<f32>) -> f32 {
    return o(o(o(a.x * v.x) + o(a.y * v.y)) + o(a.z * v.z));
}

fn reach(a: vec4<f32>, e: vec3<f32>) -> f32 {
    return o(o(o(abs(a.x) * e.x) + o(abs(a.y) * e.y)) + o(abs(a.z) * e.z));
}

fn error_units(bits: vec3<u32>, words: u32) -> vec3<f32> {
    var e: vec3<f32>;
    for (var a = 0u; a < 3u; a++) {
        let missing = select(0u, bits[a] - words * 10u, bits[a] > words * 10u);
        e[a] = f32((1u << missing) - 1u) * 0.5;
    }
    return e;
}

fn error_ok(e: vec3<f32>, zmin: f32, xm: f32, ym: f32) -> bool {
    let ex = reach(u.right, e);
    let ey = reach(u.up, e);
    let ez = reach(u.forward, e);
    if u.perspective == 0u {
        let bx = o(u.sx * ex);
        let by = o(u.sy * ey);
        return o(o(bx * bx) + o(by * by)) < o(u.max_error_px * u.max_error_px);
    }
    let d = o(zmin - ez);
    if !(d > u.near) {
        return false;
    }
    let bx = o(u.sx * o(o(ex * zmin) + o(xm * ez)));
    let by = o(u.sy * o(o(ey * zmin) + o(ym * ez)));
    let limit = o(o(u.max_error_px * zmin) * d);
    return o(o(bx * bx) + o(by * by)) < o(limit * limit);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = workgroup_linear(wg, groups) * 256u + lid;
    if i >= u.batches {
        return;
    }
    let b = plan_batches[i];
    var rec: DrawRecord;
    rec.offset = b.offset;
    rec.count = 0u;
    rec.first_index = b.first_index;
    if b.count == 0u {
        out_records[b.record] = rec;
        return;
    }
    let er = u.eye_int + vec3<i32>(select(vec3<u32>(0u), vec3<u32>(1u), u.eye_frac >= vec3<f32>(0.5)));
    var zmin = 3.40282347e+38;
    var zmax = -3.40282347e+38;
    var xm = 0.0;
    var ym = 0.0;
    var corners: array<vec3<f32>, 8>;
    for (var c = 0u; c < 8u; c++) {
        var rel: vec3<f32>;
        for (var a = 0u; a < 3u; a++) {
            let off = select(b.lo[a], b.hi[a], ((c >> a) & 1u) == 1u);
            rel[a] = o(eye_offset(b.min[a] + i32(off), u.eye_int[a]) - u.eye_frac[a]);
        }
        let v = vec3<f32>(dot3(u.right, rel), dot3(u.up, rel), dot3(u.forward, rel));
        zmin = min(zmin, v.z);
        zmax = max(zmax, v.z);
        xm = max(xm, abs(v.x));
        ym = max(ym, abs(v.y));
        corners[c] = v;
    }
    let top = max(max(b.bits.x, b.bits.y), b.bits.z);
    let needed = select(select(3u, 2u, top <= 20u), 1u, top <= 10u);
    var words = 1u;
    if u.words != 0u {
        words = min(u.words, needed);
    } else {
        loop {
            if words >= needed || error_ok(error_units(b.bits, words), zmin, xm, ym) {
                break;
            }
            words += 1u;
        }
    }
    let e = error_units(b.bits, words);
    if u.cull != 0u {
        let ext = vec3<f32>(b.hi - b.lo);
        let size = o(o(o(o(ext.x * u.scale.x) + o(ext.y * u.scale.y)) + o(ext.z * u.scale.z)) + o(o(xm + ym) + max(abs(zmax), abs(zmin))));
        let s = o(u.slack * size);
        let ex = o(reach(u.right, e) + s);
        let ey = o(reach(u.up, e) + s);
        let ez = o(reach(u.forward, e) + s);
        let m = u.margin_px;
        var planes: array<vec4<f32>, 6>;
        if u.perspective != 0u {
            planes = array<vec4<f32>, 6>(
                vec4<f32>(0.0, 0.0, 1.0, -u.near),
                vec4<f32>(0.0, 0.0, -1.0, u.far),
                vec4<f32>(u.sx, 0.0, o(u.cx + m), 0.0),
                vec4<f32>(-u.sx, 0.0, o(o(u.width + m) - u.cx), 0.0),
                vec4<f32>(0.0, -u.sy, o(u.cy + m), 0.0),
                vec4<f32>(0.0, u.sy, o(o(u.height + m) - u.cy), 0.0),
            );
        } else {
            planes = array<vec4<f32>, 6>(
                vec4<f32>(0.0, 0.0, 1.0, -u.near),
                vec4<f32>(0.0, 0.0, -1.0, u.far),
                vec4<f32>(u.sx, 0.0, 0.0, o(u.cx + m)),
                vec4<f32>(-u.sx, 0.0, 0.0, o(o(u.width + m) - u.cx)),
                vec4<f32>(0.0, -u.sy, 0.0, o(u.cy + m)),
                vec4<f32>(0.0, u.sy, 0.0, o(o(u.height + m) - u.cy)),
            );
        }
        for (var k = 0u; k < 6u; k++) {
            let p = planes[k];
            let moved = o(o(o(abs(p.x) * ex) + o(abs(p.y) * ey)) + o(abs(p.z) * ez));
            var outside = true;
            for (var c = 0u; c < 8u; c++) {
                let v = corners[c];
                let value = o(o(o(o(o(p.x * v.x) + o(p.y * v.y)) + o(p.z * v.z)) + p.w) + moved);
                outside = outside && value < 0.0;
            }
            if outside {
                out_records[b.record] = rec;
                atomicAdd(&plan_counters[0], 1u);
                return;
            }
        }
    }
    // The anchor: the eye's grid position for every batch (a point's local coordinate is p - eye,
    // whatever batch holds it), or for a batch reaching FAR_UNITS from the eye its own grid point
    // nearest to the eye (plan.rs: plan_batch).
    var far = false;
    for (var a = 0u; a < 3u; a++) {
        let lo = abs(eye_offset(b.min[a] + i32(b.lo[a]), er[a]));
        let hi = abs(eye_offset(b.min[a] + i32(b.hi[a]), er[a]));
        far = far || max(lo, hi) >= FAR_UNITS;
    }
    var anchor: vec3<i32>;
    var shift: vec3<u32>;
    var rel: vec3<f32>;
    for (var a = 0u; a < 3u; a++) {
        var base = er[a];
        if far {
            let lo = b.min[a] + i32(b.lo[a]);
            let hi = b.min[a] + i32(b.hi[a]);
            var an = b.lo[a];
            if er[a] <= lo {
                an = b.lo[a];
            } else if er[a] >= hi {
                an = b.hi[a];
            } else {
                an = u32(er[a] - b.min[a]);
            }
            base = b.min[a] + i32(an);
        }
        anchor[a] = base - b.min[a];
        shift[a] = 30u - min(b.bits[a], 30u);
        let missing = select(0u, b.bits[a] - words * 10u, b.bits[a] > words * 10u);
        let mid = f32((1u << missing) - 1u) * 0.5;
        rel[a] = o(o(eye_offset(base, u.eye_int[a]) - u.eye_frac[a]) + mid);
    }
    let wx = dot3(u.right, rel);
    let wy = dot3(u.up, rel);
    let wz = dot3(u.forward, rel);
    // The pixel origin: the viewport's centre, or where a far batch's anchor projects.
    var px = u.cx;
    var py = u.cy;
    if far {
        if u.perspective != 0u {
            if wz >= u.near {
                px = o(div_plan(o(u.sx * wx), wz) + u.cx);
                py = o(u.cy - div_plan(o(u.sy * wy), wz));
            }
        } else {
            px = o(o(u.sx * wx) + u.cx);
            py = o(u.cy - o(u.sy * wy));
        }
    }
    let ox = floor(o(min(max(px, 0.0), u.width) + 0.5));
    let oy = floor(o(min(max(py, 0.0), u.height) + 0.5));
    let dx = o(u.cx - ox);
    let dy = o(u.cy - oy);
    let f = u.forward;
    var pr: BatchProjection;
    if u.perspective != 0u {
        pr.pixel_from_local[0] = vec4<f32>(o(o(u.sx * u.right.x) + o(dx * f.x)), o(o(u.sx * u.right.y) + o(dx * f.y)), o(o(u.sx * u.right.z) + o(dx * f.z)), o(o(u.sx * wx) + o(dx * wz)));
        pr.pixel_from_local[1] = vec4<f32>(o(o(dy * f.x) - o(u.sy * u.up.x)), o(o(dy * f.y) - o(u.sy * u.up.y)), o(o(dy * f.z) - o(u.sy * u.up.z)), o(o(dy * wz) - o(u.sy * wy)));
        pr.pixel_from_local[2] = vec4<f32>(f.x, f.y, f.z, wz);
        pr.pixel_from_local[3] = vec4<f32>(f.x, f.y, f.z, wz);
    } else {
        pr.pixel_from_local[0] = vec4<f32>(o(u.sx * u.right.x), o(u.sx * u.right.y), o(u.sx * u.right.z), o(o(u.sx * wx) + dx));
        pr.pixel_from_local[1] = vec4<f32>(-o(u.sy * u.up.x), -o(u.sy * u.up.y), -o(u.sy * u.up.z), o(dy - o(u.sy * wy)));
        pr.pixel_from_local[2] = vec4<f32>(f.x, f.y, f.z, wz);
        pr.pixel_from_local[3] = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    pr.anchor = anchor;
    pr.words = words;
    pr.shift = shift;
    pr.pixel_origin = vec2<i32>(i32(ox), i32(oy));
    rec.projection = pr;
    rec.count = b.count;
    out_records[b.record] = rec;
    atomicAdd(&plan_counters[1], 1u);
    atomicAdd(&plan_counters[1u + words], b.count);
}
