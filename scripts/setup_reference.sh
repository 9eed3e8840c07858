#!/usr/bin/env bash
# The 2D pose estimator blsm/pose2d/mediapipe_pose.py runs in: the reference of the transfer check
# (recovery transfer, docs/transfer.md) and the detector of markerless registration (docs/markerless.md):
# MediaPipe Pose 0.10.9 in an environment of its own (it pins protobuf 3 and its own OpenCV), with
# its "full" BlazePose models from the wheel (nothing is downloaded at run time). About 1 minute.
#   bash scripts/setup_reference.sh [ENV]      (default: .venv-reference)
set -euo pipefail
PY=${PY:-python3.11}
ENV=${1:-.venv-reference}
if [ -x "$ENV/bin/python" ] && "$ENV/bin/python" -c "import mediapipe" 2>/dev/null; then
    echo "$ENV: MediaPipe is there"; exit 0
fi
rm -rf "$ENV.tmp"
"$PY" -m venv "$ENV.tmp"
"$ENV.tmp/bin/pip" install -q mediapipe==0.10.9 numpy==2.4.6 protobuf==3.20.3 opencv-contrib-python==5.1.0.95 pillow
"$ENV.tmp/bin/python" -c "import mediapipe, mediapipe.python.solutions.pose"
rm -rf "$ENV"
mv "$ENV.tmp" "$ENV"
# the venv's scripts name their folder: point them at the final one
sed -i "s#$PWD/$ENV.tmp#$PWD/$ENV#g; s#$ENV.tmp#$ENV#g" "$ENV"/bin/* 2>/dev/null || true
echo "$ENV: MediaPipe $("$ENV/bin/python" -c 'import mediapipe; print(mediapipe.__version__)')"
