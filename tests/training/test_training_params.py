"""Optimised scene parameters (torchir.training.parameters) without a renderer: config values
to tensors, the latent transforms and their inverses, bounds and their errors."""
from __future__ import annotations

import pytest
import torch

from torchir.training.parameters import ParameterConfig, SceneParameter, is_image_file, resolve_value


def _param(initial, **config) -> SceneParameter:
    return SceneParameter("obj.value", torch.as_tensor(initial, dtype=torch.float32), ParameterConfig(**config))


# ------------------------------------------------------------------------------ config values
def test_config_defaults_are_documented_ones():
    c = ParameterConfig()
    assert (c.init, c.bounds, c.lr, c.transform, c.seed, c.truth) == (0.5, None, None, "none", 0, None)


def test_is_image_file_by_suffix_any_case():
    assert all(is_image_file(s) for s in ("a.exr", "b.PNG", "dir/c.Jpeg", "d.hdr", "e.pfm", "f.jpg"))
    assert not any(is_image_file(s) for s in ("scene", "random", "a.txt", "exr", 0.5, [0.5]))


def test_resolve_constant_and_lists():
    """A number broadcasts to the shape, a list of fewer or as many dims too, one of more dims
    is reshaped; always a float32 tensor of its own."""
    shape = torch.Size((2, 3))
    x = resolve_value(0.25, shape, torch.zeros(shape), None, 0, "init")
    assert x.dtype == torch.float32 and x.shape == shape and bool((x == 0.25).all())
    x[0, 0] = 1.0  # its own memory, not an expanded view of one value
    assert x[1, 2].item() == 0.25
    row = resolve_value([[1.0, 2.0, 3.0]], shape, torch.zeros(shape), None, 0, "init")  # (1, 3): broadcast
    assert row.tolist() == [[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]
    flat = resolve_value([[1, 2], [3, 4]], torch.Size((4,)), torch.zeros(4), None, 0, "init")  # more dims: reshape
    assert flat.tolist() == [1.0, 2.0, 3.0, 4.0] and flat.dtype == torch.float32
    with pytest.raises(ValueError, match=r"^parameters\['k'\]\.init has shape \(2,\), which does not fit the parameter's shape \(2, 3\)"):
        resolve_value([0.1, 0.2], shape, torch.zeros(shape), None, 0, "parameters['k'].init")


def test_resolve_scene_is_a_copy():
    scene = torch.rand(3)
    x = resolve_value("scene", scene.shape, scene, None, 0, "init")
    assert torch.equal(x, scene)
    x += 1
    assert not torch.equal(x, scene)


def test_resolve_random_is_seeded_uniform_in_bounds():
    """``lo + (hi - lo) U`` with U drawn from ``seed``: the same draws rescaled for any bounds,
    default [0, 1], filling the range."""
    shape = torch.Size((2000,))
    unit = resolve_value("random", shape, torch.zeros(shape), None, 7, "init")
    assert torch.equal(unit, resolve_value("random", shape, torch.zeros(shape), None, 7, "init"))
    assert not torch.equal(unit, resolve_value("random", shape, torch.zeros(shape), None, 8, "init"))
    assert 0 <= unit.min() < 0.01 and 0.99 < unit.max() <= 1  # P(fail) ~ 2 * 0.99^2000
    scaled = resolve_value("random", shape, torch.zeros(shape), (2.0, 5.0), 7, "init")
    torch.testing.assert_close(scaled, 2.0 + 3.0 * unit)


def test_resolve_image_file(monkeypatch):
    """An image file is read as (C, H, W) (torchir.imageio, tested there; stubbed here so no
    renderer starts) and given in Mitsuba's (H, W, C) layout, contiguous; its shape must fit."""
    import torchir.imageio

    image = torch.rand(3, 4, 5)
    read = []
    monkeypatch.setattr(torchir.imageio, "read_image", lambda path: read.append(path) or image)
    x = resolve_value("dir/tex.EXR", torch.Size((4, 5, 3)), torch.zeros(4, 5, 3), None, 0, "init")
    assert read == ["dir/tex.EXR"] and x.is_contiguous()
    torch.testing.assert_close(x, image.permute(1, 2, 0), rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"^init: image 'tex\.png' is \(4, 5, 3\) \(H, W, C\), the parameter is \(5, 4, 3\)$"):
        resolve_value("tex.png", torch.Size((5, 4, 3)), torch.zeros(5, 4, 3), None, 0, "init")


def test_resolve_unknown_string():
    with pytest.raises(ValueError, match=r"^init must be a number, a list, 'random', 'scene' or an image file, got 'randm'"):
        resolve_value("randm", torch.Size((3,)), torch.zeros(3), None, 0, "init")


# ------------------------------------------------------------------------------ transforms
@pytest.mark.parametrize(
    ("transform", "bounds", "initial"),
    [("none", None, [-2.0, 0.3, 7.0]), ("none", (0, 1), [0.0, 0.3, 1.0]), ("sigmoid", None, [0.2, 0.5, 0.9]),
     ("sigmoid", (2, 6), [2.5, 4.0, 5.9]), ("log", None, [1e-3, 0.5, 40.0])],
)
def test_forward_inverts_the_initial_value(transform, bounds, initial):
    """The latent starts at ``T^-1(x0)``: ``forward()`` gives the initial value back, float32."""
    p = _param(torch.tensor(initial, dtype=torch.float64), transform=transform, bounds=bounds)
    assert p.latent.dtype == torch.float32 and p.forward().dtype == torch.float32
    torch.testing.assert_close(p.forward(), torch.tensor(initial), rtol=1e-5, atol=1e-6)


def test_latents_are_the_documented_maps():
    """``none``: u = x; ``log``: u = log x; ``sigmoid``: u = logit((x - lo) / (hi - lo))."""
    x = torch.tensor([0.25, 0.5, 0.75])
    torch.testing.assert_close(_param(x).latent.data, x)
    torch.testing.assert_close(_param(x, transform="log").latent.data, x.log())
    torch.testing.assert_close(_param(1 + 2 * x, transform="sigmoid", bounds=(1, 3)).latent.data, torch.logit(x))
    p = _param(x, transform="sigmoid")
    assert p.bounds == (0.0, 1.0)  # the sigmoid's default range
    torch.testing.assert_close(p.latent.data, torch.logit(x))


def test_latent_does_not_alias_the_initial_value():
    x = torch.tensor([0.25, 0.5])
    p = SceneParameter("k", x, ParameterConfig())
    x += 1
    assert p.latent.tolist() == [0.25, 0.5]


def test_sigmoid_init_on_an_end_of_its_range_is_refused():
    """x0 on a bound is where the sigmoid's slope is ~0 (it was clamped to 1e-4 of the range and
    barely moved): refused with what to do; just inside, the latent is finite."""
    with pytest.raises(ValueError, match=r"'obj.value': init has 1 value\(s\) on an end of the sigmoid's range \[2.0, 6.0\] "
                       r"\(e.g. 6\).*Start inside the range"):
        _param([2.5, 6.0], transform="sigmoid", bounds=(2, 6))
    with pytest.raises(ValueError, match="on an end of the sigmoid's range"):
        _param([0.0], transform="sigmoid")
    p = _param([2.0 + 1e-3, 6.0 - 1e-3], transform="sigmoid", bounds=(2, 6))
    assert bool(torch.isfinite(p.latent).all())
    torch.testing.assert_close(p.forward().detach(), torch.tensor([2.001, 5.999]))


@pytest.mark.parametrize("lr", [-1.0, 0.0, float("nan"), float("inf")])
def test_a_learning_rate_that_is_not_positive_and_finite_is_refused(lr):
    """A negative rate would run gradient ascent without a word."""
    with pytest.raises(ValueError, match=r"'obj.value': lr must be a finite number > 0 \(gradient descent\)"):
        _param([0.5], lr=lr)
    assert _param([0.5], lr=0.01).latent.item() == 0.5  # the control


def test_project_clamps_only_bounded_plain_values():
    with torch.no_grad():
        bounded = _param([0.5, 0.5], bounds=(0, 1))
        bounded.latent.copy_(torch.tensor([-0.5, 1.5]))
        free = _param([0.5, 0.5])
        free.latent.copy_(torch.tensor([-0.5, 1.5]))
        squashed = _param([0.5, 0.5], transform="sigmoid")
        squashed.latent.copy_(torch.tensor([-9.0, 9.0]))
    for p in (bounded, free, squashed):
        p.project()
    assert bounded.latent.tolist() == [0.0, 1.0]
    assert free.latent.tolist() == [-0.5, 1.5] and squashed.latent.tolist() == [-9.0, 9.0]


def test_attributes_and_repr():
    p = SceneParameter("ball.bsdf.alpha", torch.full((2, 3), 0.2), ParameterConfig(bounds=(0, 1), transform="sigmoid"))
    assert p.key == "ball.bsdf.alpha" and p.transform == "sigmoid"
    assert p.bounds == (0.0, 1.0) and all(type(b) is float for b in p.bounds)
    assert repr(p) == "SceneParameter(key='ball.bsdf.alpha', shape=(2, 3), transform='sigmoid', bounds=(0.0, 1.0))"
    assert _param([1.0], transform="log").bounds is None and _param([1.0]).bounds is None


# ------------------------------------------------------------------------------ errors
@pytest.mark.parametrize("bounds", [(1, 0), (0.5, 0.5)])
def test_bounds_must_be_increasing(bounds):
    with pytest.raises(ValueError, match=rf"^parameter 'obj.value': bounds must satisfy lo < hi, got \[{bounds[0]}, {bounds[1]}\]$"):
        _param([0.5], bounds=bounds)


def test_log_refuses_bounds_and_non_positive_values():
    with pytest.raises(ValueError, match=r"^parameter 'obj.value': transform 'log' keeps values positive; drop 'bounds'$"):
        _param([0.5], transform="log", bounds=(0.1, 1))
    for bad in ([0.5, 0.0], [-1.0]):
        with pytest.raises(ValueError, match=r"^parameter 'obj.value': transform 'log' needs a positive initial value$"):
            _param(bad, transform="log")


def test_init_outside_bounds_is_refused_with_examples():
    """Bounds are inclusive; the message counts every value outside and shows up to 4."""
    _param([0.0, 1.0], bounds=(0, 1))  # a sigmoid's ends are refused instead (test_sigmoid_init_on_an_end_of_its_range_is_refused)
    bad = [-0.5, 0.2, 1.5, 2.0, 3.0, 4.0, -1.0]
    with pytest.raises(ValueError, match=r"^parameter 'obj.value': init has 6 value\(s\) outside bounds \[0.0, 1.0\] \(e.g. \[-0.5, 1.5, 2.0, 3.0\]\): change init or bounds$"):
        _param(bad, bounds=(0, 1))
    with pytest.raises(ValueError, match=r"init has 1 value\(s\) outside bounds \[2.0, 6.0\] \(e.g. \[1.123457\]\)"):
        _param([1.1234567, 3.0], bounds=(2, 6), transform="sigmoid")


# ------------------------------------------------------------------------------ per-entry bounds
def test_per_entry_bounds_clamp_each_entry_and_pin_where_equal():
    """``bounds: [[-1, -1, 0.2], [1, 1, 0.2]]``: a translation free in x and y, its z pinned."""
    p = _param([0.1, -0.3, 0.2], bounds=([-1, -1, 0.2], [1, 1, 0.2]))
    with torch.no_grad():
        p.latent.copy_(torch.tensor([5.0, -5.0, 3.0]))
    p.project()
    torch.testing.assert_close(p(), torch.tensor([1.0, -1.0, 0.2]))
    assert "per entry" in repr(p)
    with pytest.raises(ValueError, match=r"init has 1 value\(s\) outside bounds \[\[-1.0, -1.0, 0.2.*per entry"):
        _param([0.1, -0.3, 0.0], bounds=([-1, -1, 0.2], [1, 1, 0.2]))  # init off the pinned value


def test_per_entry_bounds_with_a_sigmoid_and_a_random_init():
    x = torch.tensor([[0.5, 2.0, 20.0], [0.25, 1.5, 12.0]])
    p = _param(x, transform="sigmoid", bounds=([0, 1, 10], [1, 3, 30]))  # one range per colour channel
    torch.testing.assert_close(p(), x, atol=1e-5, rtol=1e-5)
    with torch.no_grad():
        p.latent.fill_(50.0)
    torch.testing.assert_close(p(), torch.tensor([1.0, 3.0, 30.0]).expand(2, 3))
    value = resolve_value("random", torch.Size([4, 3]), torch.zeros(4, 3), ([0, 1, 10], [1, 3, 30]), 0, "init")
    assert bool(((value >= torch.tensor([0, 1, 10])) & (value <= torch.tensor([1, 3, 30]))).all())
    assert float(value[:, 2].min()) > 1.0  # drawn in each entry's own range


@pytest.mark.parametrize(
    ("bounds", "transform", "message"),
    [(([0, 0], [1, 1, 1]), "none", r"bounds' lo has shape \(2,\), which does not broadcast to the parameter's shape \(3,\)"),
     (([0, 1, 0], [1, 0, 1]), "none", r"lo <= hi for every entry"),
     (([0, 0.5, 0], [1, 0.5, 1]), "sigmoid", r"lo < hi \(the sigmoid's range\) for every entry")],
)
def test_per_entry_bounds_errors(bounds, transform, message):
    with pytest.raises(ValueError, match=message):
        _param([0.5, 0.5, 0.5], bounds=bounds, transform=transform)
