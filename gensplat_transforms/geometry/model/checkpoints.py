"""Weights on disk: GenSplat checkpoints (config.json + model.safetensors), Pi3 checkpoints, hub ids."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file
from torch import nn

FORMAT_NAME = "gensplat-model"
FORMAT_VERSION = 1
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
GAUSSIAN_PREFIX = "gaussian_head."  # the only keys a Pi3 checkpoint lacks

_HUB_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")


@dataclass
class LoadReport:
    """What a non-strict load did: keys the model kept at their initial values (``missing``) and
    checkpoint keys it had no place for (``unexpected``)."""

    loaded: int
    missing: list[str]
    unexpected: list[str]

    @property
    def missing_outside_gaussian_head(self) -> list[str]:
        return [k for k in self.missing if not k.startswith(GAUSSIAN_PREFIX)]

    def __str__(self) -> str:
        def short(keys):
            return ", ".join(keys[:5]) + (f", ... ({len(keys)} in all)" if len(keys) > 5 else "")

        gs = len(self.missing) - len(self.missing_outside_gaussian_head)
        lines = [f"loaded {self.loaded} tensors; {gs} Gaussian-head tensors keep their initial values"]
        if self.missing_outside_gaussian_head:
            lines.append(f"missing: {short(self.missing_outside_gaussian_head)}")
        if self.unexpected:
            lines.append(f"unexpected: {short(self.unexpected)}")
        return "; ".join(lines)


def load_pi3_weights(model: nn.Module, path: str | Path) -> LoadReport:
    """Load a Pi3 ``model.safetensors`` (or any partial state dict) into ``model`` non-strictly.

    Raises ``ValueError`` when a shared key has another shape (wrong model size) or when the
    file shares no key with the model. Returns what was missing and unexpected.
    """
    path = Path(path)
    if path.is_dir():
        path = path / WEIGHTS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint file")
    state = read_weights(path)
    own = model.state_dict()
    shared = [k for k in state if k in own]
    if not shared:
        raise ValueError(f"{path}: shares no key with the model (not a Pi3 / GenSplat checkpoint?)")
    wrong = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
        for k in shared
        if state[k].shape != own[k].shape
    ]
    if wrong:
        raise ValueError(
            f"{path}: {len(wrong)} shape mismatches (another model size?): " + "; ".join(wrong[:5])
        )
    result = model.load_state_dict(state, strict=False)
    return LoadReport(len(shared), list(result.missing_keys), list(result.unexpected_keys))


def check_pi3_file(path: Path, shapes: dict[str, torch.Size]) -> None:
    """Refuse (``ValueError`` naming the file) a weights file that is not a Pi3 checkpoint of a
    model with these ``shapes`` (``state_dict`` shapes, e.g. of a model built on the meta device),
    from its header alone, before a full-size model is allocated: every tensor outside the
    Gaussian head must be there with its shape."""
    try:
        with safe_open(str(path), framework="pt") as f:
            found = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}  # noqa: SIM118 (not a dict)
    except (SafetensorError, OSError) as e:
        raise ValueError(f"{path}: not a readable safetensors file ({e})") from None
    needed = [k for k in shapes if not k.startswith(GAUSSIAN_PREFIX)]
    missing = [k for k in needed if k not in found]
    wrong = [f"{k}: file {found[k]} vs model {tuple(shapes[k])}" for k in needed if k in found
             and found[k] != tuple(shapes[k])]  # fmt: skip
    if missing or wrong:
        what = (f"{len(missing)} of the model's {len(needed)} tensors are missing (e.g. {', '.join(missing[:3])})"
                if missing else f"{len(wrong)} shape mismatches ({'; '.join(wrong[:3])})")  # fmt: skip
        raise ValueError(f"{path}: not a Pi3 checkpoint of this model (another architecture or size?): {what}")


def read_config(path: Path) -> dict:
    """A checkpoint's config.json as a dict; ``ValueError`` naming the file when it is not a JSON object,
    ``FileNotFoundError`` when it is not a file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (a checkpoint folder holds config.json beside its weights)")
    try:
        meta = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not JSON ({e})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(meta).__name__}")  # noqa: TRY004 (the file)
    return meta


