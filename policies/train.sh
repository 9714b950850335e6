#!/usr/bin/env bash
# Train a policy with LeRobot's stock trainer, with or without GenSplat.
#   bash policies/train.sh <diffusion|pi0|CONFIG.json> <gensplat|baseline> [lerobot-train overrides...]
# (a path to a JSON file uses that config instead of policies/<policy>.json), e.g.
#   bash policies/train.sh diffusion gensplat --dataset.root=data/sim --output_dir=outputs/dp_gensplat
# Run `gensplat cache --root <dataset root> --repo-id <id>` once before a GenSplat run.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
policy="${1:?policy: diffusion or pi0}"; mode="${2:?mode: gensplat or baseline}"; shift 2
if [[ -f "$policy" ]]; then config="$policy"; else config="$here/$policy.json"; fi
args=(--config_path="$config" "$@")
case "$mode" in
  # The one line that turns GenSplat on:
  gensplat) args+=(--gensplat.discover_packages_path=gensplat_lerobot.plugin) ;;
  baseline) ;;
  *) echo "mode must be gensplat or baseline, got $mode" >&2; exit 2 ;;
esac
exec lerobot-train "${args[@]}"
