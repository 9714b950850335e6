"""Where the policy study's update step goes (``updt_s`` of ``training_step.py``): the
study's Diffusion Policy (``policies/diffusion.json`` with ``policy_robustness.py``'s defaults:
one 96x96 camera, ResNet-18 encoder with group norm, U-Net of 64/128/256 channels, batch 32,
one observation step, 16 actions), one AdamW update on a random batch split into the encoder's
forward, the U-Net's forward, the backward pass and the optimiser step, for the variants a
unit's time could be cut with: smaller images, channels-last tensors, batch norm,
``torch.compile`` (``--compile``: several minutes of compiling). The variants' updates are
taken in turns, so that the machine's drift falls on all of them alike.

    python benchmarks/policy_update.py [--steps 15] [--compile] [--quick] [--out FILE]

Stop other work on the machine first: the figures are wall-clock seconds of both cores.
Writes ``benchmarks/results/policy_update.json`` (``--quick``: every variant at 64 px, one
step, figures that mean nothing, under outputs/benchmarks_quick/).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the study trains (policy_robustness.py)

import policy_robustness as pr
import torch
from gensplat_sim.control import ACTION_NAMES
from gensplat_sim.world import STATE_NAMES
from machine import cpu_model, default_out, out_help

from gensplat_transforms.core.atomic import atomic_write_json

#: the study's settings (policy_robustness.py's defaults) and its policy (policies/diffusion.json)
STUDY = pr.parse_args([])
POLICY = json.loads((pr.ROOT / "policies" / "diffusion.json").read_text())["policy"]


@dataclass(frozen=True)
class Variant:
    """One way to build and run the study's policy."""

    name: str
    size: int = STUDY.size
    group_norm: bool = True
    channels_last: bool = False
    compiled: bool = False


VARIANTS = (Variant(f"the study ({STUDY.size} px)"), Variant("80 px", size=80), Variant("64 px", size=64),
            Variant("channels-last", channels_last=True), Variant("batch norm", group_norm=False))  # fmt: skip
COMPILED = Variant("torch.compile (encoder, U-Net)", compiled=True)


def build(variant: Variant, size: int):
    """The study's Diffusion Policy for ``variant`` at ``size`` px, its optimiser and a batch."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    torch.manual_seed(0)
    features = {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, size, size)) for c in STUDY.cameras}
    features["observation.state"] = PolicyFeature(FeatureType.STATE, (len(STATE_NAMES),))
    fields = {k: v for k, v in POLICY.items() if k not in ("type", "push_to_hub")}  # the study sets the rest:
    fields |= {"use_group_norm": variant.group_norm, "n_obs_steps": STUDY.n_obs_steps, "device": "cpu",
               "down_dims": tuple(int(d) for d in STUDY.down_dims.split(",")), "noise_scheduler_type": "DDIM",
               "num_inference_steps": STUDY.inference_steps, "input_features": features,
               "output_features": {"action": PolicyFeature(FeatureType.ACTION, (len(ACTION_NAMES),))}}  # fmt: skip
    config = DiffusionConfig(**fields)
    policy = DiffusionPolicy(config).train()
    batch_size, horizon = STUDY.batch_size, config.horizon
    batch = {k: torch.rand(batch_size, STUDY.n_obs_steps, *f.shape) for k, f in features.items()}
    batch |= {"action": torch.randn(batch_size, horizon, len(ACTION_NAMES)),
              "action_is_pad": torch.zeros(batch_size, horizon, dtype=torch.bool)}  # fmt: skip
    if variant.channels_last:
        policy = policy.to(memory_format=torch.channels_last)  # the weights; convolutions follow them
    encoders = list(policy.diffusion.rgb_encoder)  # one per camera (LeRobot's default)
    if variant.compiled:
        for module in [*encoders, policy.diffusion.unet]:
            module.compile()  # in place: the state dict keeps its names
    return policy, torch.optim.AdamW(policy.parameters(), lr=1e-4, weight_decay=1e-6), batch, encoders


class Timed:
    """A variant's policy, optimiser and batch, and the seconds its updates spent in each part."""

    def __init__(self, variant: Variant, size: int) -> None:
        self.variant, self.size = variant, size
        self.policy, self.optimiser, self.batch, encoders = build(variant, size)
        self.seconds = dict.fromkeys(("encoder_forward_s", "unet_forward_s", "forward_s", "backward_s", "optimiser_s"), 0.0)
        for module, part in [*((e, "encoder_forward_s") for e in encoders), (self.policy.diffusion.unet, "unet_forward_s")]:
            self._time(module, part)

    def _time(self, module, part: str) -> None:
        start = {}
        module.register_forward_pre_hook(lambda *_: start.__setitem__("t", time.perf_counter()))
        module.register_forward_hook(lambda *_: self._add(part, time.perf_counter() - start["t"]))

    def _add(self, part: str, seconds: float) -> None:
        self.seconds[part] += seconds

    def update(self) -> None:
        """One training update, its parts' seconds added up."""
        t0 = time.perf_counter()
        loss, _ = self.policy.forward(self.batch)
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        torch.nn.utils.clip_grad_norm_(self.policy.parameters(), 10.0)  # lerobot-train's default grad_clip_norm
        self.optimiser.step()
        self.optimiser.zero_grad()
        for part, seconds in (("forward_s", t1 - t0), ("backward_s", t2 - t1), ("optimiser_s", time.perf_counter() - t2)):
            self._add(part, seconds)

    def row(self, steps: int, warmup_s: float) -> dict:
        """Mean seconds per update of each part over ``steps`` updates."""
        parts = {k: v / steps for k, v in self.seconds.items()}
        v = self.variant
        return {"name": v.name, "size": self.size, "group_norm": v.group_norm, "channels_last": v.channels_last,
                "compiled": v.compiled, **parts, "update_s": parts["forward_s"] + parts["backward_s"] + parts["optimiser_s"],
                "warmup_s": warmup_s}  # fmt: skip


