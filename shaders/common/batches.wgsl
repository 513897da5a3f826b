// The batches a draw pass reads (group 1: one bind group per chunk of points) and the one
// per-point step of every draw pass: load the words the batch's precision needs, decode, project.

@group(1) @binding(0) var<storage, read> records: array<DrawRecord>;
@group(1) @binding(1) var<storage, read> coarse: array<u32>;
@group(1) @binding(2) var<storage, read> medium: array<u32>;
@group(1) @binding(3) var<storage, read> fine: array<u32>;

// The words of point i of the batch of record `rec` (those its precision needs; 0 for the others).
fn load_words(rec: DrawRecord, i: u32) -> vec3<u32> {
    let s = rec.offset + i;
    var m = 0u;
    var f = 0u;
    if rec.projection.words >= 2u {
        m = medium[s];
    }
    if rec.projection.words >= 3u {
        f = fine[s];
    }
    return vec3<u32>(coarse[s], m, f);
}

// A point's words, decoded and projected for the frame.
fn project_words(rec: DrawRecord, w: vec3<u32>, frame: FrameUniforms) -> Projected {
    let p = rec.projection;
    return project(p, join_words(w.x, w.y, w.z, p.words), frame);
}

// Point i of the batch of record `rec`, projected for the frame.
fn load_and_project(rec: DrawRecord, i: u32, frame: FrameUniforms) -> Projected {
    return project_words(rec, load_words(rec, i), frame);
}
