// 3D Tiles check with other people's code (Node, no browser):
//  - every tile (.glb) through Khronos' glTF validator (npm `gltf-validator`): errors, warnings;
//  - the tileset, its external tilesets and every tile through loaders.gl (`@loaders.gl/3d-tiles`
//    Tiles3DLoader, as deck.gl reads them): the points of every tile counted from the decoded
//    POSITION attribute.
// Usage: node tiles_check.mjs TILESET_DIR   -> one JSON line on stdout; exit 1 on a failure.
import { readFile } from "node:fs/promises";
import path from "node:path";
import validator from "gltf-validator";
import { parse } from "@loaders.gl/core";
import { Tiles3DLoader } from "@loaders.gl/3d-tiles";

const dir = path.resolve(process.argv[2]);
const report = { tiles: 0, tilesets: 0, points: 0, validator_errors: 0, validator_warnings: 0, validator_infos: 0, messages: [], error: null };

function positionsCount(content) {
  const g = content.gltf;
  if (!g) return null;
  let n = 0;
  for (const m of g.meshes || []) {
    for (const p of m.primitives || []) {
      const a = p.attributes && p.attributes.POSITION;
      if (a) n += a.count ?? (a.value ? a.value.length / 3 : 0);
    }
  }
  return n;
}

async function tileset(file) {
  report.tilesets++;
  const data = await readFile(file);
  const ts = await parse(data, Tiles3DLoader, { "3d-tiles": { isTileset: true }, baseUri: file }, { url: file, baseUrl: path.dirname(file) });
  await tile(ts.root, path.dirname(file));
}

async function tile(t, base) {
  const uri = t.content && (t.content.uri || t.content.url);
  if (uri) {
    const f = path.isAbsolute(uri) ? uri : path.resolve(base, uri);
    if (f.endsWith(".json")) {
      await tileset(f);
    } else {
      const bytes = await readFile(f);
      const v = await validator.validateBytes(new Uint8Array(bytes), { uri: path.basename(f), maxIssues: 50 });
      report.validator_errors += v.issues.numErrors;
      report.validator_warnings += v.issues.numWarnings;
      report.validator_infos += v.issues.numInfos;
      for (const m of v.issues.messages) {
        if (report.messages.length < 10 && m.severity <= 1) report.messages.push(`${path.basename(f)}: ${m.code} ${m.message} ${m.pointer || ""}`);
      }
      const content = await parse(bytes, Tiles3DLoader, { "3d-tiles": { isTileset: false, loadGLTF: true, decodeQuantizedPositions: true }, gltf: { decompressMeshes: true } });
      const n = positionsCount(content);
      if (n === null) throw new Error(`${f}: loaders.gl gave no glTF content (type ${content.type})`);
      report.points += n;
      report.tiles++;
    }
  }
  for (const c of t.children || []) await tile(c, base);
}

try {
  await tileset(path.join(dir, "tileset.json"));
} catch (e) {
  report.error = String(e && e.stack ? e.stack : e);
}
console.log(JSON.stringify(report));
process.exit(report.error || report.validator_errors ? 1 : 0);
