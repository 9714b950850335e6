#!/usr/bin/env bash
# GenSplat with LeRobot's stock trainer, on a small built-in dataset. Needs: bash scripts/setup.sh lerobot
#   bash examples/lerobot_one_line.sh [dataset root]
# Runs from any folder with the project's environment (.venv); writes under the repository's outputs/.
set -euo pipefail
export HF_HUB_OFFLINE=1
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bin="$repo/.venv/bin"
root="${1:-$repo/outputs/scene_dataset}"
repo_id=local/gensplat_scene
run=1  # lerobot-train refuses an existing output folder: each run gets the next free one
while [ -e "$repo/outputs/dp_gensplat/run_$run" ]; do run=$((run + 1)); done
out="$repo/outputs/dp_gensplat/run_$run"

# 1. a local LeRobot dataset with calibrated cameras and depth (here: the built-in scene; kept for reruns)
[ -d "$root" ] || "$bin/python" -c "
import sys
from gensplat_lerobot.scene_dataset import record_scene_dataset
from gensplat_transforms.cache.builder import SceneEpisodes
record_scene_dataset(sys.argv[1], SceneEpisodes(num_episodes=4, num_frames=30, size=96), sys.argv[2])" "$root" "$repo_id"

# 2. once: settings + Gaussian cache beside the dataset (a rerun finds the cache built)
"$bin/gensplat" cache --root "$root" --repo-id "$repo_id" --level train --probability 0.5

# 3. train; the last line is the one that turns GenSplat on
"$bin/lerobot-train" --config_path="$repo/policies/diffusion.json" \
  --dataset.repo_id="$repo_id" --dataset.root="$root" \
  --steps=10 --batch_size=4 --num_workers=2 --output_dir="$out" \
  --gensplat.discover_packages_path=gensplat_lerobot.plugin
