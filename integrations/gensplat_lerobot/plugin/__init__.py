"""Imported by ``lerobot-train`` for ``--gensplat.discover_packages_path=gensplat_lerobot.plugin``:
wraps the training dataset that ``lerobot-train`` builds with GenSplat, and reports at the
log frequency how many samples it augmented and its time per sample. The evaluation split,
evaluation scripts and saved checkpoints are untouched."""

import logging
import math
import sys
from dataclasses import replace

from gensplat_transforms.cache.store import CacheError
from gensplat_transforms.core.counters import SampleCounters
from gensplat_transforms.rendering import render_size
from gensplat_transforms.settings import GenSplatConfig

from .. import batch_mode
from ..dataset import enable_gensplat, load_settings

LINE = "--gensplat.discover_packages_path=gensplat_lerobot.plugin"

log = logging.getLogger(__name__)  # propagates to the handlers lerobot-train sets up


def _install() -> None:
    targets = [m for name in ("lerobot.scripts.lerobot_train", "__main__")
               if (m := sys.modules.get(name)) is not None and hasattr(m, "make_train_eval_datasets")]  # fmt: skip
    if not targets:
        log.warning("gensplat_lerobot.plugin: not running lerobot-train; GenSplat is training-only "
                        "and does nothing here")  # fmt: skip
        return
    for module in targets:
        original = module.make_train_eval_datasets
        if getattr(original, "gensplat", False):
            continue
        run = {}  # this process's training run: the counters and cfg.log_freq

        def make_train_eval_datasets(cfg, _original=original, _run=run):
            train, evaluation = _original(cfg)
            enable_gensplat(train, *run_settings(train, cfg))
            batch_mode.attach_batch_renderer(train)  # "batch": the views are rendered by the loop's cycle
            train.gensplat.counters = SampleCounters(cfg.num_workers)  # shared before the workers start
            _run.update(counters=train.gensplat.counters, log_freq=cfg.log_freq)
            log.info(start_message(train, cfg))
            if (warning := render_warning(train, cfg)) is not None:
                log.warning(warning)
            return train, evaluation

        def update_policy(train_metrics, *args, _original=module.update_policy, _run=run, **kwargs):
            result = _original(train_metrics, *args, **kwargs)
            step, freq = train_metrics.steps + 1, _run.get("log_freq", 0)  # lerobot-train counts the step next
            accelerator = kwargs.get("accelerator")
            if "counters" in _run and freq > 0 and step % freq == 0 and getattr(accelerator, "is_main_process", True):
                log.info(progress_message(step, *_run["counters"].window()))
            return result

        make_train_eval_datasets.gensplat = True
        module.make_train_eval_datasets = make_train_eval_datasets
        module.update_policy = update_policy
        batch_mode.install(module)


def policy_input_size(policy, width: int, height: int) -> tuple[int, int] | None:
    """(width, height) at which ``policy`` (a LeRobot policy config) reads ``width x height``
    frames: Diffusion Policy's ``resize_shape`` (else the frame itself: it crops at full size),
    the aspect-keeping fit into pi0 / pi0.5's ``image_resolution`` (height, width) and
    SmolVLA's ``resize_imgs_with_padding`` (width, height), the frame for ACT; None for
    other policies."""
    kind = getattr(policy, "type", None)
    if kind == "diffusion":
        shape = getattr(policy, "resize_shape", None)
        return (shape[1], shape[0]) if shape else (width, height)
    if kind == "act":
        return width, height
    if kind in ("pi0", "pi05") and getattr(policy, "image_resolution", None):
        box_h, box_w = policy.image_resolution
    elif kind == "smolvla" and getattr(policy, "resize_imgs_with_padding", None):
        box_w, box_h = policy.resize_imgs_with_padding
    else:
        return None
    scale = min(box_h / height, box_w / width)
    return round(width * scale), round(height * scale)


def render_sizes(train, cfg) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int] | None, tuple[int, int]]:
    """(width, height) of the first replaced camera's frames, of its rendered views, of what the
    policy reads (None where unknown) and of the cached views (the frames', or a model's input
    size for a geometry or gensplat cache; read from the dataset's first episode)."""
    c = train.gensplat.cfg
    height, width = train.meta.features[c.image_key.format(name=c.replace[0])]["shape"][:2]
    policy = policy_input_size(getattr(cfg, "policy", None), width, height)
    try:
        cached = train.gensplat.cache.image_size((train.episodes or [0])[0])
    except (FileNotFoundError, CacheError):  # not cached yet: it is built at the frames' size or a model's
        cached = (width, height)
    return (width, height), render_size(width, height, c.render_scale), policy, cached


def render_warning(train, cfg) -> str | None:
    """A warning when GenSplat renders its views smaller than the policy reads them (the
    augmented samples would be blurrier than the others), else None."""
    (width, height), (w, h), policy, _ = render_sizes(train, cfg)
    if policy is None or (w >= policy[0] and h >= policy[1]):
        return None
    need = math.ceil(100 * max(policy[0] / width, policy[1] / height)) / 100
    return (f"GenSplat renders its views at {w}x{h} (render scale {train.gensplat.cfg.render_scale}), smaller than "
            f"the {policy[0]}x{policy[1]} the policy reads: augmented samples are blurrier than the others; run "
            f"`gensplat cache` with --render-scale {min(need, 1.0):g} or more")  # fmt: skip


