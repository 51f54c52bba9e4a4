"""Grid volumes: torchir.volumes.resample in Mitsuba's voxel convention, and a gridvolume's data
bound at another resolution than the scene loaded (Scene.check_values / to_drjit)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch

import torchir
from torchir.derived import load_callable
from torchir.functions import render
from torchir.volumes import resample, voxel_centres

from tests.helpers import ROOT

KEY = "object.interior_medium.sigma_t.data"
BUILD = f"{ROOT}/configs/examples/volume_from_views.py:build"


def _grid(shape, seed=0) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).uniform(0.0, 1.0, (*shape, 1)).astype(np.float32))


def _mitsuba_eval(grid: torch.Tensor, shape) -> torch.Tensor:
    """Mitsuba's own gridvolume (trilinear, clamp) evaluated at the voxel centres of ``shape``."""
    volume = mi.load_dict({"type": "gridvolume", "grid": mi.VolumeGrid(grid.cpu().numpy())})
    points = voxel_centres(shape).reshape(-1, 3).cpu().numpy()
    it = dr.zeros(mi.Interaction3f, points.shape[0])
    it.p = mi.Point3f(*(points[:, i].astype(np.float32) for i in range(3)))
    return torch.from_numpy(np.array(volume.eval_1(it))).reshape(*shape, 1)


@pytest.mark.parametrize("old, new", [((4, 5, 6), (8, 10, 12)), ((4, 5, 6), (7, 3, 9)), ((6, 6, 6), (3, 2, 4))])
def test_resample_is_mitsuba_s_lookup_at_the_new_voxel_centres(old, new):
    """Up, mixed and down: every resampled voxel is what Mitsuba's gridvolume evaluates at its
    centre, borders included (a half-voxel shift or align_corners=True is off by ~0.1 here)."""
    grid = _grid(old)
    torch.testing.assert_close(resample(grid, new), _mitsuba_eval(grid, new), rtol=0, atol=2e-6)


def test_resample_reproduces_a_linear_ramp_inside():
    """f(p) = 1 + 2x - 3y + 0.5z sampled at the voxel centres comes back exactly at the new
    centres that lie between the old ones (outside them the field is clamped, as Mitsuba's)."""
    old, new = (4, 6, 5), (9, 11, 13)
    f = lambda p: 1 + 2 * p[..., 0] - 3 * p[..., 1] + 0.5 * p[..., 2]  # noqa: E731
    grid = f(voxel_centres(old, torch.float64))[..., None]
    out = resample(grid, new)[..., 0]
    p = voxel_centres(new, torch.float64)
    lo = torch.tensor([0.5 / old[2], 0.5 / old[1], 0.5 / old[0]], dtype=torch.float64)
    inside = ((p >= lo) & (p <= 1 - lo)).all(-1)
    assert int(inside.sum()) > 200
    torch.testing.assert_close(out[inside], f(p)[inside], rtol=0, atol=1e-12)


def test_resample_upsampling_equals_dr_resample_linear_and_dr_upsample_of_a_texture():
    """Where Dr.Jit's own tools apply (upsampling): dr.resample(filter='linear') and dr.upsample of
    a linear, clamped Texture3f (Mitsuba's volume tutorial) give the same grid."""
    grid, new = _grid((4, 5, 3), seed=1), (8, 10, 9)
    ours = resample(grid, new)
    by_resample = torch.from_numpy(np.array(dr.resample(mi.TensorXf(grid.cpu().numpy()), (*new, 1), filter="linear")))
    texture = mi.Texture3f(mi.TensorXf(grid.cpu().numpy()), filter_mode=dr.FilterMode.Linear, wrap_mode=dr.WrapMode.Clamp)
    with pytest.warns(DeprecationWarning):
        by_upsample = torch.from_numpy(np.array(dr.upsample(texture, shape=new).tensor()))
    torch.testing.assert_close(ours, by_resample, rtol=0, atol=2e-6)
    torch.testing.assert_close(ours, by_upsample, rtol=0, atol=2e-6)


