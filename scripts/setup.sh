#!/usr/bin/env bash
# Create ./.venv with a Python >= 3.12 and install gensplat-transforms into it (editable).
# Usage: bash scripts/setup.sh [extra[,extra...]]   e.g. `bash scripts/setup.sh dev`
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-}"

find_python() {
  local candidates=(python3.12 python3.13 python3)
  if command -v pyenv >/dev/null 2>&1; then
    for v in $(pyenv versions --bare 2>/dev/null | grep -E '^3\.(1[2-9])' || true); do
      candidates+=("$(pyenv root)/versions/$v/bin/python")
    done
  fi
  for py in "${candidates[@]}"; do
    if command -v "$py" >/dev/null 2>&1 && "$py" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then
      echo "$py"; return 0
    fi
  done
  return 1
}

if [ ! -x .venv/bin/python ]; then
  py=$(find_python) || { echo "setup: need Python >= 3.12 (python3.12 on PATH or via pyenv)" >&2; exit 1; }
  echo "setup: creating .venv with $("$py" --version)"
  "$py" -m venv .venv
fi
spec="."
[ -n "$extras" ] && spec=".[${extras}]"
echo "setup: pip install -e '$spec' (the first run downloads PyTorch: several minutes)"
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e "$spec"
.venv/bin/python -c "import gensplat_transforms, torch; print('setup: gensplat_transforms', gensplat_transforms.__version__, '| torch', torch.__version__)"
