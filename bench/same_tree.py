import sys, struct, os
def load(d):
    h = open(os.path.join(d,'hierarchy.bin'),'rb').read()
    hdr = struct.unpack_from('<8sIIQQQQ3qII3i3i', h, 0)
    n = hdr[4]
    ents = [struct.unpack_from('<II3IIQQQ', h, 104+48*i) for i in range(n)]
    segs = {}
    out = []
    for e in ents:
        level, kind, i0,i1,i2, seg, count, off, length = e
        if seg not in segs:
            segs[seg] = open(os.path.join(d, 'nodes.bin' if seg==0 else 'nodes-%d.bin'%seg),'rb').read()
        out.append(((level,kind,i0,i1,i2,count,length), segs[seg][off:off+length]))
    return (hdr[6],hdr[7:11],hdr[11],hdr[12:18]), out
a, b = load(sys.argv[1]), load(sys.argv[2])
assert a[0] == b[0], (a[0], b[0])
assert len(a[1]) == len(b[1]), (len(a[1]), len(b[1]))
bad = [i for i,(x,y) in enumerate(zip(a[1],b[1])) if x != y]
print("nodes", len(a[1]), "differ", len(bad), bad[:5])
