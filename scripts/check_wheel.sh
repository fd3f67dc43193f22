#!/usr/bin/env bash
# Non-editable install check: build the wheel as `pip install .` would, install it without dependencies into a
# fresh virtualenv that borrows the test environment's packages, and run the CLI from a folder outside the
# checkout, so presets and weights can only come from the installed package.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
PY="$(cd "$VENV/bin" && pwd)/python"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/vslam-wheel.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT

# The tree as git sees it (tracked and untracked files, ignored ones left out): a stale build/ or a deleted
# module cannot slip into the wheel.
mkdir "$WORK/src"
git ls-files -z --cached --others --exclude-standard | while IFS= read -r -d '' f; do
  [ -f "$f" ] && printf '%s\0' "$f"
done | tar --null -T - -cf - | tar -xf - -C "$WORK/src"
"$PY" -m pip wheel -q --no-deps -w "$WORK/dist" "$WORK/src"
WHEEL="$(ls "$WORK"/dist/vslam-*.whl)"
echo "check_wheel: $(basename "$WHEEL") $(du -k "$WHEEL" | cut -f1) KiB"

# The new environment sees the test environment's site-packages through a .pth line: a plain path, so the
# .pth files there (the editable install's finder among them) are not run and `import vslam` finds the wheel.
"$PY" -m venv --without-pip "$WORK/venv"
NEW="$WORK/venv/bin/python"
"$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])' \
  > "$("$NEW" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/vslam-test-env.pth"
"$PY" -m pip --python "$NEW" install -q --no-deps --no-index "$WHEEL"

mkdir "$WORK/run" && cd "$WORK/run"
export MPLBACKEND=Agg
"$NEW" -c 'import sys, vslam; assert vslam.__file__.startswith(sys.prefix), vslam.__file__; print("check_wheel: vslam from", vslam.__file__)'
VSLAM="$WORK/venv/bin/vslam"
"$VSLAM" presets >/dev/null
"$VSLAM" demo --frames 30 -o demo
# One preset on real data when present, with every shipped network loaded: ConvPoint, the detector, VLADNet.
NETS=(--set slam.features.extractor=convpoint --set slam.dynamic.enabled=true --set slam.dynamic.source=detector
      --set slam.loop.enabled=true --set slam.loop.descriptor=vladnet)
TUM="${VSLAM_DATA:-}/tum/rgbd_dataset_freiburg3_teddy"
if [ -n "${VSLAM_DATA:-}" ] && [ -d "$TUM" ]; then
  "$VSLAM" run --preset tum_rgbd --data "$TUM" --max-frames 20 -o tum "${NETS[@]}"
else
  echo "check_wheel: no TUM teddy under \$VSLAM_DATA; the preset runs on the synthetic room"
  "$VSLAM" run --preset synthetic --max-frames 20 -o synthetic "${NETS[@]}"
fi
echo "check_wheel: ok"
