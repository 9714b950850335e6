#!/usr/bin/env bash
# GenSplat with LeRobot's stock trainer. Needs: bash scripts/setup.sh lerobot
#   bash examples/lerobot_one_line.sh [dataset root]
set -euo pipefail
export HF_HUB_OFFLINE=1
root="${1:-outputs/scene_dataset}"
repo_id=local/gensplat_scene

# 1. a local LeRobot dataset with calibrated cameras and depth (here: the built-in scene)
[ -d "$root" ] || python -c "
from gensplat_lerobot.record import record_scene_dataset
from gensplat_transforms.episodes import SceneEpisodes
record_scene_dataset('$root', SceneEpisodes(num_episodes=4, num_frames=30, size=96), '$repo_id')"

# 2. once: settings + Gaussian cache beside the dataset
gensplat cache --root "$root" --repo-id "$repo_id" --level train --probability 0.5

# 3. train; the last line is the one that turns GenSplat on
lerobot-train --config_path=policies/diffusion.json \
  --dataset.repo_id="$repo_id" --dataset.root="$root" \
  --steps=10 --batch_size=4 --num_workers=2 --output_dir=outputs/dp_gensplat \
  --gensplat.discover_packages_path=gensplat_lerobot.plugin
