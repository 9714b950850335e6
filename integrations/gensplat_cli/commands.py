"""Command-line entry point: ``gensplat <command>``."""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from dataclasses import replace
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    """The ``gensplat`` parser and its subcommands."""
    from gensplat_transforms import __version__

    parser = argparse.ArgumentParser(prog="gensplat", description="GenSplat camera-pose augmentation tools")
    parser.add_argument("--version", action="version", version=f"gensplat-transforms {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_demo_parser, _record_parser, _cache_parser, _import_depth_parser, _calibrate_parser,
                _train_model_parser, _preview_parser, _export_ply_parser):  # fmt: skip
        add(sub)
    return parser


def _demo_parser(sub) -> None:
    """``gensplat demo``: the main job on built-in data."""
    from gensplat_sim.demo import DemoConfig

    from gensplat_transforms.core.config_flags import add_flags

    demo = sub.add_parser("demo", help="the main job: simulated dataset -> Gaussian cache -> augmentation preview")
    add_flags(demo, DemoConfig)


def _record_parser(sub) -> None:
    """``gensplat record``: its flags are RecordConfig's (the sim extra)."""
    record = sub.add_parser("record", help="record scripted demonstrations of the simulated tabletop (LeRobot v3)")
    try:
        from gensplat_sim.record import add_record_flags
    except ImportError as e:  # its flags are RecordConfig's fields, which need the sim extra (MuJoCo)
        record.description = f"needs the sim extra: pip install 'gensplat-transforms[sim]' ({e})"
    else:
        add_record_flags(record)


def _cache_parser(sub) -> None:
    """``gensplat cache``: the transform's settings (GenSplatConfig's flags), the RGB-D discs' flags
    and how to build the cache."""
    from gensplat_transforms.core.config_flags import add_flags
    from gensplat_transforms.geometry.rgbd import RGBDConfig
    from gensplat_transforms.settings import add_config_arguments

    cache = sub.add_parser(
        "cache", help="write GenSplat settings beside a LeRobot dataset and build its Gaussian cache",
        description="Write GenSplat settings beside a LeRobot dataset and build its Gaussian cache. Runs as one "
                    "process, or as one of several started by torchrun or SLURM's srun, which then share the "
                    "episodes (e.g. torchrun --nproc-per-node 8 -m gensplat_cli cache ...; see "
                    "docs/cache_at_scale.md). Resumable: valid episodes are skipped.",
    )  # fmt: skip
    _dataset_arguments(cache)
    _cameras_argument(cache, "external cameras to reconstruct", "those with depth, else every external camera")
    add_config_arguments(cache)  # the transform's settings: one flag per GenSplatConfig field that has one
    _episodes_argument(cache)
    cache.add_argument("--trust-headers", dest="verify", action="store_false",
                       help="resume without reading cached data: skip every episode whose header is valid (data "
                            "checksums are still checked on every read; default: check every checksum)")
    cache.add_argument("--copy-depth", dest="link_depth", action="store_false",
                       help="rgbd: store a compressed copy of the dataset's depth (4-17 kB per timestep) instead of "
                            "linking its depth files, e.g. when the dataset is on slow network storage (default: link)")
    add_flags(cache, RGBDConfig)  # --fill-depth
    cache.add_argument("--reconstructor", choices=["rgbd", "geometry", "gensplat", "monocular"], default=None,
                       help="rgbd: the dataset's depth; geometry: depth from a Pi3-compatible model, RGB-D discs; "
                            "gensplat: the model's own Gaussian head; monocular: each image's metric depth from "
                            "MoGe-2 (--model: its checkpoint folder), RGB-D discs (default: rgbd when the cameras "
                            "have depth, else geometry)")
    cache.add_argument("--max-pixels", type=int, default=None,
                       help="geometry and gensplat: run the model on at most this many pixels per view, aspect kept "
                            "(benchmarks/geometry_resolution.py; default: geometry, the size the checkpoint was trained "
                            "at, 12544 for the shipped model, 255000 for Pi3; gensplat, the frame size)")
    cache.add_argument("--model", default=None,
                       help="weights directory or hub id of the geometry or gensplat model, e.g. a Pi3 checkpoint "
                            "(default: the shipped small model)")
    cache.add_argument("--batch-timesteps", type=int, default=None, metavar="N",
                       help="geometry: timesteps the model runs on at once (the same depth either way; capped so "
                            "that no tensor reaches 2**31 elements; default: on CUDA as many as that allows, up to "
                            "32, on the CPU 1)")


