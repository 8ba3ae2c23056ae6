// Bundles src/main.js (three.js, @msgpack/msgpack included) into dist/viewer.js, the one
// script viewer.html and overlay.html load, and src/perform/main.js into dist/perform.js
// for perform.html, next to the face model's weights and WebAssembly binaries copied out
// of their npm packages (dist/perform/: served by facecast, never fetched from elsewhere).
// src/landing.js becomes dist/landing.js for index.html (the landing page at /), Swagger
// UI's files are copied out of swagger-ui-dist into dist/docs/ for the API docs at /docs,
// and Draco's decoder out of three into dist/draco/ for compressed characters.
// Run by `npm run build` (scripts/setup does).
import { copyFile, mkdir } from "node:fs/promises";
import { join } from "node:path";

import { build } from "esbuild";

const common = {
  bundle: true,
  format: "esm",
  target: ["es2020"],
  minify: true,
  sourcemap: true,
  logLevel: "warning",
  legalComments: "linked",
};

await build({ ...common, entryPoints: ["src/main.js"], outfile: "dist/viewer.js" });
await build({ ...common, entryPoints: ["src/perform/main.js"], outfile: "dist/perform.js" });
// The offline tracker of `facecast track` (track.html): the page's own tracking pipeline.
await build({ ...common, entryPoints: ["src/perform/track.js"], outfile: "dist/track.js" });

await build({ ...common, entryPoints: ["src/landing.js"], outfile: "dist/landing.js" });

// The face model (BlazeFace + FaceMesh, TensorFlow.js graph models) and the WebAssembly
// backend's binaries; server/perform_page.py serves exactly these names.
// Human's package.json exports neither itself nor its models: read them from node_modules.
const packageDir = (name) => join("node_modules", name);
const PERFORM_ASSETS = {
  "@vladmandic/human": ["models/blazeface.json", "models/blazeface.bin", "models/facemesh.json", "models/facemesh.bin", "models/iris.json", "models/iris.bin"],
  "@tensorflow/tfjs-backend-wasm": [
    "dist/tfjs-backend-wasm.wasm",
    "dist/tfjs-backend-wasm-simd.wasm",
    "dist/tfjs-backend-wasm-threaded-simd.wasm",
  ],
};
await mkdir("dist/perform", { recursive: true });
for (const [pkg, files] of Object.entries(PERFORM_ASSETS)) {
  for (const file of files) {
    await copyFile(join(packageDir(pkg), file), join("dist/perform", file.split("/").pop()));
  }
}

// Draco's decoder for compressed characters (src/character.js: DRACOLoader fetches these
// from /viewer/assets/draco/, which server/pages/viewer.py serves), the build three.js
// names for glTF, with its README (its licence, Apache 2.0).
const DRACO_ASSETS = ["draco_decoder.js", "draco_decoder.wasm", "draco_wasm_wrapper.js"];
await mkdir("dist/draco", { recursive: true });
for (const file of DRACO_ASSETS) {
  await copyFile(join(packageDir("three"), "examples/jsm/libs/draco/gltf", file), join("dist/draco", file));
}
await copyFile(join(packageDir("three"), "examples/jsm/libs/draco/README.md"), "dist/draco/README.md");

// Swagger UI for /docs (server/api_docs.py serves exactly these names), with its licence.
const DOCS_ASSETS = ["swagger-ui-bundle.js", "swagger-ui.css", "favicon-32x32.png", "LICENSE", "NOTICE"];
await mkdir("dist/docs", { recursive: true });
for (const file of DOCS_ASSETS) {
  await copyFile(join(packageDir("swagger-ui-dist"), file), join("dist/docs", file));
}
