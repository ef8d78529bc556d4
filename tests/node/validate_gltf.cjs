// Runs the Khronos glTF validator (npm gltf-validator) on each .glb given and prints one JSON report per line:
// {file, issues: {numErrors, numWarnings, messages: [{code, severity, pointer, message}]}}. Run with NODE_PATH
// pointing at .ci/node/node_modules (tests/test_tiles3d.py does).
"use strict";
const fs = require("fs");
const validator = require("gltf-validator");

async function main() {
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
      uri: file, maxIssues: 1000, writeTimestamp: false,
    });
    const messages = report.issues.messages.map((m) => ({ code: m.code, severity: m.severity,
                                                          pointer: m.pointer, message: m.message }));
    console.log(JSON.stringify({ file, validatorVersion: report.validatorVersion,
                                 issues: { numErrors: report.issues.numErrors,
                                           numWarnings: report.issues.numWarnings, messages } }));
  }
}

main().catch((e) => { console.error(String(e && e.stack || e)); process.exit(1); });
