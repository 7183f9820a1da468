#!/usr/bin/env bash
# The GPU path measured on a machine with an NVIDIA GPU: CUDA tests, CPU-vs-GPU agreement, single-frame
# and sequence throughput (python -m bench.gpu), in under 8 minutes. See bench/README.md, "GPU".
#
#   bench/gpu.sh pack [DIR]            # HERE, with the project's .venv: write the carry folder DIR
#                                      # (default .gpu-carry): Warp in parts + a kernel cache for sm_90
#   bench/gpu.sh run [DIR] [ARGS...]   # THERE, from the repository root: unpack Warp from DIR (the parts
#                                      # gathered in one folder), then python3 -m bench.gpu ARGS
#
# Why the parts: the GPU machines lent to this project have PyTorch but no warp-lang and no package
# registry, and one call carries at most 64 MiB. Warp's native library (warp/bin/warp.so, ~300 MB,
# NVRTC included; warp-clang.so, ~70 MB, the CPU compiler) compresses to more than that, so `pack`
# writes the Warp package as one xz-compressed tar split into parts of at most $PART_MB MiB, one
# folder each (DIR/part0, DIR/part1, ...), carried by successive calls on a warm machine that copy
# them to one folder there (bench/README.md). It also compiles every kernel module for sm_$ARCH into
# a Warp kernel cache (wp.compile_aot_module; DIR/part0/kcache.tar.gz) that `run` points
# WARP_CACHE_PATH at, so the kernels are loaded there rather than compiled by NVRTC at first use.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PART_MB="${PART_MB:-50}"
ARCH="${ARCH:-90}"
cmd="${1:-}"
shift || true

case "$cmd" in
pack)
    DIR="${1:-$ROOT/.gpu-carry}"
    PY="${PYTHON:-$ROOT/.venv/bin/python}"
    [ -x "$PY" ] || PY="$(command -v python3)"
    SITE="$("$PY" -c 'import os, warp; print(os.path.dirname(os.path.dirname(warp.__file__)))')"
    rm -rf "$DIR"
    mkdir -p "$DIR/part0"
    echo "packing Warp from $SITE/warp into $DIR (parts of at most $PART_MB MiB)"
    tar -C "$SITE" --exclude='__pycache__' --exclude='warp/tests' --exclude='warp/examples' -cf - warp \
        | xz -T0 -6 -c | split -b "${PART_MB}m" -d -a 1 - "$DIR/warp.tar.xz."
    for f in "$DIR"/warp.tar.xz.*; do
        k="${f##*.}"
        mkdir -p "$DIR/part$k"
        mv "$f" "$DIR/part$k/"
    done
    echo "prebuilding the kernel cache for sm_$ARCH"
    rm -rf "$DIR/kcache"
    (cd "$ROOT" && WARP_CACHE_PATH="$DIR/kcache" "$PY" -m bench.gpu --prebuild-cache --arch "$ARCH")
    tar -C "$DIR/kcache" -czf "$DIR/part0/kcache.tar.gz" .
    rm -rf "$DIR/kcache"
    du -sh "$DIR"/part*
    n=$(ls -d "$DIR"/part* | wc -l)
    echo "carry $DIR/part0 .. part$((n - 1)), one per call (bench/README.md, GPU)"
    ;;
run)
    DIR="${1:-/tmp/specula-gpu}"
    shift || true
    [ -f "$DIR/warp.tar.xz.0" ] || { echo "gpu.sh: no $DIR/warp.tar.xz.0: gather the carried parts there first" >&2; exit 2; }
    W=/tmp/specula-warp
    rm -rf "$W"
    mkdir -p "$W/kcache"
    cat "$DIR"/warp.tar.xz.* | xz -dc | tar -C "$W" -xf -
    [ -f "$DIR/kcache.tar.gz" ] && tar -C "$W/kcache" -xzf "$DIR/kcache.tar.gz"
    export PYTHONPATH="$W:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
    export WARP_CACHE_PATH="$W/kcache"
    export PYTHONUNBUFFERED=1
    PY="${PYTHON:-python3}"
    cd "$ROOT"
    "$PY" -c 'import warp as wp; wp.init(); print("warp", wp.config.version, "from", wp.__file__, "devices", [d.alias for d in wp.get_devices()])'
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
    # 8 minutes at most: bench.gpu keeps its own budget (the tests get what is left), timeout is the backstop
    timeout 480 "$PY" -m bench.gpu --device cuda:0 --budget 450 "$@"
    ;;
*)
    echo "usage: bench/gpu.sh pack [DIR] | bench/gpu.sh run [DIR] [bench.gpu options]" >&2
    exit 2
    ;;
esac
