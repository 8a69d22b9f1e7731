#!/usr/bin/env bash
# Issue 26 on a GPU, in one call of at most about 7 minutes (written for one H100/H200):
#   1. every test that needs CUDA (the solver's in tests/geometry: the Triton kernels on CUDA, CUDA
#      against the CPU paths, the profiler's launch count, autocast, compile, fresh processes;
#      eigh past cuSOLVER's batch limit; a training step without host syncs; every trainer=);
#   2. bench/a_layer.py --device cuda: eigh, roma, the eager Jacobi, the Triton kernel (the
#      "rotlearn" column), 6D and SVD-9D at B = 32 ... 1M, float32 and bf16 autocast;
#   3. a whole trainer=gpu epoch, A head against 6D, at the paper's batch (100) and at 2048;
#   4. if time is left: the inductor compile of the A layer on CUDA.
# Every stage has its own time limit and runs whatever the previous ones did; results land in
# OUT_DIR: environment.json, tests.log/tests.xml, a_layer_cuda.json/.log, epoch_cuda*.json/.log,
# summary.txt (each stage's exit status and the numbers the issue's targets name).
#
#   [PYTHONPATH=WHEELS_DIR] bash bench/gpu_session.sh OUT_DIR   (from the repository root; adds src)
#
# Python packages: torch (CUDA), triton, lightning, torchmetrics, pytest, hypothesis (with their
# own dependencies: numpy, PyYAML), and the rest of the [train] extra plus roma from wheels:
# bench/gpu_wheels.sh fetches them (bench/gpu_requirements.txt) for a machine without a network,
# installed there with `pip install --no-deps --no-index --target DIR` and DIR on PYTHONPATH.
# Checked on a CPU in a venv with only those six packages and the wheels: every stage imports and
# runs (the CUDA ones stop at "no CUDA device"). environment.json lists what was found; a stage
# that lacks a package fails fast and says which.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: bash bench/gpu_session.sh OUT_DIR}
mkdir -p "$out"
PY=${PYTHON:-python3}
export PYTHONPATH="src${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1 PYTHONWARNINGS=ignore HYDRA_FULL_ERROR=1
start=$SECONDS
status=()

stage() {  # stage NAME LIMIT_S COMMAND...: run with a time limit, log to OUT_DIR/NAME.log
    local name=$1 limit=$2
    shift 2
    echo "== $name (limit ${limit} s, at $((SECONDS - start)) s)"
    local t0=$SECONDS
    timeout -k 10 "$limit" "$@" > "$out/$name.log" 2>&1
    local rc=$?
    tail -n 25 "$out/$name.log"
    status+=("$name: exit $rc after $((SECONDS - t0)) s")
    echo "== $name: exit $rc after $((SECONDS - t0)) s"
}

stage environment 30 "$PY" - "$out/environment.json" <<'PY'
import importlib.util, json, os, platform, sys
import torch
found = {}
for name in ["triton", "numpy", "lightning", "torchmetrics", "pytest", "hypothesis", "hydra",
             "omegaconf", "antlr4", "yaml", "matplotlib", "pandas", "tensorboard", "roma"]:
    spec = importlib.util.find_spec(name)
    version = None
    if spec is not None:
        try:
            version = getattr(__import__(name), "__version__", "?")
        except Exception as error:  # noqa: BLE001
            version = f"import fails: {error}"
    found[name] = version
info = {
    "python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
    "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    "capability": torch.cuda.get_device_capability(0) if torch.cuda.is_available() else None,
    "cpu_count": os.cpu_count(), "packages": found,
    "missing": sorted(k for k, v in found.items() if v is None),
}
json.dump(info, open(sys.argv[1], "w"), indent=2)
print(json.dumps(info, indent=2))
if not torch.cuda.is_available():
    sys.exit("no CUDA device")
PY

TESTS=(tests/geometry/test_eigen4.py tests/geometry/test_eigen4_triton.py
       tests/geometry/test_eigen4_first_call.py tests/geometry/test_eigen4_ops.py
       tests/geometry/test_linalg.py tests/lit/test_finite.py tests/cli/test_configs.py)
stage tests 200 "$PY" -m pytest -q -p no:cacheprovider -m "not slow" \
    -k "cuda or triton or gpu or trainer_option" --junitxml="$out/tests.xml" "${TESTS[@]}"

stage a_layer_cuda 150 "$PY" bench/a_layer.py --device cuda --repeats 3 --budget 0.1 \
    --out "$out/a_layer_cuda.json"

stage epoch_cuda 50 "$PY" bench/run.py epoch --device cuda --reps a,sixd --epochs 4 \
    --out "$out/epoch_cuda.json"
stage epoch_cuda_b2048 50 "$PY" bench/run.py epoch --device cuda --reps a,sixd --epochs 4 \
    --overrides "data.batch_size=2048 data.num_val=2048 data.eval_batch_size=2048" \
    --out "$out/epoch_cuda_b2048.json"

left=$((400 - (SECONDS - start)))
if ((left > 40)); then
    stage inductor_cuda "$left" "$PY" -m pytest -q -p no:cacheprovider \
        "tests/geometry/test_eigen4_triton.py::test_cuda_compiles_to_one_graph"
else
    status+=("inductor_cuda: skipped, ${left} s left")
fi

{
    echo "issue 26 GPU session, $((SECONDS - start)) s"
    printf '%s\n' "${status[@]}"
    "$PY" - "$out" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
try:
    res = json.loads((out / "a_layer_cuda.json").read_text())
    print("a_layer:", res["machine"].get("gpu"), "path", res["machine"].get("rotlearn_path"))
    for row in res["results"]:
        r = row["ratios"]
        fmt = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        print(f"  {row['mode']:8s} B={row['batch']:<8d} eigh/rotlearn {fmt(r['eigh/rotlearn'])}"
              f"  roma/rotlearn {fmt(r['roma/rotlearn'])}  rotlearn/sixd {fmt(r['rotlearn/sixd'])}")
except Exception as error:  # noqa: BLE001
    print("a_layer: no result:", error)
for name in ("epoch_cuda", "epoch_cuda_b2048"):
    try:
        res = json.loads((out / f"{name}.json").read_text())["result"]
        reps = {k: round(v["epoch_time_s"], 4) for k, v in res["reps"].items()}
        print(f"{name}: s/epoch {reps}, A/6D {res.get('a_over_sixd', float('nan')):.3f}")
    except Exception as error:  # noqa: BLE001
        print(f"{name}: no result:", error)
PY
} | tee "$out/summary.txt"
