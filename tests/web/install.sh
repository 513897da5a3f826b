#!/usr/bin/env bash
# Install the pinned npm packages into tests/web/node_modules and build tests/web/dist/main.js.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
npm install --prefix "$here" --no-audit --no-fund
"$here/node_modules/.bin/esbuild" "$here/main.js" --bundle --format=esm --target=es2020 \
  --outfile="$here/dist/main.js" --log-level=warning
echo "built $here/dist/main.js"
