"""Training the GenSplat model: loss goes down, resume, EMA, schedule, teachers, shipped weights."""

import itertools
import json
import math

import numpy as np
import pytest
import torch
from gensplat_cli import main as cli_main
from safetensors.torch import save_file
from tiny_model import TINY

from gensplat_transforms.data.scenes import WORKSPACE_CENTER
from gensplat_transforms.geometry import GenSplatReconstructor, Views
from gensplat_transforms.geometry.model import GenSplatModel, ModelConfig
from gensplat_transforms.geometry.model.data import ProceduralViews, RigConfig
from gensplat_transforms.geometry.model.losses import LossWeights
from gensplat_transforms.geometry.model.teacher import Pi3Teacher, TrueGeometryTeacher, camera_points
from gensplat_transforms.training import (
    CHECKPOINT_FILE,
    EXPORT_DIR,
    LOG_FILE,
    TrainConfig,
    Trainer,
    ema_model,
    lr_factor,
    pretrained_names,
)
from gensplat_transforms.weights import DEFAULT_MODEL_DIR

SIZE = 28  # 2 x 2 patches, above the 11-pixel SSIM window


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny models run fastest on one thread (and suffer most from oversubscribed cores)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_trainer(out, steps=4, dataset=None, seed=0, **overrides) -> Trainer:
    torch.manual_seed(seed)
    model = GenSplatModel(TINY)
    settings = {"batch_size": 2, "warmup_steps": 2, "log_every": 1, "save_every": 100, **overrides}
    config = TrainConfig(out=out, steps=steps, **settings)
    dataset = dataset or ProceduralViews(8, SIZE, 2, seed=3)
    return Trainer(model, dataset, TrueGeometryTeacher(), config)


def states_close(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.allclose(a[k].float(), b[k].float(), atol=1e-6) for k in a)


# ---------------------------------------------------------------- training
def test_a_few_steps_lower_the_loss_on_a_tiny_batch(tmp_path):
    data = ProceduralViews(2, SIZE, 2, seed=1)
    trainer = tiny_trainer(tmp_path, steps=30, dataset=data, lr=2e-3, warmup_steps=1, ema_decay=0.0)
    batch = [data[0], data[1]]
    with torch.no_grad():
        before = trainer.losses(batch, 0)
    for _ in range(30):
        stats = trainer.train_step()
        assert all(math.isfinite(v) for v in stats.values())
    with torch.no_grad():
        after = trainer.losses(batch, 0)
    assert after["total"] < 0.7 * before["total"], (before, after)
    assert after["points"] < before["points"] and after["cam_rot"] < before["cam_rot"]


def test_bf16_autocast_step_is_finite(tmp_path):
    stats = tiny_trainer(tmp_path, bf16=True, grad_checkpointing=True).train_step()
    assert stats["skipped"] == 0 and all(math.isfinite(v) for v in stats.values())


def test_without_distillation_needs_no_teacher_and_skips_its_terms(tmp_path):
    torch.manual_seed(0)
    config = TrainConfig(out=tmp_path, steps=2, batch_size=1, loss=LossWeights(depth=0, points=0, camera=0),
                         render_views=1, render_crop=21)  # fmt: skip
    trainer = Trainer(GenSplatModel(TINY), ProceduralViews(2, SIZE, 2), None, config)
    stats = trainer.train_step()
    assert set(stats) >= {"rgb", "total"} and not {"points", "cam_rot", "depth"} & set(stats)
    assert stats["total"] == pytest.approx(stats["rgb"])
    with pytest.raises(ValueError, match="teacher"):
        Trainer(GenSplatModel(TINY), ProceduralViews(2, SIZE, 2), None, TrainConfig(out=tmp_path))


def test_geometry_only_training_renders_nothing(tmp_path, monkeypatch):
    import gensplat_transforms.training as train_module

    monkeypatch.setattr(train_module, "render", None)  # would fail if called
    trainer = tiny_trainer(tmp_path, loss=LossWeights(l1=0, perceptual=0, depth=0))
    stats = trainer.train_step()
    assert {"points", "cam_rot", "cam_trans"} <= set(stats) and "rgb" not in stats and "depth" not in stats
    with pytest.raises(ValueError, match="positive loss weight"):
        TrainConfig(out=tmp_path, loss=LossWeights(l1=0, perceptual=0, depth=0, points=0, camera=0))