def _import_depth_parser(sub) -> None:
    """``gensplat import-depth``: one camera's recorded depth as the dataset's depth sidecars."""
    depth = sub.add_parser(
        "import-depth", help="write a camera's recorded depth (16-bit PNG, float TIFF, .npy/.npz) as the depth "
                             "sidecars of a LeRobot dataset",
        description="Read one camera's depth per episode from FROM, check it against the dataset (frames per "
                    "episode, image size, plausible distances) and write ROOT/depth/CAMERA/episode_*.safetensors, "
                    "which the rgbd reconstructor links. FROM names the episode with {episode} (e.g. "
                    "'raw/ep{episode:03d}/depth_left/*.png', 'raw/depth_left/episode_{episode}.npy'): a folder or "
                    "glob of frame images (natural order) or one (T, H, W) array. The depth must be z-depth "
                    "registered to the colour image; 0 marks no depth. The dataset's own files are not touched; "
                    "episodes whose sidecar exists are kept (--overwrite replaces them).",
    )  # fmt: skip
    _dataset_arguments(depth)
    depth.add_argument("--camera", required=True, help="the camera the depth belongs to (its image feature's name)")
    depth.add_argument("--from", dest="source", required=True, metavar="FROM",
                       help="each episode's depth, with {episode}: a folder, a glob or a .npy/.npz file")
    depth.add_argument("--units", default=None,
                       help="metres per stored value: mm, cm, m or a number (default: mm for integer data, m for "
                            "floats, refused when the median distance is implausible)")
    _episodes_argument(depth)
    depth.add_argument("--overwrite", action="store_true", help="replace existing depth sidecars")


