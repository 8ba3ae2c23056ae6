// Bundles src/main.js (three.js, @msgpack/msgpack included) into dist/viewer.js, the one
// script viewer.html and overlay.html load. Run by `npm run build` (scripts/setup does).
import { build } from "esbuild";

await build({
  entryPoints: ["src/main.js"],
  bundle: true,
  format: "esm",
  target: ["es2020"],
  minify: true,
  sourcemap: true,
  outfile: "dist/viewer.js",
  logLevel: "warning",
  legalComments: "linked",
});