def test_resume_from_checkpoint_gives_the_same_state(tmp_path):
    straight = tiny_trainer(tmp_path / "a", steps=4)
    straight.fit(progress=False)

    first = tiny_trainer(tmp_path / "b", steps=4)
    first.train_step()
    first.train_step()
    first.save()
    resumed = tiny_trainer(tmp_path / "b", steps=4, seed=123)  # other init: the checkpoint must win
    exported = resumed.fit(progress=False)

    assert resumed.step == straight.step == 4
    assert states_close(resumed.model.state_dict(), straight.model.state_dict())
    assert states_close(resumed.ema.module.state_dict(), straight.ema.module.state_dict())
    assert resumed.scheduler.get_last_lr() == straight.scheduler.get_last_lr()
    sa, sb = straight.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
    assert all(torch.allclose(sa[i]["exp_avg_sq"], sb[i]["exp_avg_sq"], atol=1e-8) for i in sa)
    # the run directory: log lines for every step of both parts, atomic checkpoint, EMA export
    assert len((tmp_path / "b" / LOG_FILE).read_text().splitlines()) == 2
    assert (tmp_path / "b" / CHECKPOINT_FILE).is_file() and not list((tmp_path / "b").glob(".checkpoint-*"))
    assert exported == tmp_path / "b" / EXPORT_DIR
    loaded = GenSplatModel.from_pretrained(exported)
    assert states_close(loaded.state_dict(), resumed.ema.module.state_dict())


def test_checkpoint_of_another_model_size_is_refused(tmp_path):
    tiny_trainer(tmp_path).save()
    other = ModelConfig(**{**TINY.to_dict(), "dim": 64, "head_dim": 64, "head_out_dim": 64})
    trainer = Trainer(GenSplatModel(other), ProceduralViews(2, SIZE, 2), TrueGeometryTeacher(),
                      TrainConfig(out=tmp_path, steps=1))  # fmt: skip
    with pytest.raises(ValueError, match="another model configuration"):
        trainer.fit(progress=False)