def _calibrate_parser(sub) -> None:
    """``gensplat calibrate``: one subcommand per source of the calibration, each with its own options."""
    from gensplat_transforms.calibration.estimate import EstimateConfig
    from gensplat_transforms.core.config_flags import add_flags

    calibrate = sub.add_parser(
        "calibrate", help="store camera calibration beside a LeRobot dataset whose features carry none",
        description="Write the external cameras' intrinsics and poses to ROOT/gensplat/calibration.json (the "
                    "dataset itself is not modified), from a calibration file, from the dataset's "
                    "camera_extrinsics features, or estimated from its own frames.",
    )  # fmt: skip
    way = calibrate.add_subparsers(dest="calibrate", required=True, metavar="{" + ",".join(CALIBRATE_WAYS) + "}")
    from_file = way.add_parser(
        "from-file", help="intrinsics and poses from a calibration file",
        description="Read intrinsics and camera poses from FILE, check them against the dataset's cameras and "
                    "write ROOT/gensplat/calibration.json (the dataset itself is not modified). Conventions: "
                    "gensplat ({camera: {K | fx, fy, cx, cy, c2w, mount}}, OpenCV axes, camera-to-world), "
                    "opencv-w2c (world-to-camera R or rvec and t as from cv2.calibrateCamera/solvePnP) and "
                    "nerfstudio (transforms.json: OpenGL camera-to-world per frame, the file_path's name naming "
                    "the camera). JSON, or YAML for files ending in .yaml/.yml.",
    )  # fmt: skip
    _dataset_arguments(from_file, repo_id=None)
    from_file.add_argument("source", metavar="FILE", help="calibration file (JSON, or YAML ending in .yaml/.yml)")
    from_file.add_argument("--convention", choices=["auto", "gensplat", "opencv-w2c", "nerfstudio"], default="auto",
                           help="how FILE states the cameras; auto: nerfstudio when it has frames, opencv-w2c when "
                                "cameras have R or rvec, else gensplat (default: auto)")
    features = way.add_parser(
        "from-features", help="each external camera's pose per episode from the dataset's camera_extrinsics "
                              "features",
        description="Each external camera's pose per episode from the dataset's camera_extrinsics.<camera> "
                    "features (x, y, z, roll, pitch, yaw, as in DROID's LeRobot port; docs/lerobot.md), "
                    "intrinsics from --intrinsics, --fov or --focal.",
    )  # fmt: skip
    _dataset_arguments(features, repo_id=None)
    features.add_argument("--intrinsics", metavar="FILE", default=None,
                          help="a calibration file giving each camera's K (no poses needed)")
    add_flags(features, EstimateConfig, only=("fov_deg", "focal_px"))
    _cameras_argument(features, "the external cameras", "those with a camera_extrinsics.<camera> feature")
    estimate = way.add_parser(
        "estimate", help="the external cameras' intrinsics and poses estimated from the dataset's own frames",
        description="Estimate the external cameras' intrinsics and poses from the dataset's own frames and "
                    "depth, or without depth from a field of view or a geometry model (--model) "
                    "(docs/calibration.md).",
    )  # fmt: skip
    _dataset_arguments(estimate, repo_id="local/<root name>")
    _cameras_argument(estimate, "the external cameras, the first the reference",
                      "every colour camera whose name does not contain 'wrist'")
    add_flags(estimate, EstimateConfig)  # what the estimate is given: one flag per EstimateConfig field


def _train_model_parser(sub) -> None:
    """``gensplat train-model``: TrainConfig's flags and the data and model to train on."""
    from gensplat_transforms.core.config_flags import add_flags
    from gensplat_transforms.training import TrainConfig

    train = sub.add_parser("train-model", help="train the GenSplat model with 3D-prior distillation")

    add_flags(train, TrainConfig)  # the run's settings: one flag per TrainConfig (and LossWeights) field with one
    train.add_argument("--size", type=int, default=112, help="image side, a multiple of 14 (default: 112)")
    train.add_argument("--model", choices=["small", "full"], default="small",
                       help="small: 128 wide, 4 + 4 blocks, trains on a CPU; full: Pi3 size, about 1 B parameters "
                            "(default: small)")
    train.add_argument("--init-weights", default=None,
                       help="Pi3 (or GenSplat) model.safetensors to initialise from; its geometry parts train at "
                            "--pretrained-lr-scale x lr (default: random initialisation)")
    train.add_argument("--data", choices=["procedural", "lerobot"], nargs="+", default=["procedural"],
                       help="one or both: both mixes the samples, in proportion to the datasets' lengths "
                            "(set the procedural one with --scenes; default: procedural)")
    train.add_argument("--views", type=int, default=2, help="procedural: cameras per sample (default: 2)")
    train.add_argument("--scenes", type=int, default=None, help="procedural: distinct scenes (default: one per sample)")
    _dataset_arguments(train, when="lerobot: ")
    _cameras_argument(train, "lerobot: external cameras", "all")
    train.add_argument("--teacher", choices=["true", "pi3"], default="true",
                       help="true: the data's depth and calibration; pi3: a frozen Pi3 model (default: true)")
    train.add_argument("--teacher-weights", default=None, help="Pi3 model.safetensors for --teacher pi3 (default: none)")
    train.add_argument("--no-distill", action="store_true", help="L_rgb only (l_depth = l_3D = l_cam = 0)")


