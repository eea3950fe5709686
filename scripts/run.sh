#!/usr/bin/env bash
# The main job: installs what is missing, fetches the real CT head once (falls back to the
# built-in phantom if that is not possible), then `cao-xr start`: a headset session when an
# OpenXR runtime answers, else the desktop window when there is a display, else a headless render
# of the carved head to out/render/*.png (it says which it chose and why).
# Any arguments go to `cao-xr render` instead, e.g. scripts/run.sh phantom:96 --tool sphere:30.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/setup.sh
cargo build --release --quiet
bin=target/release/cao-xr
# cao-xr picks a discrete GPU if there is one, else lavapipe (no variable needed).
if [ $# -eq 0 ]; then
  $bin fetch-ct || echo "could not fetch the CT head; rendering the built-in phantom" >&2
  exec $bin start
fi
exec $bin render "$@"
