#!/usr/bin/env bash
# Runs one `cao-xr xr` session against Monado inside the trixie root (scripts/xr-root.sh), with
# no display: monado-service with the null compositor and two simulated controllers, lavapipe
# for Vulkan, the Khronos Vulkan validation layer (unless CAO_XR_VALIDATION=0 is passed in) and the
# OpenXR core validation layer on.
#
#   scripts/xr-session.sh ROOT CAO_XR_BINARY OUTDIR [cao-xr xr arguments...]
#
# The mounts live in a private mount namespace (unshare), so they vanish with it even when the
# run fails; monado-service is stopped on every exit path. OUTDIR receives monado.log,
# xr-validation.txt and whatever the session wrote into its working directory (e.g. a
# recording named with a relative path). Exit status: that of cao-xr. With
# CAO_XR_KILL_RUNTIME_AFTER=S, monado-service is killed S seconds after it is up; with
# CAO_XR_SIGNAL_AFTER="SIG S" (SIG: TERM or INT), cao-xr gets that signal S seconds after.
#
# CAO_XR_MONADO=remote runs Monado's remote driver instead of the simulated devices: an HMD and
# two Index controllers with simulated hands, driven over TCP port 4242 (struct r_remote_data).
# The session then gets its own network namespace with only loopback, so the port is reachable
# from nowhere else; the pid of a process inside it is written to OUTDIR/netns.pid for the
# client to join (setns), and cao-xr starts once Monado has logged the client's connection
# (waiting at most CAO_XR_REMOTE_WAIT seconds, default 60). monado-service itself gets
# CAO_XR_MONADO_WAIT seconds (default 90) to open its socket.
set -euo pipefail
ROOT=$(realpath "$1"); BIN=$2; OUT=$3; shift 3
[ -f "$ROOT/.cao-xr-ready" ] || { echo "xr-session: $ROOT is not a built root (run scripts/xr-root.sh)" >&2; exit 2; }
export CAO_XR_MONADO=${CAO_XR_MONADO:-simulated}
case $CAO_XR_MONADO in
  simulated) NET= ;;
  remote) NET=--net ;;
  *) echo "xr-session: CAO_XR_MONADO is '$CAO_XR_MONADO'; it must be simulated or remote" >&2; exit 2 ;;
esac
mkdir -p "$OUT"; OUT=$(realpath "$OUT")
rm -f "$OUT/netns.pid"
mkdir -p "$ROOT/tmp"
WORK=$(mktemp -d "$ROOT/tmp/cao-xr.XXXXXX")
chmod 755 "$WORK"
REL=${WORK#"$ROOT"}
# Keep what the session wrote (logs, recordings), not the binary, the bindings or the fifo.
trap 'find "$WORK" -maxdepth 1 -type f ! -name cao-xr ! -name inner.sh -exec cp {} "$OUT"/ \; ; rm -rf "$WORK" "$OUT/netns.pid"' EXIT
cp "$BIN" "$WORK/cao-xr"
cp -r "$(dirname "$0")/../controllers/bindings" "$WORK/bindings"
cat > "$WORK/inner.sh" <<'INNER'
set -u
W=$1; shift
cd "$W"
export XDG_RUNTIME_DIR=$W/run
mkdir -p -m 700 "$XDG_RUNTIME_DIR"
export VK_DRIVER_FILES=/usr/share/vulkan/icd.d/lvp_icd.json
# Monado's configuration comes from the session alone, never from the root's home.
export XRT_COMPOSITOR_NULL=1 XDG_CONFIG_HOME=$W/config
if [ "$CAO_XR_MONADO" = remote ]; then
  export P_OVERRIDE_ACTIVE_CONFIG=remote
else
  export SIMULATED_ENABLE=1 SIMULATED_LEFT=simple SIMULATED_RIGHT=simple
fi
# monado-service reads stdin (and quits on EOF): give it a pipe that stays open until we close it.
mkfifo "$W/service-stdin"
monado-service < "$W/service-stdin" > "$W/monado.log" 2>&1 &
MON=$!
exec 3> "$W/service-stdin"
stop() { exec 3>&-; for _ in $(seq 50); do kill -0 $MON 2>/dev/null || return; sleep 0.1; done; kill $MON 2>/dev/null; wait $MON 2>/dev/null; }
# Its null compositor starts lavapipe: seconds when idle, more on a loaded machine.
for _ in $(seq $((${CAO_XR_MONADO_WAIT:-90} * 10))); do [ -S "$XDG_RUNTIME_DIR/monado_comp_ipc" ] && break; kill -0 $MON 2>/dev/null || break; sleep 0.1; done
if [ ! -S "$XDG_RUNTIME_DIR/monado_comp_ipc" ]; then
  echo "xr-session: monado-service did not come up within ${CAO_XR_MONADO_WAIT:-90} s; its log:" >&2; cat "$W/monado.log" >&2; stop; exit 3
fi
echo "xr-session: monado-service is up" >&2
if [ "$CAO_XR_MONADO" = remote ]; then
  for _ in $(seq $((${CAO_XR_REMOTE_WAIT:-60} * 10))); do
    grep -q "Connection received" "$W/monado.log" && break; kill -0 $MON 2>/dev/null || break; sleep 0.1
  done
  if ! grep -q "Connection received" "$W/monado.log"; then
    echo "xr-session: no client connected to Monado's remote driver; its log:" >&2; cat "$W/monado.log" >&2; stop; exit 3
  fi
  echo "xr-session: a client drives Monado's remote devices" >&2
fi
# A runtime fault, for the tests: CAO_XR_KILL_RUNTIME_AFTER=S kills monado-service (SIGKILL) S
# seconds into the session, and writes the moment to runtime-killed.txt.
if [ -n "${CAO_XR_KILL_RUNTIME_AFTER:-}" ]; then
  ( sleep "$CAO_XR_KILL_RUNTIME_AFTER"; date +%s.%N > "$W/runtime-killed.txt"; kill -9 $MON ) &
fi
# A signal, for the tests: CAO_XR_SIGNAL_AFTER="SIG S" sends SIG to cao-xr itself (its pid is
# noted by the shell that becomes it) S seconds into the session.
if [ -n "${CAO_XR_SIGNAL_AFTER:-}" ]; then
  read -r SIG SECS <<< "$CAO_XR_SIGNAL_AFTER"
  ( sleep "$SECS"; kill -"$SIG" "$(cat "$W/cao-xr.pid")" ) &
fi
XR_ENABLE_API_LAYERS=XR_APILAYER_LUNARG_core_validation \
XR_CORE_VALIDATION_EXPORT_TYPE=text XR_CORE_VALIDATION_FILE_NAME="$W/xr-validation.txt" \
CAO_XR_VALIDATION="${CAO_XR_VALIDATION:-1}" CAO_XR_BINDINGS="$W/bindings" \
  timeout "${CAO_XR_SESSION_TIMEOUT:-300}" sh -c 'echo $$ > "$0.pid"; exec "$0" xr "$@"' "$W/cao-xr" "$@"
rc=$?
stop
exit $rc
INNER
unshare --mount $NET --propagation private -- bash -c '
  set -e
  if [ -n "$4" ]; then ip link set lo up; echo $$ > "$3/netns.pid"; fi
  mount --rbind /dev "$1/dev"
  mount -t proc proc "$1/proc"
  mount --rbind /sys "$1/sys"
  exec chroot "$1" /bin/bash "$2/inner.sh" "$2" "${@:5}"' _ "$ROOT" "$REL" "$OUT" "$NET" "$@"