def _preview_parser(sub) -> None:
    """``gensplat preview``: what the policy gets from a dataset, as PNG and MP4."""
    preview = sub.add_parser(
        "preview", help="grid PNG and MP4 of what the policy gets from a LeRobot dataset (GenSplat forced on)",
        description="Write preview.png (original versus policy input per camera, a few perturbation draws per "
                    "frame, labelled with axis, theta and mu) and preview.mp4 (every frame of the episode) of a "
                    "LeRobot dataset opened as lerobot-train opens it, with the settings gensplat cache wrote and "
                    "augmentation forced on (probability 1). Nothing is written into the dataset.",
    )  # fmt: skip
    _dataset_arguments(preview, " (with gensplat cache's settings)")
    preview.add_argument("--episode", type=int, default=0, help="episode to show (default: 0)")
    preview.add_argument("--frames", type=int, nargs="+", default=None,
                         help="frames of the episode in the grid (default: 4 evenly spaced)")
    preview.add_argument("--draws", type=int, default=3,
                         help="perturbation draws per frame in the grid, draw d showing view d of the episode's "
                              "views_per_source (default: 3)")
    preview.add_argument("--image-transforms", action="store_true",
                         help="also apply LeRobot's 2D image transforms at their default config, after GenSplat "
                              "(as --dataset.image_transforms.enable=true does in lerobot-train)")
    preview.add_argument("--seed", type=int, default=0, help="torch seed of the draws (default: 0)")
    preview.add_argument("--out", required=True, help="output folder, outside the dataset (created; files replaced)")


def _export_ply_parser(sub) -> None:
    """``gensplat export-ply``: one cached timestep's Gaussians as a 3DGS PLY."""
    export = sub.add_parser(
        "export-ply", help="write the cached Gaussians of one timestep of a LeRobot dataset as a 3DGS PLY",
        description="Write the Gaussians GenSplat renders one timestep from as a standard 3DGS binary PLY "
                    "(opens in splat viewers). Read from the dataset's cache; an episode missing from it is built "
                    "first with the cache's reconstructor (run gensplat cache once before).",
    )  # fmt: skip
    _dataset_arguments(export, " (with gensplat cache's settings)")
    export.add_argument("--episode", type=int, required=True, help="episode index")
    export.add_argument("--frame", type=int, required=True, help="frame index within the episode")
    export.add_argument("--out", required=True, help="PLY file to write, outside the dataset (replaced when it exists)")


def _dataset_arguments(parser: argparse.ArgumentParser, root_note: str = "", *, repo_id: str | None = "",
                       when: str = "") -> None:
    """--root and --repo-id of a local LeRobot dataset, required unless ``when`` says when they
    are read (e.g. "lerobot: "); ``repo_id``: None for no --repo-id, else the default it states
    ("": required)."""
    parser.add_argument("--root", required=not when, default=None, help=f"{when}local LeRobot dataset root{root_note}")
    if repo_id is not None:
        default = f" (default: {repo_id})" if repo_id else ""
        parser.add_argument("--repo-id", required=not (when or repo_id), default=None,
                            help=f"{when}the dataset's repo id{default}")


def _cameras_argument(parser: argparse.ArgumentParser, what: str, default: str) -> None:
    """--cameras: the external cameras a command works on; ``default`` says which when not given."""
    parser.add_argument("--cameras", nargs="+", default=None, help=f"{what} (default: {default})")


def _episodes_argument(parser: argparse.ArgumentParser) -> None:
    """--episodes: only these episodes of the dataset."""
    parser.add_argument("--episodes", type=int, nargs="+", default=None, help="only these episodes (default: all)")


def main(argv: list[str] | None = None) -> int:
    """Run a command; a user mistake (:func:`_user_error`) ends as ``gensplat: error: <message>``
    on stderr with exit status 2, anything else raises."""
    argv = _current_spelling(sys.argv[1:] if argv is None else list(argv))
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    try:
        if unknown:
            message = _not_read(parser, args, unknown)
            if message is None:
                parser.parse_args(argv)  # argparse's own usage error
            raise ValueError(message)
        return _dispatch(args)
    except Exception as e:
        if not _user_error(e):
            raise
        print(f"gensplat: error: {e}", file=sys.stderr)
        return 2


