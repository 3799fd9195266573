#!/usr/bin/env bash
# Rebuild the page's script (service/api/static/app.js) from web/src with the locked npm packages.
#   web/build.sh            # npm ci (from package-lock.json), then esbuild
# The bundle is committed, so serving the page needs neither node nor the internet.
set -euo pipefail
cd "$(dirname "$0")"
npm ci --no-audit --no-fund
npm run build
