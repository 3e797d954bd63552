#!/usr/bin/env bash
# The README's two pictures, made by the runtime on the bundled model:
#   docs/img/demo.png            `geonet-infer demo` on the bundled synthetic sample
#   docs/img/demo_real_kitti.png `geonet-infer demo --real` on frames 0-9 of ../shared/realdata's KITTI raw extract
#   bash scripts/readme_figures.sh      # from anywhere; needs .venv (bash scripts/demo.sh makes it)
set -euo pipefail
cd "$(dirname "$0")/.."
GEONET_INFER=${GEONET_INFER:-.venv/bin/geonet-infer}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$GEONET_INFER" demo --out "$tmp/synth" --no-progress
cp "$tmp/synth/demo.png" docs/img/demo.png
"$GEONET_INFER" demo --real --out "$tmp/real" --no-progress
cp "$tmp/real/demo.png" docs/img/demo_real_kitti.png
echo "wrote docs/img/demo.png and docs/img/demo_real_kitti.png"