#: the project's own packages: their errors are the user's to fix (:func:`_user_error`)
_OWN_PACKAGES = ("gensplat_transforms", "gensplat_lerobot", "gensplat_sim", "gensplat_cli")


def _user_error(e: Exception) -> bool:
    """A FileNotFoundError, ValueError or StaleCacheError raised by this project's own code
    (gensplat_transforms, gensplat_lerobot, gensplat_sim, gensplat_cli), whose messages say what to do."""
    from gensplat_transforms.cache.store import StaleCacheError

    if not isinstance(e, (FileNotFoundError, ValueError, StaleCacheError)):
        return False
    tb = e.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    return tb.tb_frame.f_globals.get("__name__", "").split(".")[0] in _OWN_PACKAGES


#: ``gensplat calibrate``'s subcommands, one per source of the calibration
CALIBRATE_WAYS = ("from-file", "from-features", "estimate")
#: the old spelling of each (one ``calibrate`` parser, the source an option), still understood
_OLD_CALIBRATE = {"--from": "from-file", "--from-features": "from-features", "--estimate": "estimate"}


def _current_spelling(argv: list[str]) -> list[str]:
    """``argv`` with the old ``calibrate --from FILE`` / ``--from-features`` / ``--estimate``
    rewritten as its subcommand, noting the new spelling on stderr; other argv unchanged."""
    if argv[:1] != ["calibrate"] or argv[1:2] and argv[1] in (*CALIBRATE_WAYS, "-h", "--help"):
        return argv
    old = [i for i, a in enumerate(argv) if a.split("=")[0] in _OLD_CALIBRATE]
    if len(old) != 1:
        return argv  # none, or several: argparse names what is wrong
    i = old[0]
    name, _, value = argv[i].partition("=")
    way, rest = _OLD_CALIBRATE[name], argv[1:i] + argv[i + 1:]
    if way == "from-file" and not value and i + 1 < len(argv):
        value, rest = argv[i + 1], argv[1:i] + argv[i + 2:]
    new = ["calibrate", way, *([value] if way == "from-file" and value else []), *rest]
    shown = f"{name} FILE" if way == "from-file" else name
    print(f"gensplat: note: `calibrate {shown}` is deprecated; it is now `gensplat calibrate {way}"
          f"{' FILE' if way == 'from-file' else ''}`", file=sys.stderr)
    return new


def _options_of(parser: argparse.ArgumentParser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings}


def _not_read(parser: argparse.ArgumentParser, args, unknown: list[str]) -> str | None:
    """For options one ``calibrate`` subcommand was given but does not read: which of the others
    read them (None when one of them is no option of any)."""
    if args.command != "calibrate":
        return None
    ways = next(a for a in parser._subparsers._group_actions[0].choices["calibrate"]._actions
                if isinstance(a, argparse._SubParsersAction)).choices
    given = [o.split("=")[0] for o in unknown if o.startswith("--")]
    readers = {o: [w for w in CALIBRATE_WAYS if o in _options_of(ways[w])] for o in given}
    if not given or not all(readers.values()):
        return None
    return f"calibrate {args.calibrate} does not read " + "; ".join(
        f"{o} (only {' and '.join(r)})" for o, r in readers.items())


