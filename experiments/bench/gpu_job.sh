#!/usr/bin/env bash
# The prepared GPU measurement, sized for one ≈ 9-minute call of a lent GPU: what no GPU has
# measured yet (the paper-scale maze grids have been timed on an H200: docs/benchmarks.md#on-a-gpu), most
# informative first, each program's JSON line written as soon as it is measured.
#
#   OUT=/tmp/gpu bash experiments/bench/gpu_job.sh            # paper scale, stops itself after $BUDGET_S (540) s
#   OUT=/tmp/gpu bash experiments/bench/gpu_job.sh smoke      # seconds, any machine: checks the script
#
# Where the machine lacks our packages, wheels in .whl/ are installed to /tmp/site first. Carry only
# what it lacks: a GPU image's own jax needs its own flax (flax 0.12.6 fails on jax 0.11). The one
# H200 lent so far lacked brax, mujoco, mujoco-core, mujoco-mjx, jaxopt, trimesh, glfw, tyro, docstring_parser and
# typeguard (mujoco-studio, which only renders, can stay behind).
set -u -o pipefail
OUT=${OUT:-/tmp/gpu_job}
SCALE=${1:-paper}
BUDGET_S=${BUDGET_S:-540}
start=$(date +%s)
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if compgen -G ".whl/*.whl" >/dev/null; then
  rm -rf /tmp/site; python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH="/tmp/site:$PYTHONPATH"
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null | tee "$OUT/env.txt"
check='import jax, flax, optax, chex, brax, mujoco, ccp_jax.trainer, envs_mjx.peg_in_hole
flax.linen.Dense(2).init(jax.random.key(0), jax.numpy.ones(3))  # where a flax too old for this jax fails
print("jax", jax.__version__, "flax", flax.__version__, "optax", optax.__version__, "chex", chex.__version__,
      "brax", brax.__version__, "mujoco", mujoco.__version__, jax.devices())'
if ! python3 -c "$check" 2>&1 | tee -a "$OUT/env.txt"; then
  # The image's own flax/optax/chex/orbax may suit its jax better than our pins: try them.
  rm -rf /tmp/site/flax* /tmp/site/optax* /tmp/site/chex* /tmp/site/orbax
  python3 -c "$check" 2>&1 | tee -a "$OUT/env.txt" || exit 1
fi

left() { echo $((BUDGET_S - ($(date +%s) - start))); }
P=experiments/bench/paper_projection.py
# The maze grids have been timed on a GPU; what no GPU has timed yet comes first: one peg run alone (MJX: compile
# or epochs?), brax's SAC against ours on the same maze work, then the peg grid.
timeout $(( $(left) / 3 )) python3 $P --scale "$SCALE" --domains peg --no-grid --out "$OUT/projection.jsonl" \
  2>&1 | tee "$OUT/log.txt"
if [ "$SCALE" = smoke ]; then brax_args="--hidden 16 16 --epoch-steps 500 --epochs 1 --rounds 1 --buffer 5000"; \
else brax_args="--epochs 2 --rounds 1"; fi
timeout $(( $(left) / 2 )) python3 experiments/bench/vs_brax.py $brax_args 2>&1 | tee -a "$OUT/log.txt"
timeout "$(left)" python3 $P --scale "$SCALE" --domains peg --no-single --out "$OUT/projection.jsonl" \
  2>&1 | tee -a "$OUT/log.txt"
echo "job done in $(( $(date +%s) - start )) s" | tee -a "$OUT/log.txt"
