#!/usr/bin/env bash
# Create .venv and install skycap with its test extras. The CPU build of torch goes in first:
# a plain "torch" requirement with nothing installed would pull a multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
. .venv/bin/activate
python -m pip install -q --upgrade pip
python -c "import torch" 2>/dev/null || python -m pip install -q torch==2.13.0
python -m pip install -q -e ".[all,test]"
# the GStreamer camera sources (V4L2, pipelines, RTSP) need PyGObject, built against the system's GStreamer and
# gobject-introspection (scripts/setup-system.sh installs them as root); without them those sources say so
if pkg-config --exists gobject-introspection-1.0 cairo 2>/dev/null; then
    python -c "import gi" 2>/dev/null || python -m pip install -q -e ".[camera]"
else
    echo "setup: no gobject-introspection / cairo development files for PyGObject; the GStreamer camera sources are off" \
         "(run scripts/setup-system.sh as root)" >&2
fi