def _dispatch(args) -> int:
    if args.command == "record":
        try:
            from gensplat_sim.record import record_from_cli
        except ImportError as e:
            raise SystemExit(f"gensplat record needs the sim extra: pip install 'gensplat-transforms[sim]' ({e})")

        root, repo_id = record_from_cli(args).root, f"gensplat/sim_{args.task}"
        print(f"repo id {repo_id}, dataset root {root}; next: gensplat cache --root {root} --repo-id {repo_id}")
    elif args.command == "calibrate" and args.calibrate == "estimate":
        _estimate(args)
    elif args.command == "calibrate" and args.calibrate == "from-features":
        from gensplat_transforms.calibration.files import calibrate_from_features
        from gensplat_transforms.data.format import calibration_path

        cameras = calibrate_from_features(args.root, args.intrinsics, args.fov_deg, args.focal_px, args.cameras)
        print(f"calibrated {', '.join(f'{n} ({len(c.episodes)} episodes)' for n, c in cameras.items())} from the "
              f"camera_extrinsics features; written to {calibration_path(args.root)} (the dataset is not modified)")  # fmt: skip
    elif args.command == "calibrate":
        from gensplat_transforms.calibration.files import calibrate
        from gensplat_transforms.data.format import calibration_path

        cameras = calibrate(args.root, args.source, args.convention)
        print(f"calibrated {', '.join(f'{n} ({c.mount})' for n, c in cameras.items())} from {args.source}; "
              f"written to {calibration_path(args.root)} (the dataset is not modified)")  # fmt: skip
    elif args.command == "import-depth":
        _import_depth(args)
    elif args.command == "demo":
        from gensplat_sim.demo import DemoConfig, run_demo

        from gensplat_transforms.core.config_flags import config_from_flags

        run_demo(config_from_flags(args, DemoConfig))
    elif args.command == "cache":
        _cache(args)
    elif args.command == "train-model":
        _train_model(args)
    elif args.command == "preview":
        _preview(args)
    elif args.command == "export-ply":
        _export_ply(args)
    return 0


def _cache(args) -> None:
    try:
        from gensplat_lerobot import LeRobotSource, load_settings, prepare
        from gensplat_lerobot.dataset import check_cameras, content_path, default_reconstructor
    except ImportError as e:
        raise SystemExit(f"gensplat cache needs the LeRobot extra: pip install 'gensplat-transforms[lerobot]' ({e})")
    from gensplat_transforms.cache.distributed import Shard, gather
    from gensplat_transforms.cache.store import size_text
    from gensplat_transforms.core.atomic import read_json_object
    from gensplat_transforms.data.format import GENSPLAT_DIR, depth_path
    from gensplat_transforms.settings import config_from_arguments

    check_cameras(args.root, args.cameras or ())
    source = LeRobotSource(args.root, args.repo_id, tuple(args.cameras) if args.cameras else None)
    cameras = source.camera_names
    config = config_from_arguments(args, cameras=cameras)
    spec = None if args.reconstructor is None else {"name": args.reconstructor}
    if args.fill_depth_px:
        if args.reconstructor not in (None, "rgbd") or not source.has_depth():
            raise ValueError("--fill-depth fills the holes of measured depth: it needs the rgbd "
                             "reconstructor and cameras with depth")  # fmt: skip
        spec = {"name": "rgbd", "config": {"fill_depth_px": args.fill_depth_px}}
    if args.reconstructor == "monocular" and (not args.model or args.max_pixels is not None):
        raise ValueError("--reconstructor monocular needs --model <MoGe-2 checkpoint folder> "
                         "(model.pt as published) and takes no --max-pixels")  # fmt: skip
    if args.model or args.max_pixels is not None:
        if args.reconstructor == "rgbd":
            raise ValueError("--model and --max-pixels need --reconstructor geometry, gensplat or "
                             "monocular")  # fmt: skip
        spec = {"name": args.reconstructor or "geometry", "model": args.model}
        if args.max_pixels is not None:
            spec["options"] = {"max_pixels": args.max_pixels}
    name = (spec or default_reconstructor(source))["name"]
    if args.batch_timesteps is not None and name != "geometry":
        raise ValueError(f"--batch-timesteps batches the geometry reconstructor's model; this cache "
                         f"uses {name} (the default where the cameras have depth; --reconstructor geometry to batch)")
    shard = Shard.from_env()
    start, cpu = time.perf_counter(), time.process_time()
    if shard.rank == 0:
        print(f"repo id {args.repo_id}, dataset root {args.root}; settings and cache in "
              f"{Path(args.root) / GENSPLAT_DIR} (found by the dataset's content, whatever repo id training uses)")
    stats = prepare(args.root, args.repo_id, config, spec, args.episodes, shard=shard, verify=args.verify,
                    link_depth=args.link_depth, batch_timesteps=args.batch_timesteps)
    ranks = gather(shard, (stats, time.perf_counter() - start, time.process_time() - cpu))
    if ranks is None:
        return
    stats = {e: s for part, _, _ in ranks for e, s in part.items()}
    built = {e: s for e, s in stats.items() if s is not None}
    size = sum(s.bytes for s in built.values())
    frames = sum(s.num_frames for s in built.values())
    seconds, cpu_s = max(r[1] for r in ranks), sum(r[2] for r in ranks)
    who = "" if len(ranks) == shard.world else f"rank {shard.rank} of {shard.world}: "
    counts = ", ".join(str(sum(s is not None for s in part.values())) for part, _, _ in ranks)
    per = "" if len(ranks) == 1 else f" [built per process: {counts}]"
    print(f"{who}cached {len(built)} episode(s) ({len(stats) - len(built)} already valid) on {len(ranks)} "
          f"process(es) in {seconds:.2f} s, {cpu_s:.2f} CPU s ({len(built) / seconds:.3f} episodes/s): "
          f"{frames} timesteps, {size_text(size)}, {size_text(size / max(frames, 1))} per timestep{per}")
    spec = load_settings(args.root)[1]
    if frames:
        print(f"path: {CACHE_PATHS.get(spec['name'], spec['name'])}; {1000 * seconds / frames:.1f} ms per timestep "
              "built (reading, depth and encoding)")  # fmt: skip
    licence = read_json_object(content_path(args.root)).get("weights_licence")  # as prepare recorded it
    if licence is not None:
        from gensplat_transforms.weights import DEFAULT_MODEL_DIR

        print(f"model weights {spec.get('model') or DEFAULT_MODEL_DIR}: licence {licence}")
    sensed = [n for n in cameras if n in source.depth_features and not depth_path(args.root, n, 0).exists()]
    if sensed and not args.fill_depth_px and spec["name"] == "rgbd":
        print(f"tip: the depth of {', '.join(sensed)} is a sensor's (LeRobot depth maps): --fill-depth 8 gives its "
              "small holes depth before the discs are built (what it gains: docs/reconstruction.md)")


