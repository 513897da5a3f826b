// The batches a draw pass reads (group 1: one bind group per chunk of points) and the one
// per-point step of every draw pass: load the words the batch's precision needs, decode, project.

@group(1) @binding(0) var<storage, read> records: array<DrawRecord>;
@group(1) @binding(1) var<storage, read> coarse: array<u32>;
@group(1) @binding(2) var<storage, read> medium: array<u32>;
@group(1) @binding(3) var<storage, read> fine: array<u32>;

// Point i of the batch of record `rec`, projected for the frame.
fn load_and_project(rec: DrawRecord, i: u32, frame: FrameUniforms) -> Projected {
    let p = rec.projection;
    let s = rec.offset + i;
    var m = 0u;
    var f = 0u;
    if p.words >= 2u {
        m = medium[s];
    }
    if p.words >= 3u {
        f = fine[s];
    }
    return project(p, join_words(coarse[s], m, f, p.words), frame);
}
