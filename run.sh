#!/usr/bin/env bash
# Set up what is missing, then run the pipeline: `bash run.sh scene=tomb planner=ours [overrides]`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bash "$ROOT/scripts/setup.sh"
cd "$ROOT"
exec "$ROOT/.venv/bin/python" run.py "$@"
