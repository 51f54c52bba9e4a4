"""Image-space pixel samplers: which pixels to render at each optimisation step.

The adaptive sampler is that of *Image-space Adaptive Sampling for Fast Inverse Rendering*
(SIGGRAPH 2025), "the paper" below; equation numbers are the paper's.

Three strategies share one class, :class:`PixelSampler`; they differ only in the pmf:

===========================  ===================================  ==============================
class                        pmf ``p_j``                          Stage 1 (every ``refresh_every``)
===========================  ===================================  ==============================
:class:`UniformPixelSampler`  ``1 / m``                            none
:class:`LossPixelSampler`     ``∝ sqrt(E[(∂L/∂I_j)^2])`` (Eq. 5)   low-res one-path renders
:class:`AdaptivePixelSampler` ``∝ sqrt(p1_j p2_j)`` (Eq. 8)        renders + derivative probe
===========================  ===================================  ==============================

``sample()`` draws ``N`` pixel indices i.i.d. from the pmf (mixed with the uniform pmf by
``alpha``, so every pixel keeps ``p_j >= alpha / m``) and returns importance weights
``w_n = 1 / (N m p_{j_n})``: for any per-pixel loss ``l`` over the ``m`` pixels,
``(w * l[index]).sum()`` is an unbiased estimate of ``l.mean()``. Rendering the drawn pixels
with :func:`torchir.functions.render_pixels` (whose gradient pass replays independent paths,
as Eq. 4 requires) makes the gradient of that sum an unbiased estimate of the full-image gradient.
The pmf only steers sampling: however rough Stage 1 is, the estimate stays unbiased.
"""
from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from . import _pmf

__all__ = ["AdaptivePixelSampler", "LossPixelSampler", "PixelBatch", "PixelSampler", "UniformPixelSampler"]


class PixelBatch(NamedTuple):
    """Pixels drawn for one step.

    Attributes:
        index: ``(N,)`` int64 global pixel indices over all views: view ``index // (H*W)``,
            pixel ``index % (H*W)`` (flat ``y * W + x``).
        weight: ``(N,)`` float32 importance weights ``1 / (N m p[index])``.
    """

    index: torch.Tensor
    weight: torch.Tensor


class SampledLoss(NamedTuple):
    """One pixel batch rendered and scored (see :func:`sampled_loss`).

    Attributes:
        loss: the importance-weighted loss, an unbiased estimate of the full-image loss.
        radiance, target: ``(N, C)`` rendered and target values of the drawn pixels, grouped by
            view, in raster order within a view.
        weight: ``(N,)`` their importance weights, in the same order.
    """

    loss: torch.Tensor
    radiance: torch.Tensor
    target: torch.Tensor
    weight: torch.Tensor


def sampled_loss(
    scene: Any,
    params: Mapping[str, torch.Tensor],
    batch: PixelBatch,
    targets: torch.Tensor | Sequence[torch.Tensor],
    views: Sequence[int],
    loss: nn.Module,
    seed: Callable[[int], int],
    spp: int = 1,
    spp_grad: int | None = None,
) -> SampledLoss:
    """The importance-weighted loss of one pixel batch.

    The drawn pixels are rendered with :func:`torchir.functions.render_pixels` (the pixels of
    every view in one wavefront), whose gradient pass replays independent paths (Eq. 4), and
    scored with the per-pixel loss:
    ``loss = sum_n w_n l_n``, with ``l_n`` from ``loss.pixel_terms``. Backpropagating it gives
    an unbiased estimate of the gradient of ``loss`` over the full images of ``views``.

    Args:
        scene: the :class:`torchir.Scene` the sampler draws for.
        params: parameters bound for the render (as for :func:`torchir.functions.render`).
        batch: pixels drawn from ``views`` (``sampler.sample(views)``).
        targets: ``(V', C, H, W)`` or a list of ``(C, H, W)``, one per entry of ``views``.
        views: the sensors of the batch, in the order of ``targets``.
        loss: a per-pixel loss module with ``pixel_terms``.
        seed: ``view -> seed`` of the primal paths (with draws in several views: of the first).
        spp, spp_grad: paths per drawn pixel in the primal and gradient passes.
    """
    from ..functions import render_pixels  # Dr.Jit side, loaded on first use

    h, w = scene.resolution
    draws = _draws_by_view(batch.index, views, h * w)
    listed = [view for _, view, _, _ in draws]  # the views with draws: traced in one wavefront (one frozen pass)
    index = torch.cat([k * h * w + pixels for k, (_, _, _, pixels) in enumerate(draws)])
    sensor = listed[0] if len(listed) == 1 else listed
    radiance = render_pixels(scene, params, index, spp=spp, seed=seed(listed[0]), sensor=sensor, spp_grad=spp_grad)
    # the draws live on the host: move the drawn pixels' indices and weights to the images' device
    target = torch.cat([targets[position].flatten(1).t()[pixels.to(targets[position].device)] for position, _, _, pixels in draws])
    weight = batch.weight[torch.cat([chosen for _, _, chosen, _ in draws])].to(radiance.device)
    terms = loss.pixel_terms(radiance, target, len(views) * h * w)
    return SampledLoss((weight * terms).sum(), radiance, target, weight)


