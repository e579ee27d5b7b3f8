#!/usr/bin/env bash
# Real RGB-D frames end to end. Fetches the Azure Kinect frame of a desk that PyPI's
# arcor2-kinect-azure ships (colour 1920x1080 JPEG, depth already transformed to colour, 16-bit
# mm), writes it as a scene folder with the colour camera's calibration as the package states it
# (rational_polynomial distortion, removed by deocc at read time), runs deocc on it and copies the
# pictures to docs/images/. Usage: scripts/real-frames.sh [OUT_DIR] (default target/real).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-target/real}
mkdir -p "$out"
wheel=$(ls "$out"/arcor2_kinect_azure-0.6.0-*.whl 2>/dev/null | head -1 || true)
if [[ -z $wheel ]]; then
  python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.10 \
    arcor2-kinect-azure==0.6.0 -d "$out"
  wheel=$(ls "$out"/arcor2_kinect_azure-0.6.0-*.whl | head -1)
fi
scene=$out/azure_kinect_desk
rm -rf "$scene" && mkdir -p "$scene/rgb" "$scene/depth"
python3 - "$wheel" "$scene" <<'PY'
import json, sys, zipfile
wheel, scene = sys.argv[1], sys.argv[2]
with zipfile.ZipFile(wheel) as z:
    open(f"{scene}/rgb/desk.jpg", "wb").write(z.read("arcor2_kinect_azure/data/rgb.jpg"))
    open(f"{scene}/depth/desk.png", "wb").write(z.read("arcor2_kinect_azure/data/depth.png"))
# The colour camera's calibration as arcor2_kinect_azure/scripts/kinect_azure.py gives it for
# these frames (fx, fy, cx, cy and OpenCV's k1 k2 p1 p2 k3 k4 k5 k6).
cam = {"frames": [{
    "name": "desk",
    "intrinsics": {"fx": 915.575, "fy": 915.425, "cx": 957.69, "cy": 556.35,
                   "width": 1920, "height": 1080},
    "distortion": {"model": "rational_polynomial",
                   "coefficients": [0.447, -2.5, 0.00094, -0.00053, 1.432, 0.329, -2.332, 1.363]},
}]}
json.dump(cam, open(f"{scene}/cameras.json", "w"), indent=1)
PY
cargo build --release --locked --workspace --all-features --bin deocc >/dev/null 2>&1 || true
./target/release/deocc run "$scene" --out "$out/azure_kinect_desk_run"
mkdir -p docs/images
cp "$out/azure_kinect_desk_run/render_novel_view.png" docs/images/real_azure_kinect_desk_novel.png
if [[ -f $out/azure_kinect_desk_run/render_objects.png ]]; then
  cp "$out/azure_kinect_desk_run/render_objects.png" docs/images/real_azure_kinect_desk_objects.png
fi

# A Kinect-class structured-light frame of a bookshelf: Debian's mrpt-common ships it as an MRPT
# rawlog (depth and colour cameras with their own calibrations), which deocc reads directly.
rawlog=$out/tests_rgbd.rawlog
if [[ ! -f $rawlog ]]; then
  (cd "$out" && apt-get download mrpt-common >/dev/null)
  deb=$(ls "$out"/mrpt-common_*.deb | head -1)
  rm -rf "$out/mrpt-common" && dpkg-deb -x "$deb" "$out/mrpt-common"
  cp "$out/mrpt-common/usr/share/mrpt/datasets/tests_rgbd.rawlog" "$rawlog"
fi
./target/release/deocc run "$rawlog" --out "$out/mrpt_bookshelf_run"
cp "$out/mrpt_bookshelf_run/render_input_view.png" docs/images/real_mrpt_bookshelf_input.png
cp "$out/mrpt_bookshelf_run/render_novel_view.png" docs/images/real_mrpt_bookshelf_novel.png
echo "real frames: $out/azure_kinect_desk_run, $out/mrpt_bookshelf_run (report.html); pictures in docs/images/"
