#!/usr/bin/env bash
# The lent GPU machine's side of experiments/gpu_check.py (see its docstring). It has Python 3.12, torch, transformers,
# timm, numpy 2, pandas and seaborn, but not hydra-core/omegaconf (and maybe not scipy): those come as wheels in
# gpu_bundle/wheels (git-ignored; `python experiments/gpu_check.py prepare` makes it here, the run carries it).
#   run(command="bash experiments/gpu_check.sh", carry=["gpu_bundle"], timeout_s=600)
# The wheels are unpacked into a folder of their own on PYTHONPATH (no pip, nothing installed into the machine's
# Python; a module the machine has already is left alone). Extra arguments go to `gpu_check.py run`
# (e.g. --budget 420 --steps ratio forward). Results: $OUT (sent back), to copy into experiments/results/ and commit.
# The run sends the checkout, 64 MiB at most, and the zoo's weights are 85 MiB: before the call move every
# pairedgta/models/weights/<member> but the main job's four (demo_segformer, demo_segformer_noaug, demo_ddrnet,
# demo_pidnet) out of the tree, and `git checkout pairedgta/models/weights` after it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
SITE=$(mktemp -d)
$PY - "$SITE" gpu_bundle/wheels <<'PYEOF'
import importlib.util, pathlib, sys, zipfile
site, wheels = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
for wheel, module in (("hydra_core", "hydra"), ("omegaconf", "omegaconf"), ("antlr4_python3_runtime", "antlr4"),
                      ("scipy", "scipy")):
    if importlib.util.find_spec(module) is not None:
        print(f"{module}: the machine's own")
        continue
    for w in wheels.glob(f"{wheel}-*.whl"):
        zipfile.ZipFile(w).extractall(site)
        print(f"{module}: from {w.name}")
PYEOF
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
PYTHONPATH=".:$SITE${PYTHONPATH:+:$PYTHONPATH}" exec $PY experiments/gpu_check.py run --device cuda "$@"
