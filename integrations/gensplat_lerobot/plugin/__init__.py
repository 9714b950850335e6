"""Imported by ``lerobot-train`` for ``--gensplat.discover_packages_path=gensplat_lerobot.plugin``:
wraps the training dataset that ``lerobot-train`` builds with GenSplat. The evaluation
split, evaluation scripts and saved checkpoints are untouched."""

import logging
import sys

from ..dataset import enable_gensplat

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

        def make_train_eval_datasets(cfg, _original=original):
            train, evaluation = _original(cfg)
            enable_gensplat(train)
            log.info("GenSplat enabled on the training dataset: %s", train.gensplat.cfg)
            return train, evaluation

        make_train_eval_datasets.gensplat = True
        module.make_train_eval_datasets = make_train_eval_datasets


_install()