def start_message(train, cfg) -> str:
    """The INFO block logged when training starts: what GenSplat will do to the samples."""
    tf, (cached, total) = train.gensplat, train.gensplat_cached
    c = tf.cfg
    (width, height), (w, h), policy, held_size = render_sizes(train, cfg)
    reads = "" if policy is None else f"; the policy reads {policy[0]}x{policy[1]}"
    held = "" if held_size == (width, height) else f", cached at {held_size[0]}x{held_size[1]}"
    resumed = "this run resumes a checkpoint with GenSplat on again; " if cfg.resume else ""
    return "\n".join([
        "GenSplat enabled on the training dataset:",
        f"  cache: {tf.cache.root} ({cached} of {total} episodes cached), reconstructor {tf.cache.identity}",
        f"  probability {c.probability}, level {c.level}, mode {c.mode}, cameras replaced: {', '.join(c.replace)} "
        + f"(reconstructed from {', '.join(c.cameras)})",
        f"  views rendered at {w}x{h} of {width}x{height} frames (render scale {c.render_scale}{held}){reads}",
        *smaller_render_tip((width, height), (w, h), policy),
        *depth_maps_line(train, cfg),
        f"  {resumed}a run resumed with --resume=true trains without GenSplat unless {LINE} is given again",
    ])  # fmt: skip


def depth_map_keys(train, config: GenSplatConfig | None = None) -> list[str]:
    """The depth-map features of the cameras GenSplat replaces (``<image key>_depth``), by
    ``config`` (default: the dataset's transform's)."""
    c = config or train.gensplat.cfg
    return [key for n in c.replace if (key := c.image_key.format(name=n) + "_depth") in train.meta.depth_keys]


def policy_reads_any(cfg, keys: list[str]) -> bool:
    """Whether the run's policy reads any of the features ``keys``: it does unless its
    ``input_features`` are given (on the command line or by a pretrained config) without
    them; LeRobot feeds a policy whose input features are not given every feature."""
    given = getattr(getattr(cfg, "policy", None), "input_features", None)
    return not given or any(key in given for key in keys)


def run_settings(train, cfg) -> tuple[GenSplatConfig, dict]:
    """The settings ``gensplat cache`` stored beside ``train``'s dataset, settled for the
    ``lerobot-train`` run ``cfg`` before the transform is made: where it renders
    (:func:`.batch_mode.settled_render_in`), and the replaced cameras' depth maps left as
    recorded (``depth_unit="keep"``) when the policy reads none of them (rendering them would
    cost a render per sample and camera, for maps nothing reads); and the reconstructor."""
    config, reconstructor = load_settings(train.root, train.repo_id)
    keys = depth_map_keys(train, config)
    keep = bool(keys) and not policy_reads_any(cfg, keys)
    return replace(config, render_in=batch_mode.settled_render_in(config.render_in, cfg),
                   depth_unit="keep" if keep else config.depth_unit), reconstructor  # fmt: skip


def depth_maps_line(train, cfg) -> list[str]:
    """A line of the start block naming the replaced cameras' depth-map features and what
    becomes of them; none without such features."""
    keys = depth_map_keys(train)
    if not keys:
        return []
    if not policy_reads_any(cfg, keys):
        return [f"  depth maps {', '.join(keys)} kept as recorded: the policy does not read them (its input_features)"]
    if train.gensplat.cfg.depth_unit == "keep":
        return [f"  depth maps {', '.join(keys)} kept as recorded (--keep-depth-maps): they do not follow the moves"]
    return [f"  depth maps {', '.join(keys)} rendered at the new poses too, in {train.gensplat.cfg.depth_unit}"]


def smaller_render_tip(frame: tuple[int, int], rendered: tuple[int, int], policy: tuple[int, int] | None) -> list[str]:
    """A line of the start block where the views are rendered with at least twice the pixels
    the policy reads (render time grows with them): the render scale that renders what it
    reads. No line otherwise."""
    if policy is None or rendered[0] * rendered[1] < 2 * policy[0] * policy[1]:
        return []
    scale = math.ceil(100 * max(policy[0] / frame[0], policy[1] / frame[1])) / 100
    smaller = render_size(*frame, scale)
    fewer = rendered[0] * rendered[1] / (smaller[0] * smaller[1])
    tip = (f"  `gensplat cache` with --render-scale {scale:g} renders what the policy reads, {smaller[0]}x{smaller[1]}: "
           f"{fewer:.1f}x fewer pixels a view (render time falls about in proportion)")  # fmt: skip
    return [tip]


def progress_message(step: int, samples: int, augmented: int, seconds: float) -> str:
    """The INFO line logged every ``cfg.log_freq`` steps: what the workers made since the last
    one (samples made ahead of the loop, up to its prefetch, count when they are made)."""
    if samples == 0:
        return f"GenSplat step {step}: no samples made since the last report (the workers are ahead)"
    return (f"GenSplat step {step}: {augmented} of {samples} samples augmented ({augmented / samples:.0%}), "
            f"{seconds / samples * 1e3:.1f} ms per sample in the workers")  # fmt: skip


_install()
