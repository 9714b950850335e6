"""MjSpec composition of the tabletop: Franka Panda + Robotiq 2F-85, table, room, objects,
lights and cameras.

World frame: Z up, metres. The robot base stands on the table top (the plane z = 0) at the
origin and faces +x; objects live in the workspace ``WORKSPACE_LOW .. WORKSPACE_HIGH``.
The robot assets (MuJoCo Menagerie meshes) come from the ``gym-hil`` wheel, which ships
them offline; only its files are read, the package is never imported.

The arm's torque motors are replaced by joint position servos with gravity compensation,
so a controller only has to send joint targets (see :mod:`.control`).
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

#: Table top rectangle where objects are placed: (x, y) low and high corners, metres.
WORKSPACE_LOW = (0.38, -0.22)
WORKSPACE_HIGH = (0.66, 0.22)
#: Panda ready pose (7 joints, radians): gripper pointing down above the workspace.
HOME_QPOS = (0.0, -0.35, 0.0, -2.3, 0.0, 1.95, math.pi / 4)
#: Joint servo gains (kp, kv) and torque limits, shoulder (joints 1-4) and wrist (5-7).
_ARM_GAINS = ((4500.0, 450.0, 87.0),) * 4 + ((2000.0, 200.0, 12.0),) * 3
_ARM_BODIES = ("link1", "link2", "link3", "link4", "link5", "link6", "link7")


@dataclass(frozen=True)
class ObjectSpec:
    """A free rigid object on the table.

    Attributes:
        name: body and geom name.
        shape: "box", "cylinder" (upright) or "sphere".
        size: MuJoCo half sizes: box (hx, hy, hz), cylinder (radius, half height), sphere (radius,).
        mass: kilograms.
    """

    name: str
    shape: str
    size: tuple[float, ...]
    mass: float = 0.1

    @property
    def half_height(self) -> float:
        return self.size[-1]


@dataclass(frozen=True)
class CameraSpec:
    """A static camera looking from ``eye`` at ``target`` (world, metres); ``fovy`` in degrees."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fovy: float = 55.0


@dataclass
class SceneConfig:
    """Scene layout.

    Attributes:
        external: the static cameras by name (the dataset's ``left`` and ``right``).
        wrist_fovy: vertical field of view of the wrist camera, degrees.
        max_image_size: side of the offscreen framebuffer (largest renderable image).
        texture_seed: seed of the procedural table and wall textures (fixed per dataset).
    """

    external: dict[str, CameraSpec] = field(
        default_factory=lambda: {
            "left": CameraSpec((1.05, 0.40, 0.50), (0.45, 0.0, 0.12)),
            "right": CameraSpec((1.05, -0.40, 0.50), (0.45, 0.0, 0.12)),
        }
    )
    wrist_fovy: float = 75.0
    max_image_size: int = 1024
    texture_seed: int = 0


