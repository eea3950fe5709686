#!/usr/bin/env bash
# The peer benchmark (issue 26, item 6): the same volume rendered by VTK's
# vtkGPUVolumeRayCastMapper (what 3D Slicer and SlicerVirtualReality render with) and by
# cao-xr's ray caster, both on Mesa's CPU drivers (VTK: OpenGL through EGL on llvmpipe; cao-xr:
# Vulkan on lavapipe), same image size, step, transfer function, Phong shading, no AO, cao-xr's
# left-eye framing. Prints per volume VTK's seconds per frame, cao-xr's seconds of ray cast per
# eye and their ratio (medians of interleaved rounds), and writes both pictures and a side by
# side PNG per volume into OUT_DIR (scripts/bench_peer_vtk.py says exactly what is timed).
#
#   scripts/bench-peer.sh [OUT_DIR] [LABEL=VOLUME ...]
#
# OUT_DIR defaults to /tmp/bench-peer. The volumes default to the CT head (fetched once with
# `cao-xr fetch-ct`) and a full-resolution synthetic chest CT (512x512x133 at 0.7 x 0.7 x 2.5 mm,
# written once by `cao-xr bench scale` and kept in the cache); any .nrrd or .nii volume with an
# axis-aligned orientation can be given instead. VTK (pinned) and numpy are pip-installed into a
# private environment in ~/.cache/cao-xr, made once. The OpenGL window is EGL's (offscreen);
# when EGL cannot render here it falls back to GLX under Xvfb, and says so.
#
# Environment: CAO_XR_BIN (a cao-xr binary; default: `cargo build --release`),
# BENCH_PEER_SIZE (pixels per side, default 512), BENCH_PEER_ROUNDS (interleaved rounds per
# volume, default 3), BENCH_PEER_FRAMES (timed VTK renders per round, default 5),
# BENCH_PEER_CHEST (the chest's grid, default 512x512x133).
set -euo pipefail
cd "$(dirname "$0")/.."
# OpenGL through EGL or GLX on Mesa (llvmpipe), Xvfb for the fallback, a Python venv for VTK.
CAO_XR_EXTRA_PACKAGES="libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libglx-mesa0 xvfb xauth python3-venv" \
  source scripts/setup.sh

