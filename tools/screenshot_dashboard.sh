#!/usr/bin/env bash
# Re-make docs/dashboard.png: a fresh `rt-ident run` (or a given .rrd), the real rerun viewer under
# Xvfb with software rendering (Mesa's llvmpipe through Vulkan), rerun's own --screenshot-to.
#
#   tools/screenshot_dashboard.sh [--install] [RRD] [OUT.png]
#
# Needs: xvfb-run (Debian: xvfb) and a Vulkan software driver (Debian: mesa-vulkan-drivers);
# --install installs them with apt-get. The viewer binds 127.0.0.1 and runs as long as it takes
# to load and draw, then quits; nothing is left running.
set -euo pipefail
cd "$(dirname "$0")/.."
install=0
if [[ "${1:-}" == "--install" ]]; then install=1; shift; fi
rrd="${1:-}"
out="${2:-docs/dashboard.png}"
venv="${VIRTUAL_ENV:-.venv}"
rerun_bin="$venv/bin/rerun"; rt_ident="$venv/bin/rt-ident"
[[ -x "$rerun_bin" ]] || rerun_bin="$(command -v rerun || true)"
[[ -x "$rt_ident" ]] || rt_ident="$(command -v rt-ident || true)"
if [[ -z "$rerun_bin" || -z "$rt_ident" ]]; then
  echo "error: rerun / rt-ident not found: install the project first (README quick start)" >&2; exit 2
fi
if ! command -v xvfb-run >/dev/null || ! ls /usr/share/vulkan/icd.d/lvp_icd.*.json >/dev/null 2>&1; then
  if (( install )); then
    apt-get install -y -q xvfb mesa-vulkan-drivers libvulkan1 >/dev/null
  else
    echo "error: needs xvfb-run and Mesa's Vulkan software driver: apt-get install xvfb mesa-vulkan-drivers" \
         "(or run with --install)" >&2; exit 2
  fi
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
if [[ -z "$rrd" ]]; then
  rrd="$tmp/demo.rrd"
  echo "recording 8 s of the default run into $rrd ..." >&2
  (cd "$tmp" && "$rt_ident" run --duration 8 --rrd "$rrd" --json >/dev/null)
fi
mkdir -p "$(dirname "$out")"
# CI=1: rerun writes no analytics config; the viewer's own screenshot of a 1920x1080 window on a larger
# screen (the pointer starts at the screen's centre: outside the window, so no tooltip is drawn)
CI=1 XDG_RUNTIME_DIR="$tmp" timeout 180 xvfb-run -a -s "-screen 0 4000x2200x24" \
  "$rerun_bin" "$rrd" --bind 127.0.0.1 --window-size 1920x1080 --renderer vulkan --screenshot-to "$out" \
  >"$tmp/viewer.log" 2>&1 || { echo "error: the viewer failed; its log:" >&2; tail -20 "$tmp/viewer.log" >&2; exit 1; }
python3 - "$out" <<'PY'
import sys, zlib, struct
# a blank frame (the viewer could not draw) has one colour: refuse it
data = open(sys.argv[1], "rb").read()
if len(data) < 50_000:
    sys.exit(f"error: {sys.argv[1]} is only {len(data)} bytes: the viewer drew nothing")
print(f"wrote {sys.argv[1]} ({len(data) // 1024} kB)")
PY