def robot_assets_dir() -> Path:
    """Folder with gym-hil's ``panda.xml`` (Franka Panda + Robotiq 2F-85, Menagerie meshes)."""
    spec = importlib.util.find_spec("gym_hil")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(
            "the simulated world needs gym-hil for its robot assets: pip install 'gensplat-transforms[sim]'"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "assets"
    if not (path / "panda.xml").is_file():
        raise FileNotFoundError(f"gym-hil is installed but {path / 'panda.xml'} is missing")
    return path


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternion of a (3, 3) rotation."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.asarray(R, dtype=np.float64).reshape(-1))
    return quat


def look_at_quat(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """MuJoCo camera quaternion (w, x, y, z) at ``eye`` looking at ``target`` with image-up ``up``.

    MuJoCo cameras look along their -z axis with +y up (the OpenGL convention).
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    return mat_to_quat(np.stack([right, np.cross(back, right), back], axis=1))


def _noise_texture(rng: np.random.Generator, size: int, octaves: int = 5) -> np.ndarray:
    """(size, size) smooth value noise in [0, 1] (sum of bilinearly upsampled random grids)."""
    out = np.zeros((size, size))
    for o in range(octaves):
        n = 4 * 2**o
        grid = rng.random((n + 1, n + 1))
        t = np.linspace(0, n, size, endpoint=False)
        i = t.astype(int)
        f = t - i
        rows = grid[i] * (1 - f)[:, None] + grid[i + 1] * f[:, None]
        out += (rows[:, i] * (1 - f) + rows[:, i + 1] * f) / 2**o
    out -= out.min()
    return out / out.max()


def _wood_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """(size, size, 3) uint8 planks with grain."""
    noise = _noise_texture(rng, size)
    y, x = np.mgrid[0:size, 0:size] / size
    grain = 0.5 + 0.5 * np.sin(2 * math.pi * (12 * x + 3.0 * noise))
    plank = (np.floor(y * 6) % 2) * 0.08 + (np.abs((y * 6) % 1 - 0.5) > 0.48) * -0.25
    shade = np.clip(0.6 + 0.15 * grain + 0.2 * noise + plank, 0, 1)
    base = np.array([0.60, 0.45, 0.32])
    return (255 * shade[..., None] * base / base.max()).astype(np.uint8)


def _wall_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """(size, size, 3) uint8 plaster with coloured blotches (gives the background detail)."""
    a, b, c = (_noise_texture(rng, size) for _ in range(3))
    rgb = np.stack([0.55 + 0.3 * a, 0.55 + 0.25 * b, 0.5 + 0.3 * c], -1) * (0.75 + 0.25 * a[..., None])
    return (255 * np.clip(rgb, 0, 1)).astype(np.uint8)


def _add_texture(spec: mujoco.MjSpec, name: str, image: np.ndarray, repeat: tuple[float, float]) -> str:
    tex = spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D)
    tex.width, tex.height, tex.nchannel = image.shape[1], image.shape[0], 3
    tex.data = image.tobytes()
    mat = spec.add_material(name=name)
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
    mat.texrepeat = repeat
    mat.texuniform = True
    mat.reflectance = 0.15 if name == "table" else 0.0
    return name


def _servo_arm(spec: mujoco.MjSpec) -> None:
    """Turn the seven torque motors into position servos and compensate gravity on the arm."""
    for i, (kp, kv, torque) in enumerate(_ARM_GAINS):
        act = spec.actuator(f"actuator{i + 1}")
        joint = spec.joint(f"joint{i + 1}")
        act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        act.gainprm[0] = kp
        act.biasprm[:3] = [0.0, -kp, -kv]
        act.ctrlrange = joint.range
        act.forcerange = [-torque, torque]
        act.forcelimited = True
    for name in _ARM_BODIES:
        spec.body(name).gravcomp = 1.0


def build_spec(objects: list[ObjectSpec], config: SceneConfig) -> mujoco.MjSpec:
    """Compose the scene. Camera names: the keys of ``config.external``, ``wrist`` and ``probe``
    (a spare world camera that :class:`~.world.SimWorld` moves to render arbitrary poses)."""
    spec = mujoco.MjSpec.from_file(str(robot_assets_dir() / "panda.xml"))
    _set_options(spec, config.max_image_size)
    _servo_arm(spec)
    table_mat, wall_mat = _add_materials(spec, config.texture_seed)
    _add_table(spec.worldbody, table_mat)
    _add_room(spec.worldbody, wall_mat)
    _add_lights(spec.worldbody)
    _add_cameras(spec, config)
    _add_objects(spec.worldbody, objects)
    return spec


def _set_options(spec: mujoco.MjSpec, max_image_size: int) -> None:
    """Physics (2 ms implicit steps, elliptic friction cones) and rendering settings (offscreen
    framebuffer of side ``max_image_size``, clip planes, shadows, headlight)."""
    spec.option.timestep = 0.002
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.noslip_iterations = 5
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10
    spec.stat.center = [0.5, 0.0, 0.2]
    spec.stat.extent = 1.5
    spec.visual.global_.offwidth = spec.visual.global_.offheight = max_image_size
    spec.visual.map.znear = 0.01
    spec.visual.map.zfar = 4.0
    spec.visual.quality.shadowsize = 2048
    spec.visual.quality.offsamples = 0  # no MSAA: colour, depth and ids all sampled at pixel centres
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.25, 0.25, 0.25]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]


def _add_materials(spec: mujoco.MjSpec, seed: int) -> tuple[str, str]:
    """The procedural table and wall materials (textures drawn with ``seed``), and the checkered
    ``floor`` material; returns the table's and the wall's names."""
    rng = np.random.default_rng(seed)
    table_mat = _add_texture(spec, "table", _wood_texture(rng), (1.5, 1.5))
    wall_mat = _add_texture(spec, "wall", _wall_texture(rng), (0.6, 0.6))
    floor = spec.add_texture(
        name="floor", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER
    )
    floor.width = floor.height = 256
    floor.rgb1, floor.rgb2 = [0.35, 0.35, 0.38], [0.25, 0.25, 0.28]
    floor_mat = spec.add_material(name="floor", texrepeat=[4, 4], texuniform=True)
    floor_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "floor"
    return table_mat, wall_mat


def _add_table(world: mujoco.MjsBody, material: str) -> None:
    """The table: a 1.4 x 1.3 m box whose top is the plane z = 0."""
    world.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.7, 0.65, 0.02],
        pos=[0.35, 0, -0.02],
        material=material,
    )


def _add_room(world: mujoco.MjsBody, wall_material: str) -> None:
    """The floor 0.75 m below the table top and the room's four walls and ceiling (visual only:
    nothing collides with them)."""
    world.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[3, 3, 0.1],
        pos=[0, 0, -0.75],
        material="floor",
        contype=0,
        conaffinity=0,
    )
    for i, (pos, size) in enumerate(
        [
            ((2.2, 0, 0.5), (0.02, 2.5, 1.3)),
            ((-1.4, 0, 0.5), (0.02, 2.5, 1.3)),
            ((0.4, 2.5, 0.5), (1.8, 0.02, 1.3)),
            ((0.4, -2.5, 0.5), (1.8, 0.02, 1.3)),
            ((0.4, 0, 1.8), (1.8, 2.5, 0.02)),
        ]
    ):
        world.add_geom(
            name=f"wall{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=size,
            pos=pos,
            material=wall_material,
            contype=0,
            conaffinity=0,
        )


def _add_lights(world: mujoco.MjsBody) -> None:
    """Two directional lights: ``top``, which casts shadows, and a dimmer, shadowless ``fill``."""
    world.add_light(
        name="top",
        pos=[0.6, 0.3, 1.6],
        dir=[-0.1, -0.15, -1],
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        diffuse=[0.6, 0.6, 0.6],
        specular=[0.15, 0.15, 0.15],
        castshadow=True,
    )
    world.add_light(
        name="fill",
        pos=[1.5, -1.0, 1.2],
        dir=[-0.7, 0.5, -0.6],
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        diffuse=[0.25, 0.25, 0.25],
        specular=[0, 0, 0],
        castshadow=False,
    )


def _add_cameras(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    """The external cameras of ``config``, the spare world camera ``probe`` and the ``wrist``
    camera on the gripper base."""
    world = spec.worldbody
    for name, cam in config.external.items():
        world.add_camera(
            name=name, pos=list(cam.eye), quat=list(look_at_quat(cam.eye, cam.target)), fovy=cam.fovy
        )
    world.add_camera(name="probe", pos=[1.0, 0, 0.5], quat=list(look_at_quat((1.0, 0, 0.5), (0.5, 0, 0))))
    # Wrist camera on the gripper base (+z = approach, fingers close along y): offset across
    # the finger axis, looking at the point between the fingertips.
    eye, target = (0.08, 0.0, 0.03), (0.0, 0.0, 0.19)
    spec.body("base").add_camera(
        name="wrist",
        pos=list(eye),
        quat=list(look_at_quat(eye, target, up=(1, 0, 0))),
        fovy=config.wrist_fovy,
    )


def _add_objects(world: mujoco.MjsBody, objects: list[ObjectSpec]) -> None:
    """Every object as a grey free body at (0.5, 0) on the table (episodes place and colour them)."""
    geom_type = {
        "box": mujoco.mjtGeom.mjGEOM_BOX,
        "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
        "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    }
    for obj in objects:
        body = world.add_body(name=obj.name, pos=[0.5, 0, obj.half_height])
        body.add_freejoint(name=obj.name)
        body.add_geom(
            name=obj.name,
            type=geom_type[obj.shape],
            size=list(obj.size) + [0] * (3 - len(obj.size)),
            mass=obj.mass,
            friction=[1.0, 0.01, 0.001],
            condim=4,
            rgba=[0.5, 0.5, 0.5, 1],
        )


def build_model(objects: list[ObjectSpec], config: SceneConfig) -> mujoco.MjModel:
    """Compile :func:`build_spec`."""
    return build_spec(objects, config).compile()
