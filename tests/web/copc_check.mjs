// Reads a COPC file with copc.js (npm `copc`): the header, the info record, every hierarchy page
// (following the page pointers) and the points of every node, checking each node's point count
// and that each decoded point lies in its node's box (center +- halfsize / 2^level).
// Prints one JSON line; exit 1 when a check fails. Usage: node copc_check.mjs FILE.copc.laz
import { Copc } from 'copc';

const file = process.argv[2];
const out = { file, ok: false, problems: [] };
try {
  const copc = await Copc.create(file);
  const { header, info } = copc;
  out.points_header = header.pointCount;
  out.format = header.pointDataRecordFormat;
  const nodes = {};
  const todo = [info.rootHierarchyPage];
  while (todo.length) {
    const sub = await Copc.loadHierarchyPage(file, todo.pop());
    Object.assign(nodes, sub.nodes);
    for (const p of Object.values(sub.pages)) todo.push(p);
  }
  out.nodes = Object.keys(nodes).length;
  let total = 0;
  let outside = 0;
  const [cx, cy, cz] = [(info.cube[0] + info.cube[3]) / 2, (info.cube[1] + info.cube[4]) / 2, (info.cube[2] + info.cube[5]) / 2];
  const half = (info.cube[3] - info.cube[0]) / 2;
  for (const [key, node] of Object.entries(nodes)) {
    if (!node || node.pointCount === 0) continue;
    const view = await Copc.loadPointDataView(file, copc, node);
    if (view.pointCount !== node.pointCount) out.problems.push(`${key}: ${view.pointCount} points decoded, ${node.pointCount} listed`);
    total += view.pointCount;
    const [d, x, y, z] = key.split('-').map(Number);
    const edge = (2 * half) / 2 ** d;
    const lo = [cx - half + x * edge, cy - half + y * edge, cz - half + z * edge];
    const g = ['X', 'Y', 'Z'].map((n) => view.getter(n));
    for (let i = 0; i < view.pointCount; i++) {
      for (let a = 0; a < 3; a++) {
        const v = g[a](i);
        if (v < lo[a] || v > lo[a] + edge) { outside++; break; }
      }
    }
  }
  out.points_read = total;
  if (total !== out.points_header) out.problems.push(`nodes hold ${total} points, the header ${out.points_header}`);
  if (outside) out.problems.push(`${outside} points outside their node's box`);
  out.ok = out.problems.length === 0;
} catch (e) {
  out.problems.push(String(e && e.stack || e));
}
console.log(JSON.stringify(out));
process.exit(out.ok ? 0 : 1);
