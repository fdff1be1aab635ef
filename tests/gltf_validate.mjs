// Validate a glTF/GLB file with the Khronos glTF validator and print its report as JSON.
// Usage: node tests/gltf_validate.mjs FILE    (exit 0 when a report was printed, 2 otherwise)
import { readFile } from "node:fs/promises";
import path from "node:path";
import validator from "gltf-validator";

const file = process.argv[2];
if (!file) {
  console.error("usage: node tests/gltf_validate.mjs FILE");
  process.exit(2);
}
try {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 1000,
    externalResourceFunction: (uri) =>
      Promise.reject(new Error(`external resources are not allowed: ${uri}`)),
  });
  process.stdout.write(JSON.stringify(report, null, 2) + "\n");
} catch (err) {
  console.error(String(err));
  process.exit(2);
}
