"""The main job on built-in data: record a small simulated dataset (or reuse it), build
its Gaussian cache, write a preview of the online augmentation, and compare rendered
views with the simulator's truth at every perturbation level."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from gensplat_transforms.cache.store import size_text
from gensplat_transforms.core.atomic import atomic_write_json
from gensplat_transforms.core.config_flags import flag
from gensplat_transforms.core.images import save_grid
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.data.format import GENSPLAT_DIR
from gensplat_transforms.data.outputs import check_output
from gensplat_transforms.rendering.preview import write_preview
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform, render_view
from gensplat_transforms.views.perturbation import EVAL_LEVELS, PaperSampler

#: the simulated dataset's repo id, as ``gensplat record`` names it and ``policies/*.json`` use it
REPO_ID = "gensplat/sim_pick_place"


@dataclass
class DemoConfig:
    """Settings of :func:`run_demo`, each a flag of ``gensplat demo``
    (:mod:`gensplat_transforms.core.config_flags`).

    Attributes:
        out: output folder; it holds the recorded dataset, its cache and the previews.
        episodes: pick-and-place demonstrations to record.
        size: side of the square camera images, pixels.
        seed: seed of the recording and of the perturbations shown.
        backend: render backend of the previews.
    """

    out: str | Path = field(default="outputs/demo", metadata=flag("output folder", type=str))
    episodes: int = field(default=2, metadata=flag("demonstrations to record"))
    size: int = field(default=224, metadata=flag("image size in pixels"))
    seed: int = field(default=0, metadata=flag("seed of the recording and the perturbations"))
    backend: str = field(default="fast", metadata=flag("render backend"))


def run_demo(config: DemoConfig | None = None, log=print) -> dict:
    """Write ``sim_dataset/`` (unless present), ``preview.png``/``preview.mp4``,
    ``levels.png`` and ``demo.json`` to ``config.out`` (a folder: :func:`.outputs.check_output`);
    return the summary."""
    config = DemoConfig() if config is None else config
    episodes, size, seed = config.episodes, config.size, config.seed
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from gensplat_lerobot import enable_gensplat, prepare, video_backend
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from .record import RecordConfig, record
    from .truth import GroundTruth
    from .world import WorldConfig

    out_dir = check_output(config.out, folder=True)
    root = out_dir / "sim_dataset"
    summary: dict = {"dataset": str(root)}
    if (root / "meta" / "info.json").exists():
        log(f"using the simulated dataset already at {root}")
    else:
        t0 = time.perf_counter()
        res = record(RecordConfig(root, "pick_place", episodes, seed, use_videos=False, repo_id=REPO_ID,
                                  world=WorldConfig(width=size, height=size)))  # fmt: skip
        log(f"recorded {res.episodes} pick-and-place demonstrations ({res.frames} timesteps, 3 cameras "
            f"{size}x{size}, RGB + depth) in {time.perf_counter() - t0:.0f} s")
    log(f"repo id {REPO_ID}, dataset root {root}; GenSplat settings and cache in {root / GENSPLAT_DIR}")
    t0 = time.perf_counter()
    stats = prepare(root, REPO_ID, GenSplatConfig(backend=config.backend))  # the training settings
    built = [s for s in stats.values() if s is not None]
    if built:
        per_step = sum(s.bytes for s in built) / sum(s.num_frames for s in built)
        summary["cache_bytes_per_timestep"] = round(per_step)
        log(f"cached Gaussians of {len(built)} episode(s) in {time.perf_counter() - t0:.0f} s, "
            f"{size_text(per_step)} per timestep")

    dataset = enable_gensplat(LeRobotDataset(REPO_ID, root=root, video_backend=video_backend()))
    tf = dataset.gensplat
    preview_tf = GenSplatTransform(GenSplatConfig(**{**tf.cfg.__dict__, "probability": 1.0, "level": "large",
                                                     "views_per_source": 1}), tf.cache, tf.source)  # fmt: skip
    length = int(dataset.meta.episodes["length"][0])
    items = [LeRobotDataset.__getitem__(dataset, i) for i in range(length)]
    paths = write_preview(items, preview_tf, list(tf.cfg.cameras), out_dir)
    log("wrote " + " and ".join(str(p) for p in paths.values()))

    summary["levels"] = _levels(tf, GroundTruth(root), items[length // 2], out_dir / "levels.png", log)
    atomic_write_json(out_dir / "demo.json", summary)
    log(f"wrote {out_dir / 'levels.png'} and {out_dir / 'demo.json'}")
    log(f"train on it with GenSplat: bash policies/train.sh diffusion gensplat --dataset.root={root} "
        f"(policies/*.json use repo id {REPO_ID})")
    return summary


def _levels(tf: GenSplatTransform, truth, item: dict, path: Path, log) -> dict:
    """Perturb the first external camera at every level; compare with the simulator."""
    ep, fr = int(item["episode_index"]), int(item["frame_index"])
    rec = tf.cache.read(ep, fr, tf.source.views(ep, fr).images)
    rows, labels, out = [], [], {}
    for level in EVAL_LEVELS:
        p = PaperSampler(level, seed=tf.cfg.seed).sample(ep)
        target = p.move(rec.cameras, 0)
        true_rgb, _ = truth.render(ep, fr, target)
        t0 = time.perf_counter()
        res = render_view(rec, target, tf.cfg)
        ms = (time.perf_counter() - t0) * 1e3
        seen = res.alpha > 0.5
        score = psnr(res.rgb, true_rgb, seen)
        out[level] = {**p.as_dict(), "psnr_db": round(score, 2), "coverage": round(float(seen.float().mean()), 4),
                      "render_ms": round(ms, 1)}  # fmt: skip
        log(f"{level:>8}: rotate {p.theta_deg:+6.1f} deg about world {p.axis}, forward {p.mu_m * 100:4.1f} cm"
            f" -> PSNR {score:5.2f} dB against the simulator over {float(seen.float().mean()):.1%} of pixels,"
            f" {ms:.0f} ms")
        source = item[tf.cfg.image_key.format(name=tf.cfg.cameras[0])]
        source = source.float() / 255 if source.dtype == torch.uint8 else source
        rows.append([source, true_rgb[0], res.rgb[0], (res.rgb[0] - true_rgb[0]).abs() * 4])
        labels.append(f"{level}\n{p.theta_deg:+.1f} deg {p.axis}\n{p.mu_m * 100:.1f} cm")
    save_grid(rows, path, labels, ["source view", "simulator at new pose", "GenSplat render", "|error| x4"])
    return out