out="${1:-/tmp/bench-peer}"
[ $# -gt 0 ] && shift
mkdir -p "$out"
out=$(cd "$out" && pwd)

if [ -n "${CAO_XR_BIN:-}" ]; then
  src_bin=$CAO_XR_BIN
else
  cargo build --release --quiet
  src_bin=target/release/cao-xr
fi
[ -x "$src_bin" ] || { echo "bench-peer: $src_bin is not an executable" >&2; exit 1; }
# A private copy: a rebuild in this tree during the run must not change what is measured.
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
bin="$work/cao-xr"
cp "$src_bin" "$bin"

# cao-xr on lavapipe: the same Mesa CPU stack as VTK's llvmpipe, even where a GPU is present.
[ -n "${LVP_ICD:-}" ] || { echo "bench-peer: lavapipe (mesa-vulkan-drivers) is not installed" >&2; exit 1; }
export VK_DRIVER_FILES="$LVP_ICD"
# Mesa's OpenGL in software (llvmpipe), through Mesa's own EGL vendor library.
export LIBGL_ALWAYS_SOFTWARE=1
mesa_egl=/usr/share/glvnd/egl_vendor.d/50_mesa.json
[ -f "$mesa_egl" ] && export __EGL_VENDOR_LIBRARY_FILENAMES="$mesa_egl"

# cao-xr's data cache (src/volume/ct_head.rs cache_dir) and the private Python environment,
# made once with pip; VTK pinned so that the peer does not change under the numbers.
cache="${CAO_XR_DATA:-}"
if [ -z "$cache" ]; then
  case "${XDG_CACHE_HOME:-}" in
    /*) cache="$XDG_CACHE_HOME/cao-xr" ;;
    *) cache="$HOME/.cache/cao-xr" ;;
  esac
fi
mkdir -p "$cache"
vtk_version=9.7.1
venv="$HOME/.cache/cao-xr/vtk-$vtk_version"
py="$venv/bin/python"
if ! "$py" -c "import vtk, numpy" 2>/dev/null; then
  echo "bench-peer: installing VTK $vtk_version and numpy into $venv" >&2
  rm -rf "$venv"
  if ! { python3 -m venv "$venv" && "$venv/bin/pip" install -q "vtk==$vtk_version" numpy; }; then
    rm -rf "$venv"
    echo "bench-peer: VTK could not be installed into a private Python environment (python3-venv, pip)" >&2
    exit 1
  fi
fi

# The synthetic chest CT of `cao-xr bench scale` (src/volume/phantom.rs chest), kept: bench
# scale writes it as NIfTI (atomically, by rename), reads it back and removes it; a hard link
# taken as soon as it appears keeps the file, and the bench (this script's child) is stopped.
chest_volume() {
  local dims=$1 path="$cache/chest-$1.nii"
  if [ ! -f "$path" ]; then
    echo "bench-peer: writing the synthetic chest CT $dims with cao-xr bench scale" >&2
    local dir pid
    dir=$(mktemp -d "$cache/bench-scale.XXXXXX")
    "$bin" bench scale --sizes "$dims" --methods lao --rays 6 --steps 1 --size 16x16 \
      --frames 2 --dir "$dir" >"$dir/bench.log" 2>&1 &
    pid=$!
    while kill -0 "$pid" 2>/dev/null; do
      if [ -f "$dir/chest-$dims.nii" ] && ln "$dir/chest-$dims.nii" "$dir/keep" 2>/dev/null; then
        break
      fi
      sleep 0.05
    done
    if kill -0 "$pid" 2>/dev/null; then
      kill "$pid" 2>/dev/null || true
      for _ in $(seq 1 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
      kill -KILL "$pid" 2>/dev/null || true
    fi
    wait "$pid" 2>/dev/null || true
    if [ ! -f "$dir/keep" ]; then
      cat "$dir/bench.log" >&2
      rm -rf "$dir"
      echo "bench-peer: cao-xr bench scale did not write the chest CT" >&2
      return 1
    fi
    mv "$dir/keep" "$path"
    rm -rf "$dir"
  fi
  echo "$path"
}

volumes=("$@")
if [ ${#volumes[@]} -eq 0 ]; then
  ct="$cache/ct-head.nrrd"
  [ -f "$ct" ] || "$bin" fetch-ct >&2 || { echo "bench-peer: could not fetch the CT head" >&2; exit 1; }
  chest_dims="${BENCH_PEER_CHEST:-512x512x133}"
  chest=$(chest_volume "$chest_dims")
  volumes=("ct-head=$ct" "chest-$chest_dims=$chest")
fi

# EGL (offscreen, no display) first; GLX under Xvfb only if EGL cannot render here.
probe='import re, vtk
w = vtk.vtkRenderWindow(); w.SetOffScreenRendering(1); w.SetSize(16, 16)
w.AddRenderer(vtk.vtkRenderer()); w.Render()
m = re.search(r"OpenGL renderer string:\s*(.*)", w.ReportCapabilities())
print(type(w).__name__, m.group(1) if m else "?")'
run=()
if info=$(VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow "$py" -c "$probe" 2>/dev/null) \
    && [[ $info == vtkEGLRenderWindow* ]]; then
  export VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow
  backend="EGL, offscreen"
else
  echo "bench-peer: VTK could not render through EGL here; falling back to GLX under Xvfb" >&2
  export VTK_DEFAULT_OPENGL_WINDOW=vtkXOpenGLRenderWindow
  run=(xvfb-run -a -s "-screen 0 1280x1024x24")
  info=$("${run[@]}" "$py" -c "$probe" 2>/dev/null) || {
    echo "bench-peer: VTK cannot render through EGL nor GLX under Xvfb" >&2
    exit 1
  }
  backend="GLX under Xvfb (EGL failed)"
fi
echo "bench-peer: VTK renders with ${info}" >&2
[[ $info == *llvmpipe* ]] || echo "bench-peer: warning: VTK's OpenGL is not llvmpipe: ${info}" >&2

"${run[@]}" "$py" scripts/bench_peer_vtk.py --cao-xr "$bin" --out "$out" \
  --size "${BENCH_PEER_SIZE:-512}" --rounds "${BENCH_PEER_ROUNDS:-3}" \
  --frames "${BENCH_PEER_FRAMES:-5}" --backend "$backend" "${volumes[@]}"
