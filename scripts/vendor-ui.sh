#!/usr/bin/env bash
# Copies the pendant's browser libraries from node_modules (npm ci, pinned in package-lock.json)
# into the folder the service serves them from (default service/ui/vendor, git-ignored):
#   three/       three.js as ES modules (three.module.js, three.core.js) and the addons used
#   swagger-ui/  Swagger UI for /docs      redoc/  ReDoc for /redoc
#   mermaid/     mermaid.min.js: the documentation site's diagrams (make docs copies it there)
# Usage: scripts/vendor-ui.sh [NODE_MODULES [DEST]]   (also used by docker/Dockerfile)
set -euo pipefail
SRC=${1:-node_modules}
DEST=${2:-service/ui/vendor}
for f in three/build/three.module.js swagger-ui-dist/swagger-ui-bundle.js redoc/bundles/redoc.standalone.js \
         mermaid/dist/mermaid.min.js; do
    [ -f "$SRC/$f" ] || { echo "vendor-ui: $SRC/$f is missing: run 'npm ci --ignore-scripts' first" >&2; exit 1; }
done
rm -rf "$DEST.tmp"
mkdir -p "$DEST.tmp/three/addons/controls" "$DEST.tmp/swagger-ui" "$DEST.tmp/redoc" "$DEST.tmp/mermaid"
cp "$SRC"/three/build/three.module.js "$SRC"/three/build/three.core.js "$SRC"/three/LICENSE "$DEST.tmp/three/"
cp "$SRC"/three/examples/jsm/controls/OrbitControls.js "$DEST.tmp/three/addons/controls/"
cp "$SRC"/swagger-ui-dist/swagger-ui-bundle.js "$SRC"/swagger-ui-dist/swagger-ui.css \
   "$SRC"/swagger-ui-dist/favicon-32x32.png "$SRC"/swagger-ui-dist/LICENSE "$DEST.tmp/swagger-ui/"
cp "$SRC"/redoc/bundles/redoc.standalone.js "$SRC"/redoc/LICENSE "$DEST.tmp/redoc/"
cp "$SRC"/mermaid/dist/mermaid.min.js "$DEST.tmp/mermaid/"
cp "$SRC"/mermaid/LICENSE* "$DEST.tmp/mermaid/" 2>/dev/null || true
# ReDoc's "powered by" badge loads its logo from a CDN: a blank image instead (offline docs).
sed -i 's#https://cdn.redoc.ly/redoc/logo-mini.svg#data:image/gif;base64,R0lGODlhAQABAIAAAAAAAP///yH5BAEAAAAALAAAAAABAAEAAAIBRAA7#g' \
    "$DEST.tmp/redoc/redoc.standalone.js"
# What was copied, and from which versions (setup.sh compares it with package-lock.json).
sha256sum package-lock.json 2>/dev/null | cut -d' ' -f1 > "$DEST.tmp/.lock-sha256" || true
rm -rf "$DEST"
mv "$DEST.tmp" "$DEST"
