"""Derived (torch-side) scene parameters and the point-light rule: ``glossy_highlight``'s azimuth."""
from __future__ import annotations

import math

import pytest
import torch

import torchir
from torchir.functions import render
from torchir.modules import LOILoss
from torchir.scenes import glossy_highlight
from torchir.testing import check_gradients

RES = 16


@pytest.fixture(scope="module")
def highlight() -> torchir.Scene:
    return torchir.Scene.builtin("glossy_highlight", resolution=RES, azimuth=0.3)


def test_derived_parameter_is_listed_read_and_described(highlight):
    assert "light.azimuth" in highlight.parameter_names()
    assert "light.azimuth" in highlight.parameter_names(differentiable_only=True)
    info = highlight.info("light.azimuth")
    assert info.shape == (1,) and info.differentiable and info.bindable
    assert highlight.get("light.azimuth").item() == pytest.approx(0.3)
    # the loaded light sits where the derived parameter says
    expected = glossy_highlight.light_position(torch.tensor([0.3]))
    assert torch.allclose(highlight.get("light.position"), expected, atol=1e-5)
    assert expected.norm().item() == pytest.approx(glossy_highlight.RADIUS, rel=1e-6)


def test_azimuth_renders_like_the_position_it_sets(highlight):
    az = torch.tensor([0.8])
    a = render(highlight, {"light.azimuth": az}, spp=4, seed=3)
    b = render(highlight, {"light.position": glossy_highlight.light_position(az)}, spp=4, seed=3)
    assert torch.equal(a, b)
    c = render(highlight, {}, spp=4, seed=3)  # loaded azimuth 0.3: a different image
    assert not torch.allclose(a, c)


@pytest.fixture(scope="module")
def rough_highlight() -> torchir.Scene:
    # a broader lobe (roughness 0.3) keeps the Monte Carlo noise of a 16x16 check low; the
    # light-position derivative being tested is the same
    return torchir.Scene.builtin("glossy_highlight", resolution=RES, azimuth=0.3, roughness=0.3)


def _ramp_loss(scene):
    ramp = torch.linspace(0, 1, RES).expand(3, RES, RES)  # moving the highlight sideways changes it
    return lambda params, seed: (render(scene, params, spp=32, seed=seed) * ramp).mean()


def test_azimuth_gradient_matches_finite_differences(rough_highlight):
    az = torch.tensor([0.3], requires_grad=True)
    report = check_gradients(_ramp_loss(rough_highlight), {"light.azimuth": az}, seeds=range(12), directions=1, eps=0.02)
    assert report.passed, str(report)
    check = report.checks[0]
    assert abs(check.finite_difference) > 5 * check.tolerance  # a real, non-zero derivative


def test_position_gradient_under_the_cpp_direct_integrator(rough_highlight):
    pos = rough_highlight.get("light.position").requires_grad_()
    report = check_gradients(_ramp_loss(rough_highlight), {"light.position": pos}, seeds=range(12), directions=2, eps=0.05)
    assert report.passed, str(report)
    assert all(abs(c.finite_difference) > 5 * c.tolerance for c in report.checks)


def test_point_light_position_still_rejected_where_it_gets_no_gradient():
    ball = torchir.Scene.builtin("glossy_ball", resolution=8)  # prb
    with pytest.raises(ValueError, match="non-differentiable"):
        render(ball, {"light.position": ball.get("light.position").requires_grad_()}, spp=1)
    d = glossy_highlight.build(8)
    d.pop("torchir_derived")
    d["integrator"] = {"type": "direct_projective"}  # Python AD integrator: detached light samples
    projective = torchir.Scene.from_dict(d)
    with pytest.raises(ValueError, match="non-differentiable"):
        render(projective, {"light.position": projective.get("light.position").requires_grad_()}, spp=1)


def test_derived_parameter_errors(highlight):
    with pytest.raises(ValueError, match="both 'light.azimuth' and the parameter it sets"):
        render(highlight, {"light.azimuth": torch.zeros(1), "light.position": torch.zeros(3)}, spp=1)
    with pytest.raises(ValueError, match="expected \\(1,\\)"):
        render(highlight, {"light.azimuth": torch.zeros(2)}, spp=1)
    with pytest.raises(ValueError, match="NaN/Inf"):
        render(highlight, {"light.azimuth": torch.tensor([math.nan])}, spp=1)
    with pytest.raises(TypeError, match="float32"):
        render(highlight, {"light.azimuth": torch.zeros(1, dtype=torch.float64)}, spp=1)
    with pytest.raises(KeyError, match="unknown scene parameter"):
        render(highlight, {"light.azimuthh": torch.zeros(1)}, spp=1)


def test_nn_parameter_azimuth_gets_a_gradient(highlight):
    az = torch.nn.Parameter(torch.tensor([0.5]))
    target = render(highlight, {"light.azimuth": torch.tensor([0.0])}, spp=4, seed=7)
    img = render(highlight, {"light.azimuth": az}, spp=4, seed=8)
    LOILoss(transform="reinhard")(img, target).backward()
    assert az.grad is not None and torch.isfinite(az.grad).all() and az.grad.abs().item() > 0


def test_derived_is_reachable_after_a_bare_import_torchir():
    """The README writes ``torchir.derived.rigid_transform(...)`` after ``import torchir`` alone
    (it raised AttributeError); a fresh interpreter, as a user's script starts."""
    import subprocess
    import sys

    code = "import torchir; print(torchir.derived.rigid_transform.__name__, 'derived' in dir(torchir))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["rigid_transform", "True"]