def measure(variants: tuple[Variant, ...], size: int | None, steps: int, warmup: int = 3) -> list[dict]:
    """Each variant's mean seconds per update (at ``size``, default its own) over ``steps``
    updates taken in turns, one of each variant per round, so that the machine's drift falls
    on every variant alike; after ``warmup`` updates each (``warmup_s``: their time, which
    includes compiling where the variant is compiled)."""
    runs, warmups = [Timed(v, size or v.size) for v in variants], []
    for run in runs:
        t = time.perf_counter()
        for _ in range(warmup):
            run.update()
        warmups.append(time.perf_counter() - t)
        run.seconds = dict.fromkeys(run.seconds, 0.0)
    for _ in range(steps):
        for run in runs:
            run.update()
    return [run.row(steps, w) for run, w in zip(runs, warmups)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=15, help="timed updates per variant, in turns (default 15)")
    parser.add_argument("--compile", action="store_true", help="also the torch.compile variant (minutes to compile)")
    parser.add_argument("--quick", action="store_true", help="seconds-long check: every variant at 64 px, one step, figures that mean nothing")
    parser.add_argument("--out", help=out_help("policy_update.json"))
    args = parser.parse_args()
    if args.steps < 1:
        parser.error(f"--steps {args.steps}: at least one timed update")
    steps, warmup, size = (1, 1, 64) if args.quick else (args.steps, 3, None)
    variants = VARIANTS + ((COMPILED,) if args.compile else ())
    rows = measure(variants, size, steps, warmup)
    print(f"{'variant':>32} {'encoder fwd':>11} {'U-Net fwd':>9} {'forward':>8} {'backward':>8} {'optimiser':>9} "
          f"{'update s':>8} {'x study':>7}")  # fmt: skip
    for row in rows:
        row["of_study"] = row["update_s"] / rows[0]["update_s"]
        print(f"{row['name']:>32} {row['encoder_forward_s']:11.3f} {row['unet_forward_s']:9.3f} {row['forward_s']:8.3f} "
              f"{row['backward_s']:8.3f} {row['optimiser_s']:9.3f} {row['update_s']:8.3f} {row['of_study']:7.2f}")  # fmt: skip
    out = Path(args.out) if args.out else default_out("policy_update.json", args.quick)
    atomic_write_json(out, {"machine": cpu_model(), "torch": torch.__version__, "threads": torch.get_num_threads(),
                            "batch_size": STUDY.batch_size, "steps": steps, "quick": args.quick, "rows": rows})  # fmt: skip
    print("wrote", out)


if __name__ == "__main__":
    main()