def read_weights(path: Path, shapes: dict[str, torch.Size] | None = None) -> dict[str, torch.Tensor]:
    """The tensors of a safetensors file; ``ValueError`` naming the file when it is not one, when it
    holds NaN or Inf, or (given the model's ``shapes``) lacks, adds or mis-shapes a key."""

    def short(items):
        return ", ".join(items[:5]) + (f", ... ({len(items)} in all)" if len(items) > 5 else "")

    try:
        state = load_file(str(path))
    except SafetensorError as e:
        raise ValueError(f"{path}: not a readable safetensors file ({e})") from None
    if shapes is not None:
        problems = {
            "missing": [k for k in shapes if k not in state],
            "unexpected": [k for k in state if k not in shapes],
            "shape mismatches": [f"{k}: file {tuple(v.shape)} vs model {tuple(shapes[k])}"
                                 for k, v in state.items() if k in shapes and v.shape != shapes[k]],
        }  # fmt: skip
        if any(problems.values()):
            raise ValueError(f"{path}: does not fit the model (another model size?): "
                             + "; ".join(f"{name}: {short(keys)}" for name, keys in problems.items() if keys))
    bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise ValueError(f"{path}: NaN or Inf weights in {short(bad)}")
    return state


def resolve(source: str | Path) -> Path:
    """A local checkpoint directory, or a hub id ``owner/name`` fetched with huggingface_hub
    (config and weights only) when that package is installed."""
    path = Path(source).expanduser()
    if path.is_dir():
        return path
    if path.exists():
        raise ValueError(f"{path}: expected a directory holding {CONFIG_FILE} and {WEIGHTS_FILE}")
    if not _HUB_ID.fullmatch(str(source)):
        raise FileNotFoundError(f"{source}: no such directory, and not a hub id of the form 'owner/name'")
    try:
        from huggingface_hub import snapshot_download
    except ImportError:
        raise ImportError(
            f"{source!r} is not a local directory; fetching it from the Hugging Face hub needs the "
            "huggingface_hub package (pip install huggingface_hub), or download it yourself and pass "
            "the directory"
        ) from None
    try:
        return Path(snapshot_download(str(source), allow_patterns=[CONFIG_FILE, WEIGHTS_FILE]))
    except Exception as e:  # offline, no such repo, no access, network: huggingface_hub's many errors
        raise ValueError(f"{source!r} is not a local directory and could not be fetched from the Hugging Face "
                         f"hub ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}); download it where "
                         "the hub is reachable and pass the directory") from e


def check_state(model: nn.Module, state: dict[str, torch.Tensor], source: Path, what: str,
                optional: tuple[str, ...] = ()) -> None:  # fmt: skip
    """``ValueError`` naming the keys of ``state`` that do not fit ``model`` (missing but for
    ``optional``, unexpected, of another shape): ``{source}: does not fit {what}: ...``."""
    own = model.state_dict()
    missing = sorted(k for k in own.keys() - state.keys() if k not in optional)
    unexpected = sorted(state.keys() - own.keys())
    wrong = [f"{k}: file {tuple(state[k].shape)} vs model {tuple(v.shape)}"
             for k, v in own.items() if k in state and state[k].shape != v.shape]  # fmt: skip
    problems = [f"{label} ({len(keys)}): {', '.join(keys[:5])}{', ...' if len(keys) > 5 else ''}"
                for label, keys in [("missing keys", missing), ("unexpected keys", unexpected),
                                    ("shape mismatches", wrong)] if keys]  # fmt: skip
    if problems:
        raise ValueError(f"{source}: does not fit {what}: " + "; ".join(problems))