class _RunsCode:
    """Unpickling this calls ``open(marker, "w")``: a stand-in for any code a crafted file runs."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def test_crafted_checkpoint_is_refused_without_running_code(tmp_path):
    marker = tmp_path / "code_ran"
    trainer = tiny_trainer(tmp_path)
    state = trainer.state_dict()
    torch.save({**state, "step": _RunsCode(marker)}, tmp_path / CHECKPOINT_FILE)
    with pytest.raises(ValueError, match=r"checkpoint.pt: refused to load"):
        trainer.fit(progress=False)
    assert not marker.exists()
    (tmp_path / CHECKPOINT_FILE).write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="refused to load"):
        trainer.fit(progress=False)
    torch.save({"model": state["model"]}, tmp_path / CHECKPOINT_FILE)  # tensors, but incomplete
    with pytest.raises(ValueError, match="not a training checkpoint"):
        trainer.fit(progress=False)


def test_ema_differs_from_the_raw_weights_and_follows_them(tmp_path):
    trainer = tiny_trainer(tmp_path, steps=6, ema_decay=0.9)
    shadow = trainer.ema.module.state_dict()  # tensors updated in place
    initial = {k: v.clone() for k, v in shadow.items()}
    for _ in range(3):
        trainer.train_step()
    raw = trainer.model.state_dict()
    key = "camera_head.fc_t.weight"
    assert not torch.allclose(shadow[key], raw[key])  # lags behind
    assert not torch.allclose(shadow[key], initial[key])  # but moved
    # its distance to the raw weights shrinks when the raw weights stop moving
    gap = (shadow[key] - raw[key]).norm()
    for _ in range(20):
        trainer.ema.update_parameters(trainer.model)
    assert (shadow[key] - raw[key]).norm() < 0.5 * gap
    assert int(trainer.ema.n_averaged) == 24  # the starting weights and 23 updates


def test_ema_copy_and_state_round_trip():
    torch.manual_seed(0)
    model = GenSplatModel(TINY)
    ema = ema_model(model, 0.5)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    ema.update_parameters(model)
    other = ema_model(GenSplatModel(TINY), 0.9)
    other.load_state_dict(ema.state_dict())
    assert int(other.n_averaged) == 2 and states_close(other.module.state_dict(), ema.module.state_dict())
    assert not states_close(ema.module.state_dict(), model.state_dict())


# ---------------------------------------------------------------- schedule and groups
def test_lr_schedule_warms_up_linearly_then_decays_by_cosine():
    f = [lr_factor(s, warmup=10, total=110, min_ratio=0.1) for s in range(111)]
    assert f[0] == pytest.approx(0.1) and f[4] == pytest.approx(0.5) and f[9] == pytest.approx(1.0)
    assert all(a < b for a, b in itertools.pairwise(f[:10]))  # rising warm-up
    assert f[10] == pytest.approx(1.0) and f[60] == pytest.approx(0.55)  # cosine midpoint
    assert all(a >= b for a, b in itertools.pairwise(f[10:]))  # non-increasing afterwards
    assert f[110] == pytest.approx(0.1) and lr_factor(500, 10, 110, 0.1) == pytest.approx(0.1)


@pytest.mark.filterwarnings("ignore:Detected call of:UserWarning")
def test_pretrained_parameters_get_a_tenth_of_the_learning_rate(tmp_path):
    torch.manual_seed(1)
    pi3 = {k: v for k, v in GenSplatModel(TINY).state_dict().items() if not k.startswith("gaussian_head.")}
    save_file(pi3, str(tmp_path / "pi3.safetensors"))
    model = GenSplatModel(TINY)
    names = pretrained_names(model, tmp_path / "pi3.safetensors")
    assert names and all(not n.startswith("gaussian_head.") for n in names)
    assert {n for n, _ in model.named_parameters() if n.startswith("gaussian_head.")}.isdisjoint(names)
    torch.testing.assert_close(model.state_dict()["register_token"], pi3["register_token"])
    # a whole GenSplat checkpoint as init (e.g. a geometry-only run): its Gaussian head stays "new"
    save_file(GenSplatModel(TINY).state_dict(), str(tmp_path / "gensplat.safetensors"))
    assert pretrained_names(GenSplatModel(TINY), tmp_path / "gensplat.safetensors") == names

    config = TrainConfig(out=tmp_path, steps=20, lr=1e-3, warmup_steps=5)
    trainer = Trainer(model, ProceduralViews(2, SIZE, 2), TrueGeometryTeacher(), config, names)
    groups = {g["name"]: g for g in trainer.optimizer.param_groups}
    assert set(groups) == {"pretrained/decay", "pretrained/no_decay", "new/decay", "new/no_decay"}
    ids = {id(p) for n in ("pretrained/decay", "pretrained/no_decay") for p in groups[n]["params"]}
    assert ids == {id(p) for n, p in model.named_parameters() if n in names}
    for _ in range(7):
        trainer.scheduler.step()
    factor = lr_factor(7, 5, 20, config.min_lr_ratio)
    assert groups["new/decay"]["lr"] == pytest.approx(1e-3 * factor)
    assert groups["pretrained/decay"]["lr"] == pytest.approx(1e-4 * factor)
    assert groups["new/no_decay"]["weight_decay"] == 0 and groups["new/decay"]["weight_decay"] > 0


# ---------------------------------------------------------------- teachers and data
def test_true_geometry_teacher_returns_camera_frame_points_and_poses():
    views = ProceduralViews(1, SIZE, 3, seed=5)[0]
    points, poses = TrueGeometryTeacher().geometry(views)
    assert points.shape == (3, SIZE, SIZE, 3) and poses.shape == (3, 4, 4)
    torch.testing.assert_close(points[..., 2], views.depths[:, 0])
    # back in the world, the teacher's points are the cameras' unprojected depth
    world = points.reshape(3, -1, 3) @ poses[:, :3, :3].transpose(1, 2) + poses[:, None, :3, 3]
    cams = views.cameras
    expected = cams.unproject(
        cams.pixel_centers()[None].expand(3, -1, -1), views.depths.reshape(3, -1).double()
    )
    torch.testing.assert_close(world, expected.float(), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="depth"):
        TrueGeometryTeacher().geometry(Views(views.images, views.cameras))


def test_camera_points_zero_out_invalid_depth():
    depth = torch.tensor([[[[1.0, 0.0], [float("nan"), -2.0]]]])
    K = torch.tensor([[[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]]])
    pts = camera_points(depth, K)
    torch.testing.assert_close(pts[0, 0, 0], torch.tensor([-0.25, -0.25, 1.0]))
    assert (pts[0].reshape(-1, 3)[1:] == 0).all()


def test_pi3_teacher_wraps_a_model_loaded_from_a_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError):
        Pi3Teacher(tmp_path / "missing.safetensors", config=TINY)
    torch.manual_seed(2)
    source = GenSplatModel(TINY)
    save_file(source.state_dict(), str(tmp_path / "model.safetensors"))
    teacher = Pi3Teacher(tmp_path, config=TINY)
    assert teacher.metric is False and not any(p.requires_grad for p in teacher.model.parameters())
    views = ProceduralViews(1, SIZE, 2)[0]
    points, poses = teacher.geometry(views)
    assert points.shape == (2, SIZE, SIZE, 3) and poses.shape == (2, 4, 4)
    with torch.no_grad():
        expected = source.eval()(views.images[None])
    torch.testing.assert_close(points, expected["local_points"][0])
    torch.testing.assert_close(poses, expected["camera_poses"][0])
    # a checkpoint without the geometry (here: only the Gaussian head) is refused
    save_file({k: v for k, v in source.state_dict().items() if k.startswith("gaussian_head.")},
              str(tmp_path / "partial.safetensors"))  # fmt: skip
    with pytest.raises(ValueError, match="not a complete Pi3"):
        Pi3Teacher(tmp_path / "partial.safetensors", config=TINY)


def test_pi3_teacher_trains_with_scale_alignment(tmp_path):
    torch.manual_seed(2)
    save_file(GenSplatModel(TINY).state_dict(), str(tmp_path / "model.safetensors"))
    trainer = tiny_trainer(tmp_path / "run")
    trainer.teacher = Pi3Teacher(tmp_path, config=TINY)
    stats = trainer.train_step()
    assert all(math.isfinite(v) for v in stats.values())


def test_procedural_views_are_deterministic_and_varied():
    data = ProceduralViews(4, SIZE, 2, seed=7)
    a, b, c = data[1], data[1], data[2]
    assert torch.equal(a.images, b.images) and torch.equal(a.cameras.c2w, b.cameras.c2w)
    assert not torch.allclose(a.cameras.c2w, c.cameras.c2w)
    assert a.images.shape == (2, 3, SIZE, SIZE) and a.depths.shape == (2, 1, SIZE, SIZE)
    assert (a.depths > 0).all()  # the rig stays inside the room
    with pytest.raises(IndexError):
        data[4]
    with pytest.raises(ValueError, match="multiple of 14"):
        ProceduralViews(4, 30)


def test_rig_cameras_respect_the_azimuth_range_and_separation():
    rig = RigConfig(target_jitter=0.0)
    rng = np.random.default_rng(0)
    for _ in range(10):
        cams = rig.sample(rng, 3, 28)
        offset = cams.centers - torch.tensor(WORKSPACE_CENTER, dtype=torch.float64)
        azimuth = torch.rad2deg(torch.atan2(offset[:, 1], offset[:, 0])).sort().values
        assert rig.azimuth[0] <= azimuth.min() and azimuth.max() <= rig.azimuth[1]
        assert azimuth.diff().min() >= rig.min_separation - 1e-6
        looking_at_target = -offset / offset.norm(dim=-1, keepdim=True)
        torch.testing.assert_close(cams.forward, looking_at_target)


def test_resized_views_keep_intrinsics_consistent():
    views = ProceduralViews(1, 56, 2)[0]
    small = views.resized(42, 28)
    assert small.images.shape == (2, 3, 28, 42) and small.depths.shape == (2, 1, 28, 42)
    assert (small.cameras.width, small.cameras.height) == (42, 28)
    torch.testing.assert_close(small.cameras.K[:, 0, 0], views.cameras.K[:, 0, 0] * 42 / 56)
    assert views.resized(56, 56) is views


def test_lerobot_views_train_with_the_recorded_geometry(scene_dataset, dataset_copy, tmp_path, monkeypatch):
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    from gensplat_lerobot import LeRobotViews

    dataset_copy(scene_dataset("local/t", episodes=1, frames=3, size=42))
    data = LeRobotViews(tmp_path / "ds", "local/t", size=SIZE)
    assert len(data) == 3
    views = data[2]
    assert views.images.shape == (2, 3, SIZE, SIZE) and views.depths.shape == (2, 1, SIZE, SIZE)
    assert views.cameras.width == SIZE and (views.depths > 0).all()
    stats = tiny_trainer(tmp_path / "run", dataset=data).train_step()
    assert all(math.isfinite(v) for v in stats.values())


# ---------------------------------------------------------------- CLI
def test_cli_trains_and_exports(tmp_path):
    out = tmp_path / "run"
    args = ["train-model", "--out", str(out), "--steps", "2", "--batch-size", "1", "--size", "28",
            "--render-views", "1", "--warmup", "1", "--log-every", "1"]  # fmt: skip
    assert cli_main(args) == 0
    lines = [json.loads(s) for s in (out / LOG_FILE).read_text().splitlines()]
    assert [r["step"] for r in lines] == [1, 2]
    assert {"rgb", "points", "cam_rot", "total", "lr"} <= set(lines[0])
    model = GenSplatModel.from_pretrained(out / EXPORT_DIR)
    assert model.config == ModelConfig.small()
    assert model.max_pixels == 28 * 28  # the size it was trained at: the geometry path keeps to it


def test_cli_mixes_procedural_and_lerobot_data(scene_dataset, dataset_copy, tmp_path, monkeypatch):
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    from gensplat_transforms import training as train_module

    dataset_copy(scene_dataset("local/t", episodes=1, frames=3, size=42))
    seen = {}

    def capture(config, model_config, dataset, teacher=None, init_weights=None, progress=True):
        seen["dataset"] = dataset
        return tmp_path

    monkeypatch.setattr(train_module, "train", capture)
    args = ["train-model", "--out", str(tmp_path / "run"), "--steps", "2", "--size", "28", "--data", "procedural",
            "lerobot", "--scenes", "5", "--root", str(tmp_path / "ds"), "--repo-id", "local/t"]  # fmt: skip
    assert cli_main(args) == 0
    data = seen["dataset"]
    assert len(data) == 5 + 3 and [len(d) for d in data.datasets] == [5, 3]
    assert data[0].images.shape == data[7].images.shape == (2, 3, 28, 28)


# ---------------------------------------------------------------- shipped weights
def test_shipped_default_weights_load_and_give_finite_output():
    model = GenSplatModel.from_pretrained(DEFAULT_MODEL_DIR)
    assert model.config == ModelConfig.small()
    views = ProceduralViews(1, 112, 2, seed=10_000)[0]
    with torch.no_grad():
        out = model(views.images[None])
    assert all(torch.isfinite(v).all() for v in out.values())
    assert (out["local_points"][..., 2] > 0).all()


def test_reconstructor_defaults_to_the_shipped_weights():
    recon = GenSplatReconstructor()
    shipped = GenSplatModel.from_pretrained(DEFAULT_MODEL_DIR)
    assert states_close(recon.model.state_dict(), shipped.state_dict())
    views = ProceduralViews(1, 112, 2, seed=10_001)[0]
    result = recon(Views(views.images, views.cameras))
    assert len(result.gaussians) == 2 * 112 * 112 and torch.isfinite(result.gaussians.means).all()
