#!/usr/bin/env python3
"""The import graph of each library crate, file by file, and its circles (issue 27).

A node is a module file (`a/b.rs` is `a::b`, `a/mod.rs` is `a`, `lib.rs` the crate root). There
is an edge A -> B when the code of A (comments and `#[cfg(test)] mod tests` left out) names a
path that resolves into B: `crate::...`, `super::...`, `self::...` or a child module of A by
name, to the deepest module file the path reaches. A crate's graph should be a DAG; every
strongly connected component of more than one file is printed as a circle.

Usage: python3 .ci/imports.py [--strict] [CRATE_DIR...]   (default: every lib/*/src)
Exit status: 1 with --strict when a circle exists, else 0.
"""
import re
import sys
from pathlib import Path

IDENT = r"[A-Za-z_][A-Za-z0-9_]*"


def module_of(src: Path, f: Path):
    rel = f.relative_to(src).with_suffix("")
    parts = list(rel.parts)
    if parts == ["lib"] or parts == ["main"]:
        return ()
    if parts[-1] == "mod":
        parts = parts[:-1]
    return tuple(parts)


def strip(code: str) -> str:
    # tests at the end of a file are not the module's imports
    m = re.search(r"#\[cfg\(test\)\]\s*mod\s+tests\s*\{", code)
    if m:
        code = code[: m.start()]
    code = re.sub(r"/\*.*?\*/", "", code, flags=re.S)
    code = re.sub(r"//[^\n]*", "", code)
    # string literals (paths inside messages)
    code = re.sub(r'"(?:\\.|[^"\\])*"', '""', code)
    return code


def expand(head, rest):
    """Paths of `head::rest`, where rest may start with a brace group."""
    out = []
    rest = rest.strip()
    if rest.startswith("{"):
        depth, cur, items = 0, "", []
        for ch in rest[1:]:
            if ch == "{":
                depth += 1
            elif ch == "}":
                if depth == 0:
                    items.append(cur)
                    break
                depth -= 1
            if ch == "," and depth == 0:
                items.append(cur)
                cur = ""
            else:
                cur += ch
        for it in items:
            it = it.strip()
            if not it:
                continue
            m = re.match(rf"({IDENT}(?:::{IDENT})*)(::\s*\{{.*)?", it, flags=re.S)
            if not m:
                continue
            segs = m.group(1).split("::")
            if m.group(2):
                out += expand(head + segs, m.group(2)[2:])
            else:
                out.append(head + segs)
    else:
        m = re.match(rf"{IDENT}(?:::{IDENT})*", rest)
        if m:
            out.append(head + m.group(0).split("::"))
    return out


def inline_depths(code: str):
    """For each position of `code`, how many inline `mod name { ... }` blocks enclose it."""
    out = [0] * (len(code) + 1)
    depth, mods = 0, []
    starts = {m.end() - 1 for m in re.finditer(rf"\bmod\s+{IDENT}\s*\{{", code)}
    for i, ch in enumerate(code):
        if ch == "{":
            depth += 1
            if i in starts:
                mods.append(depth)
        elif ch == "}":
            if mods and mods[-1] == depth:
                mods.pop()
            depth -= 1
        out[i] = len(mods)
    out[len(code)] = len(mods)
    return out


def graph(src: Path):
    files = sorted(src.rglob("*.rs"))
    mods = {module_of(src, f): f for f in files}
    edges = {m: set() for m in mods}
    for m, f in mods.items():
        code = strip(f.read_text())
        children = {k[-1] for k in mods if len(k) == len(m) + 1 and k[: len(m)] == m}
        paths = []
        inline = inline_depths(code)
        for mt in re.finditer(rf"\b(crate|super|self)((?:::super)*)::", code):
            kind, supers = mt.group(1), mt.group(2).count("super")
            # inside `mod x { ... }` blocks of this file, `self` and the first `super`s stay here
            k = inline[mt.start()]
            if kind == "crate":
                base = []
            elif kind == "self" or supers + 1 <= k:
                base = list(m)
            else:
                up = supers + 1 - k
                base = list(m[: len(m) - up]) if len(m) >= up else []
            paths += expand(base, code[mt.end():mt.end() + 400])
        for mt in re.finditer(rf"(?<![:\w])({IDENT})::", code):
            if mt.group(1) in children:
                paths += expand(list(m), code[mt.start():mt.start() + 400])
        for p in paths:
            # the deepest module file the path reaches
            best = None
            for i in range(len(p), -1, -1):
                if tuple(p[:i]) in mods:
                    best = tuple(p[:i])
                    break
            if best is not None and best != m:
                edges[m].add(best)
    return mods, edges


def circles(edges):
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in edges:
        if v not in index:
            visit(v)
    return out


def name(m):
    return "::".join(m) or "(root)"


def main():
    args = [a for a in sys.argv[1:] if a != "--strict"]
    strict = "--strict" in sys.argv[1:]
    root = Path(__file__).resolve().parent.parent
    crates = [Path(a) for a in args] or sorted(root.glob("lib/*/src"))
    total = 0
    for src in crates:
        mods, edges = graph(src)
        cs = circles(edges)
        total += len(cs)
        n_edges = sum(len(e) for e in edges.values())
        print(f"{src}: {len(mods)} module files, {n_edges} imports, {len(cs)} circle(s)")
        for c in cs:
            inner = sum(1 for v in c for w in edges[v] if w in c)
            print(f"  circle of {len(c)} ({inner} imports): " + ", ".join(name(v) for v in c))
    return 1 if strict and total else 0


if __name__ == "__main__":
    sys.exit(main())
