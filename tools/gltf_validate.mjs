// Validate a glTF 2.0 file with the Khronos glTF validator (npm package gltf-validator) and
// print its report's summary as one JSON line: {"errors", "warnings", "infos", "messages"}.
//
//   node tools/gltf_validate.mjs FILE.glb [NODE_MODULES_DIR]
//
// NODE_MODULES_DIR: where gltf-validator is installed (default: ~/.cache/articast/
// gltf-validator/node_modules, where .ci/run installs it with
// `npm install --prefix ~/.cache/articast/gltf-validator gltf-validator`).
import { createRequire } from "node:module";
import { readFileSync } from "node:fs";
import { homedir } from "node:os";
import { join } from "node:path";

const [file, modules] = process.argv.slice(2);
if (!file) { console.error("usage: node tools/gltf_validate.mjs FILE.glb [NODE_MODULES_DIR]"); process.exit(2); }
const dir = modules || join(homedir(), ".cache", "articast", "gltf-validator", "node_modules");
let validator;
try {
  validator = createRequire(join(dir, "noop.js"))("gltf-validator");
} catch (e) {
  console.error(`gltf-validator is not installed in ${dir}: npm install --prefix ${join(dir, "..")} gltf-validator`);
  process.exit(3);
}
const report = await validator.validateBytes(new Uint8Array(readFileSync(file)), { maxIssues: 200 });
const i = report.issues;
console.log(JSON.stringify({ errors: i.numErrors, warnings: i.numWarnings, infos: i.numInfos,
  messages: i.messages.map((m) => `${m.severity} ${m.code} ${m.pointer || ""}: ${m.message}`) }));
