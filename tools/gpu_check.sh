#!/usr/bin/env bash
# GPU check: the CUDA tests against the CPU result, and GPU build / accuracy figures.
#
# A GPU machine may lack open3d, pycolmap and rerun (and a package registry), so the check has two halves:
#   bash tools/gpu_check.sh prepare   # here, on the machine with the full install: fills .gpu/ with pycolmap
#                                     # (its wheel for the GPU machine's Python, unpacked, xz), the pre-rendered
#                                     # small test sequence and (when ../shared/data/fox exists) the fox sequence
#   bash tools/gpu_check.sh run [OUT] # there (needs torch with CUDA, numpy, h5py, opencv, scipy, pytest):
#                                     # unpacks pycolmap into /tmp/site, runs tests/test_cuda.py and times fox builds
#                                     # (640 px and full resolution; GPU_REFERENCE=1: also the reference-quality
#                                     # accuracy run, ~6 minutes)
# .gpu/ is ignored by git; carry it to the GPU machine (about 38 MB). GPU_PY (default 3.12) is the GPU machine's
# Python version for the wheel. Results (log, JSON) go to OUT (default: $OUT, else ./gpu-out).
set -euo pipefail
cd "$(dirname "$0")/.."
export RERUN_ANALYTICS=false PYTHONUNBUFFERED=1
mode="${1:-}"

case "$mode" in
prepare)
    py="${GPU_PY:-3.12}"
    rm -rf .gpu && mkdir -p .gpu
    whl="$(mktemp -d)"
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$py" --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        -d "$whl" "pycolmap==$(python3 -c 'import pycolmap; print(pycolmap.__version__)')"
    # the wheels unpacked (a wheel is its site-packages tree) and packed with xz: 22 MB instead of the
    # 38 MB zip, which with the fox and the tracked files passed the 64 MiB a GPU call can carry
    mkdir "$whl/site" && for w in "$whl"/*.whl; do python3 -m zipfile -e "$w" "$whl/site"; done
    tar -C "$whl/site" -cf - . | xz -T0 -6 > .gpu/site.tar.xz
    rm -rf "$whl"
    python3 - <<'PY'
import sys
sys.path.insert(0, "tests")
from conftest import SMALL
from favormap.synthetic import write_sequence
write_sequence(".gpu/small", depth=False, **SMALL)  # tests/test_cuda.py needs no depth maps (and the carry limit is 64 MiB)
PY
    if [ -d ../shared/data/fox ]; then cp -r ../shared/data/fox .gpu/fox; fi
    du -sh .gpu
    # what a device call sends: tracked and untracked-not-ignored files, plus the carried .gpu/ (64 MiB at most)
    tree=$( { git ls-files -z; git ls-files -z --others --exclude-standard; } | xargs -0 stat -c %s 2>/dev/null | awk '{s += $1} END {print s + 0}')
    gpu=$(du -sb .gpu | cut -f1)
    echo "working tree ${tree} + .gpu ${gpu} = $((tree + gpu)) bytes (the device takes 67108864)"
    if [ $((tree + gpu)) -gt 67108864 ]; then echo "warning: over the device's 64 MiB: carry less (e.g. no fox)" >&2; fi
    echo "prepared .gpu/: carry it to the GPU machine and run 'bash tools/gpu_check.sh run' there"
    ;;
run)
    out="${2:-${OUT:-gpu-out}}"
    mkdir -p "$out"
    [ -f .gpu/site.tar.xz ] || { echo "error: .gpu/ missing: run 'bash tools/gpu_check.sh prepare' on a full install first" >&2; exit 1; }
    rm -rf /tmp/site && mkdir -p /tmp/site && tar -xJf .gpu/site.tar.xz -C /tmp/site
    export PYTHONPATH="$PWD:/tmp/site${PYTHONPATH:+:$PYTHONPATH}" FAVORMAP_SMALL_SEQUENCE="$PWD/.gpu/small"
    {
        nvidia-smi -L || true
        python3 -c 'import torch; print("torch", torch.__version__, "cuda", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")'
        echo "== CUDA tests (against the CPU result)"
        python3 -m pytest -p no:cacheprovider -m cuda tests/test_cuda.py -v -rs 2>&1 || echo "CUDA TESTS FAILED"
        if [ -d .gpu/fox ]; then
            export FAVORMAP_FOX="$PWD/.gpu/fox"
            echo "== SIFT patch descriptors alone, full resolution: OpenCV on the CPU threads against torch on the GPU"
            # with two other chunk sizes (sift_torch._default_budget: 2^24 window pixels on a GPU)
            timeout 150 python3 tools/bench_patches.py .gpu/fox --max-side 0 --budgets 4194304,67108864 \
                || echo "(benchmark failed or timed out)"
            echo "== fox build, 640 px, the defaults (balanced quality, next 10 frames at 1 px), GPU; CPU stages on a thread per core"
            timeout 150 python3 tools/bench_build.py .gpu/fox --device cuda || echo "(build failed or timed out)"
            echo "== fox build, 640 px, fast quality (Adam), GPU"
            timeout 150 python3 tools/bench_build.py .gpu/fox --device cuda --quality fast || echo "(build failed or timed out)"
            echo "== the same, SIFT's patch descriptors by OpenCV on the CPU threads (--patches-on cpu)"
            timeout 150 python3 tools/bench_build.py .gpu/fox --device cuda --patches-on cpu \
                || echo "(build failed or timed out)"
            echo "== fox build, full resolution, the defaults (balanced quality), GPU"
            timeout 200 python3 tools/bench_build.py .gpu/fox --device cuda --max-side 0 || echo "(build failed or timed out)"
            echo "== fox build, full resolution, fast quality (Adam), GPU"
            timeout 200 python3 tools/bench_build.py .gpu/fox --device cuda --max-side 0 --quality fast \
                || echo "(build failed or timed out)"
            echo "== the same, SIFT's patch descriptors by OpenCV on the CPU threads (--patches-on cpu)"
            timeout 200 python3 tools/bench_build.py .gpu/fox --device cuda --max-side 0 --patches-on cpu \
                || echo "(build failed or timed out)"
            echo "== fox build, full resolution, quick quality, GPU"
            timeout 150 python3 tools/bench_build.py .gpu/fox --device cuda --max-side 0 --quality quick \
                || echo "(build failed or timed out)"
            if [ "${GPU_REFERENCE:-0}" = 1 ]; then
                echo "== accuracy, reference quality, GPU (fox hold-out and extrapolation, with the pycolmap baseline)"
                timeout "${GPU_ACC_TIMEOUT:-330}" python3 tools/bench_accuracy.py --splits fox-holdout,fox-extrap \
                    --quality reference --device cuda --priors noise --variants rendered,mean,nearest-view \
                    --workdir /tmp/acc --json "$out/accuracy-reference.json" || echo "(accuracy run failed or timed out)"
            fi
        fi
    } 2>&1 | tee "$out/gpu_check.log"
    ;;
*)
    echo "usage: bash tools/gpu_check.sh prepare | run [OUT]" >&2
    exit 2
    ;;
esac
