"""EstimateConfig: what the calibration estimate is given, checked when it is made."""

import dataclasses

import numpy as np
import pytest

from gensplat_transforms.calibration.estimate import EstimateConfig


def test_defaults_give_nothing_and_sample_16_timesteps():
    config = EstimateConfig()
    assert (config.timesteps, config.fov_deg, config.focal_px, config.model, config.per_episode) == (16, None, None, None, False)
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.timesteps = 4


@pytest.mark.parametrize("fields, message", [
    ({"timesteps": 1}, "EstimateConfig.timesteps (--timesteps) must be a whole number >= 2, got 1"),
    ({"timesteps": 4.0}, "EstimateConfig.timesteps (--timesteps) must be a whole number >= 2, got 4.0"),
    ({"timesteps": True}, "EstimateConfig.timesteps (--timesteps) must be a whole number >= 2, got True"),
    ({"fov_deg": 180.0}, "EstimateConfig.fov_deg (--fov) must be a positive number below 180 degrees, got 180.0"),
    ({"fov_deg": float("nan")}, "EstimateConfig.fov_deg (--fov) must be a positive number below 180 degrees"),
    ({"fov_deg": "60"}, "EstimateConfig.fov_deg (--fov) must be a positive number below 180 degrees, got '60'"),
    ({"focal_px": 0.0}, "EstimateConfig.focal_px (--focal) must be a positive number, got 0.0"),
    ({"focal_px": float("inf")}, "EstimateConfig.focal_px (--focal) must be a positive number, got inf"),
    ({"baseline_m": 0.0}, "EstimateConfig.baseline_m (--baseline) is a distance in metres"),
    ({"table_m": float("nan")}, "EstimateConfig.table_m (--table-distance) is a distance in metres"),
    ({"table_m": 1e3}, "0.001 to 100 m, got 1000.0"),
    ({"fov_deg": 60.0, "focal_px": 500.0}, "give one of fov_deg (--fov), focal_px (--focal) and model (--model)"),
    ({"focal_px": 500.0, "model": "shipped"}, "give one of fov_deg (--fov), focal_px (--focal) and model"),
    ({"baseline_m": 0.8, "table_m": 0.5}, "give one of baseline_m (--baseline) and table_m (--table-distance)"),
    ({"fov_deg": True}, "EstimateConfig.fov_deg (--fov) must be a positive number below 180 degrees, got True"),
    ({"principal_point": (311.7, 255.4)}, "must be one or more (cx, cy) pairs of numbers in pixels"),
    ({"principal_point": [(1.0, 2.0, 3.0)]}, "must be one or more (cx, cy) pairs of numbers in pixels"),
    ({"principal_point": []}, "EstimateConfig.principal_point (--principal-point) must be one or more (cx, cy)"),
    ({"principal_point": [("311", 255)]}, "must be one or more (cx, cy) pairs of numbers in pixels"),
    ({"principal_point": [(float("nan"), 255.0)]}, "must be one or more (cx, cy) pairs of numbers in pixels"),
])  # fmt: skip
def test_a_value_out_of_range_or_two_sources_are_refused_naming_the_field_and_flag(fields, message):
    with pytest.raises(ValueError) as error:
        EstimateConfig(**fields)
    assert message in str(error.value)


def test_numpy_numbers_and_lists_are_taken_as_python_ones():
    config = EstimateConfig(timesteps=np.int64(4), fov_deg=np.float32(69.4), principal_point=[[311, 255.5]])
    assert config.timesteps == 4 and config.principal_point == ((311.0, 255.5),)
    assert EstimateConfig(principal_point=config.principal_point) == config.__class__(principal_point=((311, 255.5),))
