"""Hostile calibration input: every file ``gensplat calibrate`` reads, and the
``calibration.json`` it writes when read back, is checked where it enters, and an error names
the file, the camera and the field (a ``gensplat: error:`` line, exit status 2, on the CLI)."""

import json
import re
import time

import pytest
import test_files
import torch
import yaml
from gensplat_cli import main
from test_files import HEIGHT, WIDTH, entry, nerfstudio, write_info

from gensplat_transforms.calibration.files import MAX_FILE_BYTES, calibrate, load_calibration
from gensplat_transforms.data.format import calibration_path

truth = test_files.truth  # its fixture


def billion_laughs(levels: int = 9) -> str:
    """A YAML file of a few hundred bytes whose aliases expand to 10**levels strings."""
    lines = ["l0: &l0 [" + ", ".join(["lol"] * 10) + "]"]
    lines += [f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]" for i in range(1, levels + 1)]
    return "\n".join([*lines, f"left: {{K: *l{levels}}}"]) + "\n"


def test_yaml_aliases_are_refused_before_they_are_expanded(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    write_info(root)
    source = tmp_path / "calibration.yaml"
    source.write_text(billion_laughs())
    assert source.stat().st_size < 1000

    def expand(*args):
        raise AssertionError("the file was loaded: its aliases expand")

    monkeypatch.setattr(yaml, "safe_load", expand)
    monkeypatch.setattr(yaml, "load", expand)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"calibration.yaml: YAML aliases \(\*name\) are not allowed"):
        calibrate(root, source)
    assert time.perf_counter() - start < 10  # a loose bound: the refusal comes before any expansion
    assert not calibration_path(root).exists()


def test_deeply_nested_yaml_is_refused_as_it_is_parsed(tmp_path):
    """PyYAML scans nested brackets in quadratic time: 60 kB of them took a minute, a 1 MB file
    days. Refused at the 33rd level, at once."""
    root = tmp_path / "ds"
    write_info(root)
    source = tmp_path / "calibration.yaml"
    source.write_text("left: " + "[" * 30_000 + "]" * 30_000)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"calibration.yaml: nested deeper than 32 levels at line 1"):
        calibrate(root, source)
    assert time.perf_counter() - start < 5


