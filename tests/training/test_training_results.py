"""Fast, exact tests of :mod:`torchir.training.results` (``result.yaml``, parameter files, final
images), written for the mutation audit: a stand-in module (a namespace with the methods
results.py calls), tiny tensors and a stand-in for ``write_image`` that saves ``.npy`` bytes
under the image name (a Mitsuba call in a mutmut child forked from a process that already ran
Mitsuba hangs); files are read back independently (yaml, numpy).
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import torchir  # noqa: F401  (before torch: sets the OpenMP policy)

import numpy as np
import pytest
import torch
import yaml

import torchir.training.results as results
from torchir.training.results import INLINE_MAX, _rounded, parameter_entry, write_results

from tests.helpers import DEVICE


def test_inline_max():
    assert INLINE_MAX == 16


def test_rounded():
    with torch.device("cpu"):  # host values, as parameter_entry gives them
        assert _rounded(torch.tensor([1.23456789])) == 1.23457
        assert type(_rounded(torch.tensor(2.0))) is float
        assert _rounded(torch.tensor([[1.0, 123456789.0], [0.000123456789, -2.5]])) == [[1.0, 123457000.0], [0.000123457, -2.5]]
        assert _rounded(torch.tensor([0.1, 0.2])) == [0.1, 0.2]
        empty = _rounded(torch.zeros(0))
        assert empty == []


def test_parameter_entry_inline(tmp_path):
    value = torch.arange(16, dtype=torch.float64).reshape(4, 4) / 3
    entry = parameter_entry("k", value.requires_grad_(), tmp_path)
    assert len(entry) == 4 and all(len(row) == 4 for row in entry)
    assert entry[0] == [0.0, 0.333333, 0.666667, 1.0]
    assert entry[3] == [4.0, 4.33333, 4.66667, 5.0]
    assert not (tmp_path / "parameters").exists()
    assert parameter_entry("s", torch.tensor(0.5), tmp_path) == 0.5


def test_parameter_entry_npy(tmp_path):
    value = torch.arange(17, dtype=torch.float64) / 4  # 17 entries: one past INLINE_MAX
    entry = parameter_entry("mesh.vertex_positions", value, tmp_path / "run")
    assert entry["file"] == "parameters/mesh.vertex_positions.npy" and entry["shape"] == [17]
    saved = np.load(tmp_path / "run" / "parameters" / "mesh.vertex_positions.npy")
    assert saved.dtype == np.float32 and np.array_equal(saved, np.arange(17, dtype=np.float32) / 4)


def test_parameter_entry_npy_2d_and_4_channels(tmp_path):
    value = torch.tensor([[1.0, 2.0], [3.0, 5.0]]).repeat(5, 1)  # (10, 2)
    entry = parameter_entry("v", value, tmp_path)
    assert entry == {"file": "parameters/v.npy", "shape": [10, 2], "mean": [2.0, 3.5]}
    four = torch.ones(3, 2, 4)  # (H, W, 4): not a texture
    entry = parameter_entry("t4", four, tmp_path)
    assert entry == {"file": "parameters/t4.npy", "shape": [3, 2, 4], "mean": [1.0, 1.0, 1.0, 1.0]}
    flat = torch.ones(6, 3)  # 2-D with last dim 3: not a texture (not 3-D)
    assert parameter_entry("f", flat * 2, tmp_path)["file"] == "parameters/f.npy"


@pytest.mark.parametrize("channels", [1, 3])
def test_parameter_entry_texture(tmp_path, channels):
    h, w = 3, 6  # 18 entries at 1 channel: past INLINE_MAX
    value = torch.arange(h * w * channels, dtype=torch.float32).reshape(h, w, channels) / 8
    entry = parameter_entry("tex.data", value, tmp_path)
    assert entry["file"] == "parameters/tex.data.exr"
    assert entry["shape"] == [h, w, channels]
    means = value.reshape(-1, channels).mean(0).tolist()
    assert entry["mean"] == (means[0] if channels == 1 else means)
    image = read_image(tmp_path / "parameters" / "tex.data.exr")
    assert image.shape == (channels, h, w)
    assert torch.allclose(image, value.permute(2, 0, 1))


class FakeModule:
    def __init__(self, values, truth=None, error=0.0, sensors=6, name="cbox") -> None:
        self.values, self.truth, self.error = values, truth, error
        self.scene = SimpleNamespace(name=name, sensor_count=sensors)
        self.previews = []
        self.truth_args = []

    def scene_values(self):
        return self.values

    def ground_truth(self, explicit_only=False):
        self.truth_args.append(explicit_only)
        return self.truth

    def parameter_error(self, truth):
        assert truth is self.truth
        return self.error

    def preview(self, view, values):
        self.previews.append((view, values))
        return torch.full((3, 1, 2), 0.25 * (view + 1))


def read_image(path):
    return torch.from_numpy(np.load(path)).to(DEVICE)


@pytest.fixture(autouse=True)
def images(monkeypatch):
    written = []

    def record(path, image):
        path = Path(path)
        written.append(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as f:
            np.save(f, image.detach().cpu().numpy())
        return path

    monkeypatch.setattr(results, "write_image", record)
    return written


def test_write_results_yaml(tmp_path, images):
    values = {"red.reflectance.value": torch.tensor([0.1234567, 0.5, 2.0], requires_grad=True),
              "big": torch.arange(20, dtype=torch.float32).reshape(4, 5)}
    m = FakeModule(values, truth={"red.reflectance.value": torch.zeros(3)}, error=0.01234567)
    folder = tmp_path / "new" / "run"
    path = write_results(m, str(folder), 12.0, images=False)
    assert path == folder / "result.yaml"
    assert m.truth_args == [True]
    text = path.read_text()
    assert text.splitlines()[0] == "# recovered scene parameters, in the scene's own units (torchir 0.1.0)"
    loaded = yaml.safe_load(text)
    assert loaded == {
        "step": 12, "scene": "cbox",
        "parameters": {
            "red.reflectance.value": [0.123457, 0.5, 2.0],
            "big": {"file": "parameters/big.npy", "shape": [4, 5], "mean": [7.5, 8.5, 9.5, 10.5, 11.5]},
        },
        "param_error": 0.0123457,
    }
    assert type(loaded["step"]) is int
    assert list(loaded) == ["step", "scene", "parameters", "param_error"]  # not sorted
    assert list(loaded["parameters"]) == ["red.reflectance.value", "big"]
    # flow style for the leaves, block style above them
    assert "  red.reflectance.value: [0.123457, 0.5, 2.0]\n" in text
    assert images == [] and m.previews == []


def test_write_results_no_truth(tmp_path, images):
    m = FakeModule({"k": torch.tensor(0.5)}, truth={})
    path = write_results(m, tmp_path, 3, images=False)
    loaded = yaml.safe_load(path.read_text())
    assert loaded == {"step": 3, "scene": "cbox", "parameters": {"k": 0.5}}
    m2 = FakeModule({"k": torch.tensor(0.5)}, truth=None)
    assert "param_error" not in yaml.safe_load(write_results(m2, tmp_path, 3, images=False).read_text())


def test_write_results_zero_error_written(tmp_path):
    m = FakeModule({"k": torch.tensor(0.5)}, truth={"k": torch.tensor(0.5)}, error=0.0)
    loaded = yaml.safe_load(write_results(m, tmp_path, 1, images=False).read_text())
    assert loaded["param_error"] == 0.0


def test_write_results_long_line_width(tmp_path):
    value = torch.arange(16, dtype=torch.float32) + 0.123456
    m = FakeModule({"k": value}, truth=None)
    text = write_results(m, tmp_path, 1, images=False).read_text()
    lines = text.splitlines()
    entry_lines = [line for line in lines if line.startswith("  ")]
    assert len(entry_lines) > 1  # wrapped
    assert len(entry_lines[0]) > 100  # yaml breaks a flow sequence once past width 100 (its default: 80)
    # 16 x "0.1001, " after "  k: [": the line passes column 100 after the 12th item, not at 101
    m = FakeModule({"k": torch.full((16,), 0.1001)}, truth=None)
    lines = write_results(m, tmp_path, 1, images=False).read_text().splitlines()
    assert lines[-2:] == ["  k: [" + ", ".join(["0.1001"] * 12) + ",", "    " + ", ".join(["0.1001"] * 4) + "]"]


def test_write_results_images_default_views(tmp_path, images):
    m = FakeModule({"k": torch.tensor([0.5, 0.25])}, sensors=6)
    write_results(m, tmp_path, 1)
    assert [v for v, _ in m.previews] == [0, 1, 2, 3]
    assert all(vals["k"].tolist() == [0.5, 0.25] and not vals["k"].requires_grad for _, vals in m.previews)
    assert [str(p.relative_to(tmp_path)) for p in images] == [
        f"images/final_v{v}.{s}" for v in range(4) for s in ("png", "exr")
    ]
    exr = read_image(tmp_path / "images" / "final_v2.exr")
    assert torch.allclose(exr, torch.full((3, 1, 2), 0.75))


def test_write_results_images_few_sensors_and_given_views(tmp_path, images):
    m = FakeModule({"k": torch.tensor(0.5)}, sensors=2)
    write_results(m, tmp_path, 1, images=True)
    assert [v for v, _ in m.previews] == [0, 1]
    m = FakeModule({"k": torch.tensor(0.5)}, sensors=2)
    write_results(m, tmp_path, 1, views=[5, 1])
    assert [v for v, _ in m.previews] == [5, 1]


def test_write_results_no_grad(tmp_path):
    seen = []
    m = FakeModule({"k": torch.tensor(0.5)}, truth={"k": torch.tensor(0.0)})
    m.scene_values = lambda: (seen.append(torch.is_grad_enabled()), {"k": torch.tensor(0.5, requires_grad=True) * 2})[1]
    loaded = yaml.safe_load(write_results(m, tmp_path, 1, images=False).read_text())
    assert seen == [False] and loaded["parameters"] == {"k": 1.0}


def test_parameter_entry_flat_array_mean_is_a_summary(tmp_path):
    # vertex_positions is (3V,) (torchir.scene's docstring): result.yaml should summarise it,
    # not inline every entry that went to the .npy file
    value = torch.arange(300, dtype=torch.float32)  # 100 vertices
    entry = parameter_entry("mesh.vertex_positions", value, tmp_path)
    assert entry["mean"] == pytest.approx(149.5)  # one number: the mean of 0..299
    assert entry["shape"] == [300]
    # a texture keeps its per-channel mean
    texture = torch.stack([torch.zeros(8, 8), torch.ones(8, 8), torch.full((8, 8), 0.25)], -1)
    assert parameter_entry("tex.data", texture, tmp_path)["mean"] == pytest.approx([0.0, 1.0, 0.25])
