#!/usr/bin/env bash
# README command two: set up and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-system.sh
bash scripts/setup.sh
. .venv/bin/activate
# Blender as a Python module (tests only), for the test that imports the BVH export the way Blender does: bpy 5.0 pins numpy<2
# (the project needs numpy>=2), so it gets its own environment beside .venv (pyproject.toml, test extra)
if [ ! -x .venv-blender/bin/python ] || ! .venv-blender/bin/python -c "import bpy" 2>/dev/null; then
    python -m venv .venv-blender && .venv-blender/bin/python -m pip install -q bpy==5.0.1 \
        || echo "setup: bpy 5.0.1 (Python 3.11 only) did not install into .venv-blender; the Blender import test is skipped" >&2
fi
export QT_QPA_PLATFORM=offscreen
python -m pytest -q "$@"