@pytest.mark.parametrize("text, message", [
    ("? [left, right]\n: {K: [[30, 0, 16], [0, 30, 12], [0, 0, 1]]}\n", "found unhashable key"),  # a raw TypeError
    ("left:\n\tK: 1\n", "found character '\\t' that cannot start any token"),  # PyYAML's message spans lines
])  # fmt: skip
def test_malformed_yaml_is_one_error_line(text, message, tmp_path, capsys):
    root = tmp_path / "ds"
    write_info(root)
    source = tmp_path / "calibration.yaml"
    source.write_text(text)
    assert main(["calibrate", "from-file", "--root", str(root), str(source)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"gensplat: error: {source}: not valid YAML (") and err.count("\n") == 1, err
    assert message in err, err


@pytest.mark.parametrize("suffix", ["json", "yaml"])
def test_a_key_given_twice_is_refused_naming_it(truth, tmp_path, suffix):
    """The same camera (or episode) given twice: a parser keeps the last silently; refused."""
    root = tmp_path / "ds"
    write_info(root)
    cameras = entry(truth)
    name = next(iter(cameras))
    pairs = [*cameras.items(), (name, cameras[name])]
    source = tmp_path / f"calibration.{suffix}"
    source.write_text("{" + ", ".join(f"{json.dumps(n)}: {json.dumps(c)}" for n, c in pairs) + "}")  # YAML too
    with pytest.raises(ValueError, match=rf"calibration.{suffix}: key '{name}' appears twice in one mapping"):
        calibrate(root, source)
    source.write_text("{" + ", ".join(f"{json.dumps(n)}: {json.dumps(c)}" for n, c in cameras.items()) + "}")
    assert set(calibrate(root, source)) == set(cameras)  # the same file without the repeat


def test_a_file_over_the_size_limit_is_refused_unread(truth, tmp_path):
    root = tmp_path / "ds"
    write_info(root)
    source = tmp_path / "calibration.json"
    source.write_text(json.dumps(entry(truth)) + " " * MAX_FILE_BYTES)  # valid JSON, padded
    with pytest.raises(ValueError, match=rf"calibration.json: \d+ bytes; .* at most {MAX_FILE_BYTES} bytes"):
        calibrate(root, source)


@pytest.mark.parametrize("focal", [1e308, 1e-300, 0.004 * WIDTH, 60.0 * WIDTH])
def test_focal_lengths_outside_1_to_179_degrees_are_refused(focal, truth, tmp_path):
    root = tmp_path / "ds"
    write_info(root)
    c2w = truth["left"][1].tolist()
    source = tmp_path / "calibration.json"
    source.write_text(json.dumps({"left": {"fx": focal, "fy": 40.0, "cx": 32.0, "cy": 24.0, "c2w": c2w}}))
    message = r"camera 'left', field K: focal lengths must be > 0 and give a field of view of 1 to 179"
    with pytest.raises(ValueError, match=message):
        calibrate(root, source)


def test_focal_lengths_at_the_ends_of_the_range_are_accepted(truth, tmp_path):
    root = tmp_path / "ds"
    write_info(root)
    c2w = truth["left"][1].tolist()
    source = tmp_path / "calibration.json"
    source.write_text(json.dumps({"left": {"fx": 0.0045 * WIDTH, "fy": 57.0 * HEIGHT, "cx": 32.0, "cy": 24.0,
                                           "c2w": c2w}}))  # fmt: skip
    assert calibrate(root, source)["left"].K[0, 0] == 0.0045 * WIDTH


def cli_case(case: str, truth: dict) -> tuple[bytes, list[str]]:
    """The file's bytes and the extra arguments of each CLI case."""
    c2w = truth["left"][1]
    frames = nerfstudio(truth, 1.0)
    if case == "nerfstudio_w_0":
        frames["frames"][0]["intrinsics"]["w"] = 0
    data = {
        "width_0": entry(truth, width=0, height=HEIGHT),
        "nerfstudio_w_0": frames,
        "int_1e400": {"left": {"fx": 10**400, "fy": 40.0, "cx": 32.0, "cy": 24.0, "c2w": c2w.tolist()}},
        "frames_not_a_list": {"frames": 3},
        "frame_not_a_mapping": {"frames": [3]},
        "file_path_not_a_string": {"frames": [{"file_path": 3, "transform_matrix": c2w.tolist()}]},
        "nerfstudio_without_frames": entry(truth),
    }.get(case)
    text = b'{"left": {"mount": "\xff"}}' if data is None else json.dumps(data).encode()
    return text, ["--convention", "nerfstudio"] if case == "nerfstudio_without_frames" else []


@pytest.mark.parametrize("case, message", [
    ("width_0", r"camera 'left': width and height \(nerfstudio: w, h\) must be positive whole .*, got 0, 48"),
    ("nerfstudio_w_0", r"camera 'left': width and height \(nerfstudio: w, h\) must be positive .*, got 0"),
    ("not_utf8", r"calibration.json: not UTF-8 text \(.*\); save it as UTF-8"),
    ("int_1e400", r"camera 'left', field fx: expected a finite number, got 1000000"),
    ("frames_not_a_list", r"field frames: a nerfstudio file needs a non-empty list of frames, got 3"),
    ("frame_not_a_mapping", r"frames\[0\] must be a mapping with file_path \(a string\), transform_matrix"),
    ("file_path_not_a_string", r"frames\[0\] must be a mapping with file_path \(a string\)"),
    ("nerfstudio_without_frames", r"field frames: a nerfstudio file needs a non-empty list .*, got None"),
])  # fmt: skip
def test_cli_reports_malformed_files_as_an_error_line(case, message, truth, tmp_path, capsys):
    root = tmp_path / "ds"
    write_info(root)
    source = tmp_path / "calibration.json"
    text, extra = cli_case(case, truth)
    source.write_bytes(text)
    assert main(["calibrate", "from-file", "--root", str(root), str(source), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"gensplat: error: {source}: ") and err.count("\n") == 1
    assert re.search(message, err), err
    assert not calibration_path(root).exists()


def test_a_folder_given_as_the_calibration_file_is_named_a_folder(tmp_path, capsys):
    root = tmp_path / "ds"
    write_info(root)
    folder = tmp_path / "calib"
    folder.mkdir()
    assert main(["calibrate", "from-file", "--root", str(root), str(folder)]) == 2
    err = capsys.readouterr().err
    assert err == f"gensplat: error: calibration file {folder} is a folder, not a file: give the JSON or YAML file in it\n"
    assert not calibration_path(root).exists()


def test_calibrate_refuses_cameras_whose_features_carry_calibration(truth, tmp_path, capsys):
    root = tmp_path / "ds"
    features = write_info(root)
    K, c2w = truth["left"]
    info = {"camera.intrinsics": K.tolist(), "camera.extrinsics": c2w.tolist()}
    features["observation.images.left"]["info"] = info
    (root / "meta" / "info.json").write_text(json.dumps({"features": features}))
    source = tmp_path / "calibration.json"
    source.write_text(json.dumps(entry(truth, "left") | entry(truth, "right")))
    assert main(["calibrate", "from-file", "--root", str(root), str(source)]) == 2
    assert capsys.readouterr().err == (
        f"gensplat: error: {source}: camera(s) ['left'] already carry calibration in "
        f"{root / 'meta' / 'info.json'} (camera.intrinsics in their feature's info), which is used "
        "instead of calibration.json: leave them out\n"
    )
    assert not calibration_path(root).exists()


@pytest.mark.parametrize("case, message", [
    ("no_cameras", r"calibration.json: field cameras: expected a mapping of camera names, got None"),
    ("cameras_not_a_mapping", r"calibration.json: field cameras: expected a mapping of .*, got \['left'\]"),
    ("camera_not_a_mapping", r"calibration.json: camera 'left': expected a mapping of fields, not str"),
    ("intrinsics_abc", r"calibration.json: camera 'left', field K: expected numbers .*, got 'abc'"),
    ("intrinsics_2x2", r"calibration.json: camera 'left', field K: expected shape \(3, 3\), got \(2, 2\)"),
    ("depth_without_width", r"calibration.json: camera 'left', field depth: needs K .*width, height"),
    ("focal_1e308", r"calibration.json: camera 'left', field K: focal lengths must be > 0 and give"),
])  # fmt: skip
def test_a_hand_edited_calibration_json_names_file_camera_field_and_fix(case, message, truth, tmp_path):
    root = tmp_path / "ds"
    features = write_info(root)
    K = truth["left"][0]
    depth = {"K": K.tolist(), "width": WIDTH, "height": HEIGHT, "to_camera": torch.eye(4).tolist()}
    source = tmp_path / "source.json"
    source.write_text(json.dumps(entry(truth, "left", depth=depth) | entry(truth, "right")))
    calibrate(root, source)
    assert set(load_calibration(features, root)) == {"left", "right"}
    path = calibration_path(root)
    data = json.loads(path.read_text())
    left = data["cameras"]["left"]
    if case == "no_cameras":
        del data["cameras"]
    elif case == "cameras_not_a_mapping":
        data["cameras"] = ["left"]
    elif case == "camera_not_a_mapping":
        data["cameras"]["left"] = "left"
    elif case == "intrinsics_abc":
        left["camera.intrinsics"] = "abc"
    elif case == "intrinsics_2x2":
        left["camera.intrinsics"] = [[1.0, 0.0], [0.0, 1.0]]
    elif case == "depth_without_width":
        del left["camera.depth"]["width"]
    else:
        left["camera.intrinsics"][0][0] = 1e308
    path.write_text(json.dumps(data))
    fix = rf"; write it again with `gensplat calibrate from-file --root {re.escape(str(root))} FILE`$"
    with pytest.raises(ValueError, match=message + ".*" + fix):
        load_calibration(features, root)