#: what each reconstructor's cache is made of (``gensplat cache`` says which path built it)
CACHE_PATHS = {"rgbd": "RGB-D, the dataset's depth", "geometry": "a geometry model's depth, then RGB-D discs",
               "monocular": "MoGe-2's metric depth of each image, then RGB-D discs",
               "gensplat": "the GenSplat model's own Gaussians"}


def _train_model(args) -> None:
    from torch.utils.data import ConcatDataset

    from gensplat_transforms.core.config_flags import config_from_flags
    from gensplat_transforms.data.outputs import check_output
    from gensplat_transforms.geometry.model import ModelConfig
    from gensplat_transforms.geometry.model.data import ProceduralViews
    from gensplat_transforms.geometry.model.losses import LossWeights
    from gensplat_transforms.geometry.model.teacher import Pi3Teacher, TrueGeometryTeacher
    from gensplat_transforms.training import LOG_FILE, TrainConfig, train

    check_output(args.out, args.root, folder=True)  # against the dataset of --data lerobot
    check_output(Path(args.out) / LOG_FILE, args.root)  # appended to; the other files are replaced atomically
    loss = config_from_flags(args, LossWeights)
    if args.no_distill:
        loss = replace(loss, depth=0.0, points=0.0, camera=0.0)
    config = config_from_flags(args, TrainConfig, loss=loss)
    model_config = ModelConfig.full() if args.model == "full" else ModelConfig.small()
    datasets = []
    for kind in dict.fromkeys(args.data):
        if kind == "lerobot":
            if not (args.root and args.repo_id):
                raise ValueError("train-model --data lerobot needs --root and --repo-id")
            from gensplat_lerobot import LeRobotViews

            cameras = tuple(args.cameras) if args.cameras else None
            datasets.append(LeRobotViews(args.root, args.repo_id, args.size, cameras))
        else:
            length = args.scenes or args.steps * args.batch_size
            datasets.append(ProceduralViews(length, args.size, args.views, seed=args.seed))
    dataset = datasets[0] if len(datasets) == 1 else ConcatDataset(datasets)
    teacher = None
    if config.distills:
        if args.teacher == "pi3":
            if not args.teacher_weights:
                raise ValueError("--teacher pi3 needs --teacher-weights (Pi3 model.safetensors)")
            teacher = Pi3Teacher(args.teacher_weights)
        else:
            teacher = TrueGeometryTeacher()
    exported = train(config, model_config, dataset, teacher, args.init_weights)
    print(f"trained {args.steps} steps; EMA model written to {exported}")


