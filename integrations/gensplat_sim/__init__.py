"""Simulated Franka tabletop (MuJoCo): calibrated cameras, scripted experts, LeRobot
recording, ground truth at any camera pose and a perturbed-camera evaluation environment.

Modules: :mod:`.world` (``SimWorld``: physics, control, rendering), :mod:`.tasks` and
:mod:`.experts` (``pick_place``, ``stack``), :mod:`.record` (LeRobot datasets,
``gensplat record``), :mod:`.truth` (``GroundTruth``), :mod:`.evaluate`
(``PerturbedCameraEnv``, ``evaluate``); :mod:`.demo` (``gensplat demo``: record, cache,
augment and score against the simulator's ground truth). Calibration and depth follow
:mod:`gensplat_transforms.data.format`. A layer above ``gensplat_transforms`` and
``gensplat_lerobot``; below ``gensplat_cli``.

Needs the ``sim`` extra (``pip install 'gensplat-transforms[sim]'``). Importing this package
selects MuJoCo's headless EGL backend (``MUJOCO_GL=egl``, Mesa llvmpipe on a CPU) unless
``MUJOCO_GL`` is already set; it must happen before ``mujoco`` is first imported.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
