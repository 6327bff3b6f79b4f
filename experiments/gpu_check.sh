#!/usr/bin/env bash
# The lent GPU machine's side of experiments/gpu_check.py (see its docstring). It has Python 3.12, torch, transformers,
# timm, numpy 2, pandas and seaborn, but not hydra-core/omegaconf (and maybe not scipy): those come as wheels in
# gpu_bundle/wheels (git-ignored; `python experiments/gpu_check.py prepare` makes it here, the run carries it).
#   run(command="bash experiments/gpu_check.sh", carry=["gpu_bundle"], timeout_s=600)
# Extra arguments go to `gpu_check.py run` (e.g. --budget 420 --steps ratio forward). Results: $OUT (sent back),
# to be copied into experiments/results/ and committed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
need=(hydra-core omegaconf antlr4-python3-runtime)
$PY -c "import scipy" 2>/dev/null || need+=(scipy)
$PY -m pip install -q --no-index --no-deps --find-links gpu_bundle/wheels "${need[@]}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
PYTHONPATH=. exec $PY experiments/gpu_check.py run --device cuda "$@"