def _lerobot_module(name: str, command: str):
    """``gensplat_lerobot.<name>``, or exit saying the command needs the LeRobot extra."""
    try:
        return importlib.import_module(f"gensplat_lerobot.{name}")
    except ImportError as e:
        raise SystemExit(f"gensplat {command} needs the LeRobot extra: pip install 'gensplat-transforms[lerobot]' ({e})")


def _preview(args) -> None:
    preview = _lerobot_module("training_preview", "preview").write_lerobot_preview(
        args.root, args.repo_id, args.out, episode=args.episode, frames=args.frames, draws=args.draws,
        image_transforms=args.image_transforms, seed=args.seed,
    )  # fmt: skip
    print("wrote", preview.png, preview.mp4 or "(no MP4: PyAV is not installed)")


def _estimate(args) -> None:
    from gensplat_transforms.calibration.estimate import EstimateConfig
    from gensplat_transforms.core.config_flags import config_from_flags
    from gensplat_transforms.data.format import calibration_path

    estimate = _lerobot_module("estimate", "calibrate estimate")
    repo_id = args.repo_id or f"local/{Path(args.root).name}"
    config = config_from_flags(args, EstimateConfig)
    config = replace(config, model=_model_source(config.model))
    rig = estimate.estimate_calibration(args.root, repo_id, tuple(args.cameras) if args.cameras else None, config)
    print("\n".join(estimate.report(rig)))
    print(f"estimated {', '.join(rig.names)}; written to {calibration_path(args.root)} (the dataset is not modified)")


def _model_source(model: str | None) -> str | None:
    """``--model``'s checkpoint: "shipped" is the shipped small model's directory."""
    from gensplat_transforms.weights import DEFAULT_MODEL_DIR

    return str(DEFAULT_MODEL_DIR) if model == "shipped" else model


def _import_depth(args) -> None:
    done = _lerobot_module("depth", "import-depth").import_dataset_depth(
        args.root, args.repo_id, args.camera, args.source, args.units, args.episodes, args.overwrite,
    )  # fmt: skip
    written = {e: d for e, d in done.items() if not d.skipped}
    if written:
        frames = sum(d.frames for d in written.values())
        invalid = sum(d.invalid * d.frames for d in written.values()) / frames
        medians = sorted(d.median_m for d in written.values())
        print(f"wrote the depth of {args.camera!r} for {len(written)} episode(s), {frames} frames, to "
              f"{Path(args.root) / 'depth' / args.camera}: {invalid:.1%} of pixels without depth, median distance "
              f"{medians[len(medians) // 2]:.3f} m")  # fmt: skip
    print(f"{len(done) - len(written)} episode(s) already had depth (--overwrite replaces it)")


def _export_ply(args) -> None:
    path = _lerobot_module("export", "export-ply").export_ply(args.root, args.repo_id, args.episode, args.frame, args.out)
    print("wrote", path)


if __name__ == "__main__":
    sys.exit(main())