def _draws_by_view(index: torch.Tensor, views: Sequence[int], pixels_per_view: int) -> list[tuple[int, int, torch.Tensor, torch.Tensor]]:
    """``(position in views, view, positions in the batch, pixels)`` of each view with draws,
    in raster order: i.i.d. draws come in random order, and traced in raster order neighbouring
    lanes take coherent paths, which makes render + backward faster (measured:
    docs/pixel-sampling.md, "Measurements behind the design")."""
    if len(views) == 1 and index.numel() > 0:  # one view (the usual step): no filtering when every draw is in it
        first = views[0] * pixels_per_view
        low, high = (int(v) for v in torch.aminmax(index))
        if first <= low and high < first + pixels_per_view:
            pixels, chosen = (index - first).sort()  # the permutation argsort() gives
            return [(0, views[0], chosen, pixels)]
    view_of, local = index // pixels_per_view, index % pixels_per_view
    out = []
    for position, view in enumerate(views):
        chosen = (view_of == view).nonzero().squeeze(1)
        if chosen.numel() > 0:
            chosen = chosen[local[chosen].argsort()]
            out.append((position, view, chosen, local[chosen]))
    return out


def _check_budget(budget: object, pixel_count: int) -> int:
    if isinstance(budget, bool) or not isinstance(budget, (int, float)):
        raise TypeError(f"budget must be an int (pixel draws) or a float in (0, 1] (fraction of pixels), got {type(budget).__name__}")
    if isinstance(budget, float):
        if not 0.0 < budget <= 1.0:
            raise ValueError(f"a fractional budget must be in (0, 1], got {budget}; give an int for more draws than pixels")
        return max(1, round(budget * pixel_count))
    if budget < 1:
        raise ValueError(f"budget must be >= 1 pixel draw, got {budget}")
    return budget


def _stage1_grids(size: tuple[int, int], scale: int, min_side: int, levels: int) -> list[tuple[int, int]]:
    """Stage-1 grid sizes, finest first: level 0 is ``size / scale`` but no smaller than
    ``min_side`` (nor than the image); level ``d`` halves it ``d`` times while its shorter side
    stays >= 4 px."""
    h, w = size
    factor = min(float(scale), max(1.0, min(h, w) / min_side))
    h0, w0 = max(1, round(h / factor)), max(1, round(w / factor))
    grids = [(h0, w0)]
    for d in range(1, levels + 1):
        hd, wd = round(h0 / 2**d), round(w0 / 2**d)
        if min(hd, wd) < 4:
            break
        grids.append((hd, wd))
    return grids


