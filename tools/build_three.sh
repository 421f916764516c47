#!/usr/bin/env bash
# Rebuild the viewer's vendored three.js (service/sfmloc/viewer/static/vendor/three.min.js):
# three from the npm registry plus its OrbitControls, bundled into one minified ES module by
# esbuild (both versions pinned here; the output is byte-for-byte reproducible). Needs node and
# npm; run from the repository root, then update the SHA-256 in vendor/README.md.
set -euo pipefail
THREE_VERSION=0.187.0
ESBUILD_VERSION=0.28.2
out="$(pwd)/service/sfmloc/viewer/static/vendor"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
npm init -y >/dev/null
npm install --no-audit --no-fund --silent "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION"
cat > entry.js <<'JS'
export * from 'three';
export { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
JS
npx esbuild entry.js --bundle --format=esm --minify --legal-comments=inline \
    --outfile="$out/three.min.js"
cp node_modules/three/LICENSE "$out/LICENSE-three"
sha256sum "$out/three.min.js"
