#!/usr/bin/env bash
# README command one: set up and run the demo (a full simulated flight and its reconstruction).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
skycap demo "$@"
