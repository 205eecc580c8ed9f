#!/usr/bin/env bash
# Regenerate every shipped bag (and its .truth.yaml) from its scenario file.
# Usage: bags/make_bags.sh [NAME ...]   (default: all). Run from anywhere; needs `ppoe` or the repo's venv.
set -euo pipefail
cd "$(dirname "$0")/.."
PPOE=${PPOE:-"python -m ppoe_ros.cli"}
NAMES=("$@")
if [ ${#NAMES[@]} -eq 0 ]; then
  NAMES=(table1_exp1 table1_exp2 contact no_effect effect_joint_offset effect_gravity_compliance
         effect_mount_bending effect_unexplained effect_camera_extrinsics)
fi
for name in "${NAMES[@]}"; do
  PYTHONPATH=. $PPOE simulate "bags/${name}.yaml" --out "bags/${name}" --force
done
du -sh bags/*/ | sort -k2
