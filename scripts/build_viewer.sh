#!/usr/bin/env bash
# Rebuild lidarmap/viewer/static/viewer.bundle.js: our viewer (lidarmap/viewer/src/viewer.js) with three.js, its
# GLTFLoader and OrbitControls, bundled by esbuild into ONE minified classic script (inlined into every page by
# `lidarmap view`, so pages open from file:// without a server or network). Needs node + npm and a registry.
# Versions are pinned; the bundle is committed, so users and CI never run this.
set -euo pipefail
THREE_VERSION=0.170.0
ESBUILD_VERSION=0.24.0
repo="$(cd "$(dirname "$0")/.." && pwd)"
viewer="$repo/lidarmap/viewer"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cp "$viewer/src/viewer.js" "$work/"
cd "$work"
npm init -y >/dev/null
npm install --no-audit --no-fund --silent "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION"
npx esbuild viewer.js --bundle --minify --format=iife --target=es2020 --legal-comments=none \
  --outfile=viewer.bundle.js
# the bundle is inlined in a <script> element: it must not contain "</script"
if grep -qi '</script' viewer.bundle.js; then echo "bundle contains </script" >&2; exit 1; fi
{ echo "/* lidarmap viewer + three.js r${THREE_VERSION#0.} (MIT, see THREE_LICENSE) */"; cat viewer.bundle.js; } \
  > "$viewer/static/viewer.bundle.js"
cp node_modules/three/LICENSE "$viewer/THREE_LICENSE"
echo "wrote $viewer/static/viewer.bundle.js ($(wc -c < "$viewer/static/viewer.bundle.js") bytes)"
