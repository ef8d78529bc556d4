// Build Spark's "quality" LoD tree (bhatt-lod, rust/spark-lib/src/bhatt_lod.rs compiled to WASM) under Node,
// headless, with the npm package @sparkjsdev/spark itself: its worker's wasm-bindgen glue (the `jsContent` string
// of dist/spark.module.js) is run here instead of in a Web Worker, on the package's inlined WASM module, and
// called as its loadExtSplats(lod: "quality") does: decode_to_gsplatarray -> bhatt_lod(lodBase) ->
// to_extsplats_lod(). The tree (every node: originals and merged interior splats) is written as raw arrays:
//
//   node spark_lod.mjs IN.ply OUT_PREFIX [lodBase=1.75]
//
// writes OUT_PREFIX.ext0.u32 / .ext1.u32 (4 words per node: f32 centre, f16 opacity | f16 rgb, f16 ln scales,
// oct-10-10-12 quaternion), .lod.u32 (4 words per node: f16 centre, f16 size, child count, child start),
// .sh1.u32/.sh2.u32/... when present, and OUT_PREFIX.json (counts, timing, version).
import fs from "node:fs";
import path from "node:path";
import { createRequire } from "node:module";

const [input, prefix, baseArg] = process.argv.slice(2);
if (!input || !prefix) {
  console.error("usage: node spark_lod.mjs IN.ply OUT_PREFIX [lodBase]");
  process.exit(2);
}
const require = createRequire(import.meta.url);
const distDir = path.dirname(require.resolve("@sparkjsdev/spark"));
const pkg = JSON.parse(fs.readFileSync(path.join(distDir, "..", "package.json"), "utf8"));
const src = fs.readFileSync(path.join(distDir, "spark.module.js"), "utf8");
const wasmB64 = src.match(/const WASM = decode64\("([^"]+)"\)/)[1];
const jsLine = src.split("\n").find((l) => l.startsWith("const jsContent = '"));
const jsContent = (0, eval)(jsLine.slice("const jsContent = ".length).replace(/;\s*$/, ""));
const marker = "initialize().catch(console.error);";
if (!jsContent.includes(marker)) throw new Error("unexpected worker layout in spark.module.js");
const code = jsContent.replace(marker, "self.__spark = { __wbg_init, decode_to_gsplatarray };");
const selfShim = { addEventListener() {}, removeEventListener() {}, postMessage() {} };
new Function("self", code)(selfShim);
const S = selfShim.__spark;
await S.__wbg_init({ module_or_path: await WebAssembly.compile(Buffer.from(wasmB64, "base64")) });

const lodBase = Math.max(1.1, Math.min(2, Number(baseArg ?? 1.75)));  // loadExtSplats' clamp and default
const bytes = fs.readFileSync(input);
const decoder = S.decode_to_gsplatarray("ply", input);
for (let o = 0; o < bytes.length; o += 1 << 20) {
  decoder.push(new Uint8Array(bytes.buffer, bytes.byteOffset + o, Math.min(1 << 20, bytes.length - o)));
}
const arr = decoder.finish();
const n0 = arr.len();
const t0 = performance.now();
arr.bhatt_lod(lodBase);
const ms = performance.now() - t0;
const out = arr.to_extsplats_lod();
const fields = {};
for (const [k, v] of Object.entries(out)) {
  if (v instanceof Uint32Array) {
    fs.writeFileSync(`${prefix}.${k}.u32`, new Uint8Array(v.buffer, v.byteOffset, v.byteLength));
    fields[k] = v.length;
  }
}
const lodTree = out.lodTree ?? out.extra?.lodTree;
if (lodTree instanceof Uint32Array && !fields.lodTree) {
  fs.writeFileSync(`${prefix}.lodTree.u32`, new Uint8Array(lodTree.buffer, lodTree.byteOffset, lodTree.byteLength));
  fields.lodTree = lodTree.length;
}
const meta = {
  spark: pkg.version, node: process.version, input: path.basename(input), lodBase, inputSplats: n0,
  nodes: out.numSplats, maxShDegree: arr.maxShDegree, bhattLodMs: Math.round(ms), fields,
  keys: Object.keys(out),
};
fs.writeFileSync(`${prefix}.json`, JSON.stringify(meta, null, 1));
console.error(`spark ${pkg.version} bhatt_lod(${lodBase}): ${n0} -> ${out.numSplats} nodes in ${Math.round(ms)} ms`);