def test_resample_gradcheck_float64():
    grid = torch.rand(3, 2, 4, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda g: resample(g, (5, 3, 2)), (grid,))


def test_resample_shapes_and_errors():
    grid = torch.rand(2, 3, 4, 3)
    assert resample(grid, (5, 1, 2)).shape == (5, 1, 2, 3)
    same = resample(grid, (2, 3, 4))
    assert torch.equal(same, grid) and same.data_ptr() != grid.data_ptr()
    with pytest.raises(ValueError, match=r"\(Z, Y, X, C\)"):
        resample(torch.rand(2, 3, 4), (2, 2, 2))
    with pytest.raises(ValueError, match="three ints >= 1"):
        resample(grid, (2, 0, 2))
    with pytest.raises(ValueError, match="three ints >= 1"):
        resample(grid, (2, 2))


@pytest.fixture(scope="module")
def volume_scenes():
    """The example's scene at an 8² film, 1 view, loaded with a 4³ grid, and the same scene loaded
    with the 8³ grid that the first will be given."""
    build = load_callable(BUILD)
    fine = _grid((8, 8, 8), seed=2) * 0.3
    coarse_dict = build(resolution=8, grid=4, views=1, max_depth=3)
    fine_dict = build(resolution=8, grid=4, views=1, max_depth=3)
    fine_dict["object"]["interior"]["sigma_t"]["grid"] = mi.VolumeGrid(fine.cpu().numpy())
    return torchir.Scene.from_dict(coarse_dict), torchir.Scene.from_dict(fine_dict), fine


def test_a_grid_of_another_resolution_renders_as_a_scene_loaded_at_that_resolution(volume_scenes):
    """A 4³-loaded scene given an 8³ grid renders what the 8³-loaded scene renders (same seed),
    the gradient comes back at 8³, and the next render without it is the loaded 4³ scene again."""
    coarse, fine, grid = volume_scenes
    assert coarse.is_grid_volume_data(KEY) and coarse.info(KEY).shape == (4, 4, 4, 1)
    loaded = render(coarse, {}, spp=8, seed=5)
    value = grid.clone().requires_grad_()
    image = render(coarse, {KEY: value}, spp=8, seed=5)
    torch.testing.assert_close(image, render(fine, {}, spp=8, seed=5), rtol=0, atol=1e-5)
    assert (image - loaded).abs().max() > 1e-2  # the bound grid really is another volume
    image.mean().backward()
    assert value.grad.shape == (8, 8, 8, 1) and bool(torch.isfinite(value.grad).all()) and value.grad.abs().sum() > 0
    torch.testing.assert_close(render(coarse, {}, spp=8, seed=5), loaded, rtol=0, atol=0)


def test_only_grid_volume_data_binds_at_another_shape(volume_scenes):
    coarse, _, _ = volume_scenes
    assert not coarse.is_grid_volume_data("light.radiance.value")
    assert not coarse.is_grid_volume_data("object.vertex_positions")
    with pytest.raises(ValueError, match=r"expected \(Z, Y, X, 1\).*1 channel"):
        coarse.check_values({KEY: torch.zeros(8, 8, 8, 3)})
    with pytest.raises(ValueError, match=r"expected \(Z, Y, X, 1\)"):
        coarse.check_values({KEY: torch.zeros(8, 8, 8)})
    with pytest.raises(ValueError, match=r"expected \(Z, Y, X, 1\)"):
        coarse.check_values({KEY: torch.zeros(8, 0, 8, 1)})
    positions = coarse.get("object.vertex_positions")
    with pytest.raises(ValueError, match=r"has shape \(6,\), expected"):
        coarse.check_values({"object.vertex_positions": positions[:6].clone()})
    coarse.check_values({KEY: torch.zeros(2, 3, 5, 1)})  # any positive (Z, Y, X)
