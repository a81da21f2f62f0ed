#!/usr/bin/env bash
# GPU half of benchmarks/dense_cuda.py, run on a CUDA machine (Python 3.12, no network) from
# the repo root:  OUT=results bash benchmarks/dense_cuda.sh [STEP ...]
#   dense   CUDA back-end + fusion on .dense_cuda/workspace.tar -> $OUT/dense_cuda.{ply,json}, dense.log
#   test    the `cuda`-marked test tests/test_dense_cuda.py       -> $OUT/pytest.log
#   render  MuJoCo EGL timing of the tomb's .render_whl/viewpoints.csv (100 views) -> $OUT/render.log
# Copy .dense_cuda beside the checkout for dense/test, .render_whl and .gl (the GL loader .debs:
# libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2) for render. Build them on a
# machine with network access (git-ignored), Python 3.12 wheels by
# `pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 ...`:
#   .dense_cuda/pycolmap_cuda.tar.xz  the unpacked pycolmap-cuda12==4.0.4 wheel, `tar -cf - . | xz -9e` (39 MB)
#   .dense_cuda/lib/  libcudart.so.12 of nvidia-cuda-runtime-cu12==12.9.79; libSM.so.6 libICE.so.6
#       libX11.so.6 libXext.so.6 libxcb.so.1 libXau.so.6 libXdmcp.so.6 libbsd.so.0 libmd.so.0 as real
#       files from `apt-get download libsm6 libice6 libx11-6 libxext6 libxcb1 libxau6 libxdmcp6 libbsd0
#       libmd0` + dpkg -x (Debian bookworm). libcurand.so.10 is the device's (CUDA 13 toolkit).
#   .dense_cuda/workspace.tar  `python -m benchmarks.dense_cuda workspace ...` (12 MB; may be xz-compressed
#       as workspace.tar.xz to fit the carry budget with the pycolmap archive)
#   .render_whl/  mujoco==4.0.0 mujoco-core==4.0.0 pyopengl==3.1.10 trimesh==5.2.0 wheels + the
#       exploratory flight's plan/viewpoints.csv;  .gl/  the README's GL loader .debs.
set -o pipefail
OUT=${OUT:-results/device_dense_cuda}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/site:$PWD
mkdir -p /tmp/site /tmp/ws
nvidia-smi -L
pycolmap_ready=
setup_pycolmap() {
  [ -n "$pycolmap_ready" ] && return 0
  tar -xJf .dense_cuda/pycolmap_cuda.tar.xz -C /tmp/site || return 1
  local curand
  curand=$(find / -xdev -name 'libcurand.so.10' -not -path '/proc/*' 2>/dev/null | head -1)
  export LD_LIBRARY_PATH=$PWD/.dense_cuda/lib:$(dirname "${curand:-/x/x}")
  ldd /tmp/site/pycolmap/_core*.so | grep -E 'not found|curand|cudart'
  python3 -c 'import pycolmap; print("pycolmap", pycolmap.__version__, "has_cuda", pycolmap.has_cuda)' &&
    pycolmap_ready=1
}
for step in ${*:-dense test}; do
  case $step in
    dense)
      setup_pycolmap && tar -xf .dense_cuda/workspace.tar* -C /tmp/ws || exit 1
      python3 -m benchmarks.dense_cuda dense /tmp/ws --backend cuda --out "$OUT" 2>&1 |
        tee "$OUT/dense.log" | grep -v '^[IW]2' ;;
    test)
      setup_pycolmap || exit 1
      python3 -m pytest -q -p no:cacheprovider -m cuda tests/test_dense_cuda.py 2>&1 | tail -c 200000 >"$OUT/pytest.log"
      tail -4 "$OUT/pytest.log" ;;
    render)
      for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
      python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        .render_whl/*.whl || exit 1
      vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
      [ -f $vendor ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
      MUJOCO_GL=egl python3 -m benchmarks.dense_cuda render .render_whl/viewpoints.csv /tmp/render --views 100 2>&1 |
        tee "$OUT/render.log" | tail -4 ;;
    *) echo "unknown step $step (dense | test | render)"; exit 2 ;;
  esac
done
