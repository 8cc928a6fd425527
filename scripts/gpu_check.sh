#!/usr/bin/env bash
# The GPU check (issue: train and view on a GPU): on a machine with CUDA, nvcc and torch and no
# network, in one run of under eight minutes, from the repository root:
#   1. install the wheels carried in .whl/ (gsplat and what the image lacks, below) and this package;
#   2. build gsplat's CUDA kernels (its first use compiles them);
#   3. render the same Gaussians with gsplat and with the C++ CPU rasteriser: mean absolute
#      difference (bar: 1/255) and frames per second at 960x540 (`kgs-app bench gpu`);
#   4. train SCENE (walk at 960 px) with the defaults on CUDA, evaluate it on CUDA, and print
#      the training time, PSNR/SSIM at the sharp camera and render FPS.
#
# Usage: scripts/gpu_check.sh SCENE [OUT]     (OUT defaults to $OUT, else gpu_check_out)
#
# Prepare on a machine with the package registry (the device machine has none):
#   echo /.whl/ >> .git/info/exclude; echo /.gpu/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
#     pydantic pydantic-core annotated-types typing-inspection
#   python3 -m pip download --no-deps -d .whl gsplat     # a py3-none-any wheel: kernels built on first use
#   python3 scripts/pack_scene_jpeg.py /path/to/walk960 .gpu/walk960   # frames as JPEG: ~15 MB, not 51
# and carry .whl and .gpu; SCENE is then .gpu/walk960.
set -euo pipefail
SCENE=${1:?usage: scripts/gpu_check.sh SCENE [OUT]}
RESULTS=${2:-${OUT:-gpu_check_out}}
mkdir -p "$RESULTS"
export PYTHONUNBUFFERED=1
say() { printf '\n== %s (%ss)\n' "$1" "$SECONDS"; }

say "machine"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
nvcc --version | tail -1 || true
python3 -c "import torch; assert torch.cuda.is_available(), 'torch sees no CUDA device'; print('torch', torch.__version__, torch.cuda.get_device_name())"

say "install"
SITE=/tmp/kgs_site
mkdir -p "$SITE"
if compgen -G ".whl/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl
fi
python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir --target "$SITE" .
export PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}"
KGS=(python3 -m kgs_app.cli)

say "build gsplat's CUDA kernels"
python3 - <<'EOF'
import time, torch, gsplat
t0 = time.time()
means = torch.zeros(1, 3, device="cuda"); means[0, 2] = 2.0
quats = torch.tensor([[1.0, 0, 0, 0]], device="cuda"); scales = torch.full((1, 3), 0.1, device="cuda")
K = torch.tensor([[[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]], device="cuda")
img, _, _ = gsplat.rasterization(means, quats, scales, torch.ones(1, device="cuda"), torch.ones(1, 3, device="cuda"),
                                 torch.eye(4, device="cuda")[None], K, 64, 64)
torch.cuda.synchronize()
print(f"gsplat {gsplat.__version__}: built and drew in {time.time() - t0:.0f} s (centre {img[0, 32, 32].tolist()})")
EOF
"${KGS[@]}" build-ext

say "gsplat against the CPU rasteriser"
"${KGS[@]}" bench gpu --json "$RESULTS/compare.json"

say "train $SCENE on CUDA with the defaults"
start=$SECONDS
"${KGS[@]}" train "$SCENE" --out "$RESULTS/walk" --device cuda
echo "wall time of the training command: $((SECONDS - start)) s"

say "evaluate on CUDA"
"${KGS[@]}" eval "$RESULTS/walk" --device cuda | tee "$RESULTS/eval.md"
python3 - "$RESULTS" <<'EOF'
import json, sys
out = sys.argv[1]
info = json.load(open(f"{out}/walk/run.json")); m = json.load(open(f"{out}/walk/metrics.json"))
h, fps = m["heldout"], m["levels"][-1]["render_fps"]
print(f"SUMMARY: train {info['train_seconds']:.0f} s ({info['iteration']} iterations, {info['gaussians']:,} Gaussians); "
      f"sharp camera PSNR {h['psnr']:.2f} SSIM {h['ssim']:.3f} detail {h['detail']:.2f}; render {fps:.0f} FPS at full size")
EOF
say "done"