def _rademacher(value: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    bits = torch.randint(0, 2, value.shape, generator=generator, device="cpu")  # drawn on the host
    return (2 * bits - 1).to(device=value.device, dtype=torch.float32)


class PixelSampler:
    """Base class: a pixel pmf over all views, i.i.d. draws and importance weights.

    Args:
        scene: the :class:`torchir.Scene` to render (Stage 1 needs it); or ``None`` for
            torch-only use with ``resolution`` and ``views``.
        budget: pixel draws per step: an int ``N >= 1``, or a float in ``(0, 1]`` (fraction of
            all pixels of all views, ``max(1, round(f m))``). ``N > m`` is allowed (draws are
            with replacement). Over all processes when distributed (:meth:`distribute`).
        refresh_every: steps between Stage-1 refreshes (``R``; alias ``update_every``).
        levels: multi-resolution depth ``D`` (capped so the coarsest grid has sides >= 4 px).
        alpha: weight of the uniform pmf mixed in, in ``[0, 1]`` (so every ``p_j >= alpha / m``).
        seed: seed of the index draws and derivative probes (a ``torch.Generator``) and of
            Stage 1's paths.
        resolution: ``(H, W)`` of every view (default: the scene's).
        views: number of views (default: the scene's sensor count).
        scale: Stage-1 downsampling factor ``s`` (the paper leaves it open).
        min_side: smallest Stage-1 side at level 0, in pixels (default 32).
        stage1_spp: one-path passes per Stage-1 pixel (``S``).
        multires: level weighting, ``"equal"`` or ``"paper"`` (the literal sum of Eq. 18).
        sigma: Stage-1 denoising blur in low-res pixels.
        fd_step: finite-difference step of the derivative probe (see
            :func:`torchir.functions.probe.probe_pixels`).

    Shape:
        ``pdf``: ``(V*H*W,)`` float64; ``pdf_image()``: ``(V, H, W)``.
    """

    strategy = "base"
    uses_stage1 = False  # runs Stage 1 on update()
    uses_derivatives = False  # Stage 1 also probes p2

    def __init__(
        self,
        scene: Any = None,
        budget: float = 0.05,
        refresh_every: int = 20,
        levels: int = 4,
        alpha: float = 0.1,
        seed: int = 0,
        resolution: tuple[int, int] | None = None,
        views: int | None = None,
        scale: int = 4,
        min_side: int = 32,
        stage1_spp: int = 4,
        multires: str = "equal",
        sigma: float = 1.0,
        fd_step: float = 1e-2,
        update_every: int | None = None,
    ) -> None:
        if update_every is not None:
            refresh_every = update_every  # the name DESIGN.md uses
        self.scene = scene
        if scene is not None:
            sizes = {scene.sensor_resolution(v) for v in range(scene.sensor_count)}
            if len(sizes) > 1:
                raise ValueError(f"pixel samplers need every sensor at one film size, the scene has {sorted(sizes)}")
            scene_res, scene_views = scene.resolution, scene.sensor_count
            if resolution is not None and tuple(resolution) != tuple(scene_res):
                raise ValueError(f"resolution {tuple(resolution)} differs from the scene's {tuple(scene_res)}")
            if views is not None and views != scene_views:
                raise ValueError(f"views={views} differs from the scene's {scene_views} sensor(s)")
            resolution, views = scene_res, scene_views
        if resolution is None:
            raise ValueError("give a scene, or resolution=(H, W) (and views) for torch-only use")
        if isinstance(resolution, int):
            resolution = (resolution, resolution)
        h, w = (int(r) for r in resolution)
        views = 1 if views is None else int(views)
        if h < 1 or w < 1 or views < 1:
            raise ValueError(f"resolution and views must be >= 1, got {(h, w)} and {views}")
        for name, value in (("refresh_every", refresh_every), ("stage1_spp", stage1_spp), ("scale", scale), ("min_side", min_side)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if not isinstance(levels, int) or levels < 0:
            raise ValueError(f"levels must be an int >= 0, got {levels!r}")
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        if alpha == 0.0 and self.uses_stage1:
            warnings.warn("alpha=0: pixels the Stage-1 pmf misses are never drawn, which biases the gradient if they contribute", stacklevel=2)
        if multires not in ("equal", "paper"):
            raise ValueError(f"multires must be 'equal' or 'paper', got {multires!r}")
        if fd_step <= 0 or sigma < 0:
            raise ValueError(f"fd_step must be > 0 and sigma >= 0, got {fd_step} and {sigma}")
        self.resolution, self.views = (h, w), views
        self.pixel_count = views * h * w
        self.budget = _check_budget(budget, self.pixel_count)
        self.refresh_every, self.levels, self.alpha, self.seed = refresh_every, levels, alpha, seed
        self.scale, self.min_side, self.stage1_spp = scale, min_side, stage1_spp
        self.multires, self.sigma, self.fd_step = multires, sigma, fd_step
        self.generator = torch.Generator(device="cpu").manual_seed(seed)  # draws on the host; the pmf lives there too
        self._set_pmf(torch.full((views, h, w), 1.0 / self.pixel_count, dtype=torch.float64, device="cpu"))
        self.last_update: int | None = None  # step of the last refresh
        self.refreshes = 0
        self.rank, self.world = 0, 1  # this process's share of the work (see distribute)
        self.draw_calls = 0  # sample() calls: with several processes, each call's draws are seeded by it
        self._signature: tuple | None = None  # parameter shapes and views of the last refresh
        self._stats: dict[str, float] = {"predicted_gain": 1.0}

    # ------------------------------------------------------------------------------ pmf
    def _set_pmf(self, pmf: torch.Tensor) -> None:
        self._cdf = _pmf.cumulative(pmf)
        # The pmf the draws really follow (differences of the float64 CDF), used for the weights.
        self._pdf = torch.diff(self._cdf, prepend=self._cdf.new_zeros(1))

    @property
    def pdf(self) -> torch.Tensor:
        """The current pmf over all ``V*H*W`` pixels, float64, sums to 1."""
        return self._pdf

    def pdf_image(self) -> torch.Tensor:
        """The current pmf as ``(V, H, W)`` images."""
        return self._pdf.reshape(self.views, *self.resolution)

    @property
    def stage1_grids(self) -> list[tuple[int, int]]:
        """Stage-1 grid sizes ``(h_d, w_d)``, finest first."""
        return _stage1_grids(self.resolution, self.scale, self.min_side, self.levels)

    # ------------------------------------------------------------------------ processes
    def distribute(self, rank: int, world: int) -> None:
        """Share the work with ``world`` processes (DDP), this one being ``rank``.

        ``budget`` then counts over all processes: :meth:`sample` draws this process's share
        (``budget // world``, one more on the first ``budget % world`` ranks) from its own
        random stream (seeded by ``(seed, rank, call)``, so processes never repeat each other's
        pixel layout and a resumed run continues it), and :meth:`update` probes every
        ``world``-th view and sums the maps over processes (``torch.distributed``), so every
        process holds the pmf one process would have computed at that refresh. Each process's
        weighted loss estimates the mean loss over its own views; averaging the processes'
        gradients (as DDP does, over equal view counts) estimates it over all of them.
        """
        if isinstance(world, bool) or not isinstance(world, int) or world < 1:
            raise ValueError(f"world must be an int >= 1, got {world!r}")
        if isinstance(rank, bool) or not isinstance(rank, int) or not 0 <= rank < world:
            raise ValueError(f"rank must be an int in [0, {world}), got {rank!r}")
        if self.budget < world:
            raise ValueError(
                f"budget {self.budget} is smaller than the {world} processes: every process needs at least one pixel draw"
            )
        self.rank, self.world = rank, world

    @property
    def share(self) -> int:
        """Pixel draws of this process per step (``budget`` with one process)."""
        return self.budget // self.world + (1 if self.rank < self.budget % self.world else 0)

    def _draw_generator(self) -> torch.Generator:
        """The generator of this call's draws: the sampler's own with one process; with several,
        a fresh one per call seeded by ``(seed, rank, call)`` (Stage 1 keeps the shared one, which
        every process advances alike)."""
        if self.world == 1:
            return self.generator
        mixed = (self.seed * 0x9E3779B97F4A7C15 + (self.rank + 1) * 0xBF58476D1CE4E5B9 + self.draw_calls * 0x94D049BB133111EB)
        return torch.Generator(device="cpu").manual_seed(mixed % 2**63)

    # ---------------------------------------------------------------------------- draws
    def sample(self, views: Sequence[int] | None = None) -> PixelBatch:
        """Draw ``budget`` pixels (this process's :attr:`share`) i.i.d. from the pmf (restricted
        to ``views`` when given).

        With ``views``, the pmf is conditioned on those views' pixels and the weights are
        ``1 / (N m_V p_V[j])`` with ``m_V`` their pixel count: the estimate is of the mean loss
        over those views, as a full render of that view batch would give.
        """
        n = self.share
        generator = self._draw_generator()
        self.draw_calls += 1
        views = list(range(self.views)) if views is None else sorted({int(v) for v in views})
        if views == list(range(self.views)):
            index, prob = _pmf.draw(self._cdf, n, generator, self._pdf)
            m = self.pixel_count
        else:
            if not views or views[0] < 0 or views[-1] >= self.views:
                raise ValueError(f"views must be a non-empty subset of range({self.views}), got {views}")
            per_view = self.resolution[0] * self.resolution[1]
            sub = self.pdf_image()[views].reshape(-1)
            local, prob = _pmf.draw(_pmf.cumulative(sub), n, generator)
            view_ids = torch.tensor(views, dtype=torch.int64, device=local.device)
            index = view_ids[local // per_view] * per_view + local % per_view
            m = len(views) * per_view
        weight = 1.0 / (n * m * prob)
        self._stats.update(
            ess_fraction=float(weight.sum().square() / weight.square().sum()) / n,  # (Σw)²/Σw² / N
            max_weight_ratio=float(weight.max()) * n,  # largest weight relative to a uniform draw's
        )
        return PixelBatch(index=index.to(torch.int64), weight=weight.to(torch.float32))

    # -------------------------------------------------------------------------- refresh
    def due(self, step: int, params: Mapping[str, torch.Tensor] | None = None, views: Sequence[int] | None = None) -> bool:
        """Whether Stage 1 should run at ``step``: never run yet, ``refresh_every`` steps since
        the last refresh, or the parameters' shapes or the view set changed."""
        if not self.uses_stage1:
            return False
        if self.last_update is None or step - self.last_update >= self.refresh_every or step < self.last_update:
            return True
        return params is not None and self._signature_of(params, views) != self._signature

    def _signature_of(self, params: Mapping[str, torch.Tensor], views: Sequence[int] | None) -> tuple:
        shapes = tuple(sorted((k, tuple(v.shape)) for k, v in params.items()))
        return shapes, tuple(range(self.views)) if views is None else tuple(views)

    def update_from_maps(
        self,
        p1: torch.Tensor | Sequence[torch.Tensor],
        p2: torch.Tensor | Sequence[torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Set the pmf from factor maps ``p1`` and ``p2``, each ``(V, h, w)`` (or a list with one
        map per multi-resolution level, finest first): blur, bilinear upsampling,
        ``sqrt(p1 p2)`` (``sqrt(p1)`` when ``p2`` is None), level weighting and uniform mixing
        (see :func:`torchir.samplers._pmf.pmf_from_maps`). All-zero or non-finite maps fall
        back to the uniform pmf (with a warning for NaN/Inf). Returns the ``(V, H, W)`` pmf."""
        pmf, stats = _pmf.pmf_from_maps(p1, p2, self.resolution, self.alpha, self.multires, self.sigma, self.views)
        self._set_pmf(pmf)
        self._stats.update(stats)
        return self.pdf_image()

    def update(
        self,
        params: Mapping[str, torch.Tensor] | None = None,
        targets: torch.Tensor | Sequence[torch.Tensor] | None = None,
        loss: nn.Module | None = None,
        views: Sequence[int] | None = None,
        step: int = 0,
    ) -> None:
        """Refresh the pmf (Stage 1, paper Algorithm 1 lines 2-9) at ``step``.

        Renders each view on the Stage-1 grids with ``stage1_spp`` one-path passes,
        ``p1 = mean_i sum_c (∂ℓ/∂I_c)^2`` against the area-averaged target (summed over
        channels; ``loss`` is the per-pixel loss, default L2), and for the adaptive strategy
        ``p2 = mean_i sum_c t_c^2`` with ``t`` the derivative along a Rademacher direction
        over all parameters in ``params`` (our stand-in for the custom AD pass of the paper's
        Sec. 4.3), then builds the pmf with :meth:`update_from_maps`.

        Args:
            params: ``{name: value}`` of the optimised parameters (detached internally).
            targets: ``(V', C, H, W)`` or a list of ``(C, H, W)``, one per entry of ``views``.
            loss: a per-pixel loss module (``pixelwise = True``), default L2.
            views: the sensors ``targets`` belong to (default: all, in order).
            step: the optimiser step (for the refresh schedule).
        """
        params = {} if params is None else {k: v.detach() for k, v in params.items()}
        signature = self._signature_of(params, views)
        if not self.uses_stage1:
            self._signature, self.last_update, self.refreshes = signature, step, self.refreshes + 1
            return
        started = time.perf_counter()
        if self.scene is None:
            raise RuntimeError(f"{type(self).__name__}.update needs a scene; use update_from_maps for torch-only use")
        if self.world > 1:
            _check_process_group()
        views = list(range(self.views)) if views is None else [int(v) for v in views]
        targets = self._check_targets(targets, views)
        loss = _check_loss(loss)
        grids = self.stage1_grids
        p1 = [torch.zeros(self.views, h, w, dtype=torch.float64, device="cpu") for h, w in grids]
        p2 = [torch.zeros_like(m) for m in p1] if self.uses_derivatives else None
        probed = {k: v for k, v in params.items() if v.is_floating_point()}
        from ..functions.probe import probe_pixels  # Dr.Jit side, loaded on first use

        for i, v in enumerate(views):
            # every process draws every view's tangents and seed: the shared generator stays in step
            tangents = {k: _rademacher(val, self.generator) for k, val in probed.items()} if p2 is not None and probed else None
            seed = int(torch.randint(0, 2**32 - 1, (1,), generator=self.generator, device="cpu"))
            if i % self.world != self.rank:  # another process probes this view
                continue
            radiance, derivative = probe_pixels(
                self.scene, params, grids, passes=self.stage1_spp, seed=seed, sensor=v, tangents=tangents, step=self.fd_step
            )
            for d, (h, w) in enumerate(grids):
                target = F.interpolate(targets[i][None].float(), size=(h, w), mode="area").to(radiance[d].device)
                p1[d][v] = _adjoint_second_moment(loss, radiance[d], target)  # the maps stay on the host
                if p2 is not None and derivative is not None:
                    p2[d][v] = derivative[d].double().square().sum(1).mean(0)  # p2 = mean_i sum_c t_c^2
        if self.world > 1:
            _sum_over_processes(p1 + (p2 or []))  # each map is non-zero in one process only: the sums are exact
        self.update_from_maps(p1, p2)
        # only a refresh that finished counts: one that raised stays due
        self._signature, self.last_update, self.refreshes = signature, step, self.refreshes + 1
        probed_views = len(views[self.rank :: self.world])
        paths = probed_views * self.stage1_spp * sum(h * w for h, w in grids) * (2 if p2 is not None and probed else 1)
        self._stats.update(stage1_seconds=time.perf_counter() - started, stage1_paths=float(paths))

    def _check_targets(self, targets, views: list[int]) -> list[torch.Tensor]:
        if targets is None:
            raise ValueError("update needs the target images (one per view)")
        targets = list(targets) if not isinstance(targets, torch.Tensor) or targets.dim() == 4 else [targets]
        if len(targets) != len(views):
            raise ValueError(f"got {len(targets)} target(s) for {len(views)} view(s)")
        expected = self.resolution
        for t in targets:
            if t.dim() != 3 or tuple(t.shape[-2:]) != expected:
                raise ValueError(f"targets must be (C, {expected[0]}, {expected[1]}) images, got {tuple(t.shape)}")
            if not bool(torch.isfinite(t).all()):
                raise ValueError("targets contain NaN/Inf")
        return [t.detach() for t in targets]

    # -------------------------------------------------------------------- diagnostics
    def diagnostics(self) -> dict[str, float]:
        """Scalars to log: predicted gain (from Eq. 8: ``m sum a / (sum sqrt a)^2`` with ``a = p1 p2``
        of the finest level; for the Eq. 5 sampler ``a = p1``, i.e. assuming equal derivative
        moments everywhere, so it overstates that sampler's real gain), effective sample size
        fraction and largest weight (relative to uniform) of the last batch, Stage-1 seconds
        and paths."""
        return dict(self._stats)

    def state_dict(self) -> dict[str, Any]:
        return {
            "strategy": self.strategy,
            "pmf": self.pdf_image().clone(),
            "generator": self.generator.get_state(),
            "last_update": self.last_update,
            "refreshes": self.refreshes,
            "draw_calls": self.draw_calls,
            "signature": self._signature,
            "stats": dict(self._stats),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if state.get("strategy") != self.strategy:
            raise ValueError(f"state of a {state.get('strategy')!r} sampler, this one is {self.strategy!r}")
        pmf = state["pmf"]
        if tuple(pmf.shape) != (self.views, *self.resolution):
            raise ValueError(f"state pmf has shape {tuple(pmf.shape)}, this sampler {(self.views, *self.resolution)}")
        self._set_pmf(pmf.to(device="cpu", dtype=torch.float64))
        self.generator.set_state(state["generator"].cpu())
        self.last_update, self.refreshes = state["last_update"], state["refreshes"]
        self.draw_calls = int(state.get("draw_calls", 0))
        self._signature, self._stats = state["signature"], dict(state["stats"])

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(budget={self.budget}, views={self.views}, resolution={self.resolution}, "
            f"refresh_every={self.refresh_every}, levels={self.levels}, alpha={self.alpha}, seed={self.seed})"
        )


def _check_process_group() -> None:
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        raise RuntimeError("a sampler distributed over several processes needs torch.distributed initialised (DDP)")


def _sum_over_processes(maps: list[torch.Tensor]) -> None:
    """Sum ``maps`` (host tensors) in place over the processes of the default ``torch.distributed``
    group; through this process's GPU where the group's backend reduces only CUDA tensors (NCCL)."""
    import torch.distributed as dist

    via = _reduction_device(dist.get_backend())
    for value in maps:
        moved = value.to(via)
        dist.all_reduce(moved, op=dist.ReduceOp.SUM)
        value.copy_(moved)


def _reduction_device(group_backend: str) -> torch.device:
    """Where a tensor must be for ``all_reduce`` on a group with this backend ("nccl": the current GPU)."""
    if group_backend == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def _check_loss(loss: nn.Module | None) -> nn.Module:
    if loss is None:
        from ..modules.losses import L2Loss

        return L2Loss()
    if not getattr(loss, "pixelwise", False):
        raise ValueError(
            f"{type(loss).__name__} couples pixels (or does not declare pixelwise = True): pixel sampling needs a "
            f"per-pixel loss (l1, l2, relative_l2); LOI, pyramid and SSIM losses need full images"
        )
    return loss


def _adjoint_second_moment(loss: nn.Module, radiance: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``mean_i sum_c (∂ℓ/∂I_c)^2`` over the passes of ``radiance`` ``(S, C, h, w)``;
    any per-pixel loss, by autograd (the loss's overall scale cancels in the pmf)."""
    image = radiance.detach().requires_grad_()
    with torch.enable_grad():
        value = loss(image, target.expand_as(image))
        (grad,) = torch.autograd.grad(value, image)
    return grad.double().square().sum(1).mean(0)


class UniformPixelSampler(PixelSampler):
    """Uniform pixel draws (the baseline): ``p_j = 1 / m``, no Stage 1."""

    strategy = "uniform"


class LossPixelSampler(PixelSampler):
    """The loss-proportional baseline of Su & Gkioulekas (paper Eq. 5):
    ``p_j ∝ sqrt(E[(∂L/∂I_j)^2])``, estimated by the same Stage 1 without the derivative probe."""

    strategy = "loss"
    uses_stage1 = True


class AdaptivePixelSampler(PixelSampler):
    """Variance-aware adaptive pixel sampling: ``p_j ∝ sqrt(p1_j p2_j)`` (paper Eq. 8), ``p1`` the
    loss adjoint's and ``p2`` the pixel derivatives' second moments (``p2`` summed over the
    parameters, Eqs. 10-12)."""

    strategy = "adaptive"
    uses_stage1 = True
    uses_derivatives = True

