"""``probe_pixels``: one-path radiance and forward-mode derivatives on low-resolution grids.

Stage 1 of the adaptive pixel sampler (Yan et al. 2025, Alg. 1 lines 2-9) needs, per low-res
pixel, a few *one-path* estimates of the radiance ``I`` (for the loss adjoint, factor ``p1``)
and of the directional derivative ``t = sum_k v_k dI/dθ_k`` along a Rademacher tangent ``v``
(factor ``p2``; this probe replaces the paper's custom squared forward-mode pass: as
``E[v_k v_l] = δ_kl``, ``E[t²]`` equals the one-path estimate of ``p2``). Camera rays are
generated directly on each grid (a low-res pixel covers the same film area as the block of
full-res pixels under it), so no film resize is needed per level, and every level and pass
runs in one wavefront.

The derivative is a central difference along the tangent with common random numbers (the
same paths at ``θ + h v`` and ``θ - h v``), not prb's Forward mode: in Mitsuba 3.9 / Dr.Jit 1.5
prb's Forward pass (``dr.forward_to`` inside its loop) cannot be driven per ray from Python
("edge ... lies outside of the current dr.isolate_grad() scope", or zero tangents through a
custom op). For the continuous parameters pixel sampling targets (albedo, roughness,
textures, emitters) the two agree to O(h²); a rare path whose discrete choices flip between
the two renders gives one large value, which the sampler's blur and uniform mixing absorb.
The outputs only steer sampling, so the pixel estimator stays unbiased either way.
Not differentiable.
"""
from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from .. import backend
from ..backend import gc_paused
from ..scene import Scene
from . import _args
from .render_pixels import _check_integrator, _pixel_passes

__all__ = ["probe_pixels"]


def _grid_lanes(grids: Sequence[tuple[int, int]], passes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-lane pixel x, y and grid width, height: for each grid, ``passes`` copies of its
    pixels in row-major order (pass-major)."""
    xs, ys, ws, hs = [], [], [], []
    for h, w in grids:
        y, x = np.divmod(np.arange(h * w, dtype=np.float32), np.float32(w))
        for _ in range(passes):
            xs.append(x)
            ys.append(y)
            ws.append(np.full(h * w, w, np.float32))
            hs.append(np.full(h * w, h, np.float32))
    return tuple(np.concatenate(a) for a in (xs, ys, ws, hs))  # type: ignore[return-value]


@functools.lru_cache(maxsize=8)
def _lanes(variant: str, grids: tuple[tuple[int, int], ...], passes: int) -> tuple[mi.Float, ...]:
    """The lane arrays of :func:`_grid_lanes` as Dr.Jit arrays, made once per configuration:
    a frozen pass given freshly built copies of these constant arrays re-records on every
    call (measured: one recording per call instead of one in all), so every refresh reuses
    the same arrays."""
    return tuple(mi.Float(a) for a in _grid_lanes(grids, passes))


def _to_drjit(scene: Scene, name: str, value: torch.Tensor):
    # through DLPack, on the tensor's own device (no host copy on a GPU; the result is evaluated
    # before the caller's optimiser can change the tensor in place)
    return scene.to_drjit(name, mi.TensorXf(value.detach().to(torch.float32).contiguous()))


def _one_path(scene: Scene, values: dict[str, torch.Tensor], lanes: tuple, sensor: int, seed: int) -> mi.Color3f:
    """Radiance (times the camera ray weight) of one path per lane, with ``values`` bound."""
    with gc_paused():
        scene.bind({name: _to_drjit(scene, name, v) for name, v in values.items()})
        result = _pixel_passes(scene).one_path(sensor, lanes, seed)  # frozen like render_pixels
        dr.eval(result)
    return result


def probe_pixels(
    scene: Scene,
    params: Mapping[str, torch.Tensor] | None,
    grids: Sequence[tuple[int, int]],
    passes: int = 4,
    seed: int = 0,
    sensor: int = 0,
    tangents: Mapping[str, torch.Tensor] | None = None,
    step: float = 1e-2,
) -> tuple[list[torch.Tensor], list[torch.Tensor] | None]:
    """One-path radiance (and derivative along ``tangents``) of every pixel of each grid.

    Args:
        scene: a scene with a path-replay integrator (``prb``, ``prb_basic``, ``prbvolpath``).
        params: ``{name: value}`` bound for the probe (as for :func:`render`; not differentiated).
        grids: ``[(h, w), ...]`` grid sizes over the full film.
        passes: independent one-path estimates per pixel, >= 1.
        seed: seed of the paths.
        sensor: sensor index.
        tangents: ``{name: tensor of the parameter's shape}``, the forward-mode direction
            (e.g. Rademacher ±1 entries); ``None`` computes the radiance only.
        step: finite-difference step ``h`` along the tangent.

    Returns:
        ``(radiance, derivative)``: per grid a ``(passes, C, h, w)`` tensor; ``derivative`` is
        ``None`` without ``tangents``. Both already include the camera ray weight.
    """
    scene = _args.check_scene(scene)
    _check_integrator(scene)
    passes = _args.check_count("passes", passes)
    seed = _args.check_seed("seed", seed)
    scene.sensor(sensor)
    if not grids:
        raise ValueError("grids is empty")
    for h, w in grids:
        if h < 1 or w < 1:
            raise ValueError(f"grid sizes must be >= 1, got {(h, w)}")
    values = {} if params is None else {k: v.detach() for k, v in params.items()}
    tangents = {} if tangents is None else dict(tangents)
    unknown = set(tangents) - set(values)
    if unknown:
        raise KeyError(f"tangents for parameters not in params: {sorted(unknown)}")
    scene.check_values(values)
    for name, t in tangents.items():
        if tuple(t.shape) != tuple(values[name].shape):
            raise ValueError(f"tangent of {name!r} has shape {tuple(t.shape)}, the parameter {tuple(values[name].shape)}")

    lanes = _lanes(backend.variant(), tuple((int(h), int(w)) for h, w in grids), passes)
    if not tangents:
        return _split(_one_path(scene, values, lanes, sensor, seed), grids, passes), None
    shifted = [{**values, **{k: values[k] + sign * step * tangents[k].to(values[k]) for k in tangents}} for sign in (1.0, -1.0)]
    plus, minus = (_one_path(scene, v, lanes, sensor, seed) for v in shifted)  # common random numbers
    radiance = _split(0.5 * (plus + minus), grids, passes)
    derivative = _split((plus - minus) / (2.0 * step), grids, passes)
    return radiance, derivative


def _split(values: mi.Color3f, grids: Sequence[tuple[int, int]], passes: int) -> list[torch.Tensor]:
    flat = mi.TensorXf(dr.ravel(values), (dr.width(values), 3)).torch()
    out, start = [], 0
    for h, w in grids:
        n = passes * h * w
        out.append(flat[start : start + n].reshape(passes, h, w, 3).permute(0, 3, 1, 2).contiguous())
        start += n
    return out
