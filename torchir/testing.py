"""Gradient checks for render-based functions: a ``torch.autograd.gradcheck`` for Monte Carlo.

``torch.autograd.gradcheck`` needs float64 and a deterministic function; a render is float32
and noisy. :func:`gradcheck` instead compares, for each parameter and a few random directions
``v``, the autograd directional derivative ``<grad f, v>`` with the central difference
``(f(p + eps v) - f(p - eps v)) / (2 eps)``. Both sides of the difference use the *same* seed
(common random numbers), so the difference is the derivative of one fixed Monte Carlo
estimate, not of noise. Over several seeds both are unbiased estimates of the same directional
derivative, so their per-seed difference ``d_s`` has mean zero for a correct gradient; the check
passes when ``|mean(d)| <= n_sigma * stderr(d) + atol + rtol * |mean(FD)|``. The ``atol`` and
``rtol`` terms absorb float32 rounding and the finite-difference truncation error.

Example:
    >>> from torchir.testing import gradcheck
    >>> def loss(p, seed):
    ...     return render(scene, p, spp=8, seed=seed).mean()
    >>> gradcheck(loss, {"red.reflectance.value": red})
    True
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch

from .device_audit import DeviceAudit, device_audit

__all__ = ["gradcheck", "check_gradients", "GradcheckError", "GradcheckReport", "DirectionCheck", "device_audit", "DeviceAudit"]

LossFn = Callable[[dict[str, torch.Tensor], int], torch.Tensor]


class GradcheckError(AssertionError):
    """A render gradient disagrees with finite differences beyond its noise."""


@dataclass(frozen=True)
class DirectionCheck:
    """One parameter, one direction: autograd vs central differences over seeds."""

    name: str
    direction: int
    autograd: float  # mean over seeds of <grad f, v>
    finite_difference: float  # mean over seeds of the central difference
    stderr: float  # standard error of the per-seed difference
    tolerance: float  # the bound |autograd - finite_difference| had to meet
    passed: bool

    @property
    def error(self) -> float:
        return abs(self.autograd - self.finite_difference)


@dataclass
class GradcheckReport:
    checks: list[DirectionCheck] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list[DirectionCheck]:
        return [c for c in self.checks if not c.passed]

    def __str__(self) -> str:
        head = f"{'parameter':40s} {'dir':>3s} {'autograd':>12s} {'central FD':>12s} {'|diff|':>10s} {'tolerance':>10s}  ok"
        rows = [
            f"{c.name[:40]:40s} {c.direction:3d} {c.autograd:12.5g} {c.finite_difference:12.5g} "
            f"{c.error:10.3g} {c.tolerance:10.3g}  {'yes' if c.passed else 'NO'}"
            for c in self.checks
        ]
        return "\n".join([head, *rows])


def _direction(tensor: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """A random unit direction of ``tensor``'s shape (Gaussian, normalised)."""
    v = torch.randn(tensor.shape, generator=generator, dtype=torch.float64, device="cpu")  # the same on every device
    return (v / v.norm()).to(device=tensor.device, dtype=tensor.dtype)


def check_gradients(
    fn: LossFn,
    params: Mapping[str, torch.Tensor],
    *,
    seeds: Sequence[int] = tuple(range(8)),
    directions: int = 2,
    eps: float = 1e-2,
    rtol: float = 0.05,
    atol: float = 1e-5,
    n_sigma: float = 4.0,
    generator_seed: int = 0,
) -> GradcheckReport:
    """Compare autograd with central differences for every parameter of ``params``.

    Args:
        fn: ``fn(params, seed) -> scalar tensor``, deterministic for a given seed (it should
            pass ``seed`` to the render calls it makes).
        params: ``{name: tensor}``; the tensors that require grad are checked, one at a time.
        seeds: the seeds to average over; >= 3 so that the standard error is estimable.
        directions: random unit directions per parameter.
        eps: finite-difference step along a unit direction (float32 renders need ~1e-2).
        rtol, atol: allowance for float32 rounding and the O(eps^2) truncation error.
        n_sigma: how many standard errors of Monte Carlo noise the difference may span.
        generator_seed: seed of the random directions.

    Returns:
        A :class:`GradcheckReport` (``str()`` prints a table; ``.passed``, ``.failed``).
    """
    seeds = list(seeds)
    if len(seeds) < 3:
        raise ValueError("check_gradients needs at least 3 seeds to estimate the noise")
    names = [n for n, t in params.items() if t.requires_grad]
    if not names:
        raise ValueError("no tensor in params requires grad: nothing to check")
    base = {n: t.detach() for n, t in params.items()}
    generator = torch.Generator(device="cpu").manual_seed(generator_seed)
    report = GradcheckReport()
    for name in names:
        for k in range(directions):
            v = _direction(base[name], generator)
            ad, fd = [], []
            for seed in seeds:
                x = base[name].clone().requires_grad_(True)
                (grad,) = torch.autograd.grad(fn({**base, name: x}, seed), x)
                ad.append(float((grad * v).sum()))
                with torch.no_grad():
                    up = float(fn({**base, name: base[name] + eps * v}, seed))
                    down = float(fn({**base, name: base[name] - eps * v}, seed))
                fd.append((up - down) / (2 * eps))
            diff = torch.tensor(ad, dtype=torch.float64, device="cpu") - torch.tensor(fd, dtype=torch.float64, device="cpu")
            stderr = float(diff.std(unbiased=True)) / math.sqrt(len(seeds))
            ad_mean, fd_mean = sum(ad) / len(ad), sum(fd) / len(fd)
            tolerance = n_sigma * stderr + atol + rtol * abs(fd_mean)
            report.checks.append(
                DirectionCheck(name, k, ad_mean, fd_mean, stderr, tolerance, abs(ad_mean - fd_mean) <= tolerance)
            )
    return report


def gradcheck(fn: LossFn, params: Mapping[str, torch.Tensor], *, raise_exception: bool = True, **kwargs) -> bool:
    """Like ``torch.autograd.gradcheck`` for render-based functions (see :func:`check_gradients`).

    Returns ``True`` when every parameter passes; otherwise raises :class:`GradcheckError` with
    the report naming the failing parameters (or returns ``False`` if ``raise_exception`` is off).
    """
    report = check_gradients(fn, params, **kwargs)
    if not report.passed and raise_exception:
        failed = sorted({c.name for c in report.failed})
        raise GradcheckError(f"gradient check failed for {', '.join(failed)}:\n{report}")
    return report.passed
