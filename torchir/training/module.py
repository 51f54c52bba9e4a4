"""InverseRenderingModule: a LightningModule that recovers scene parameters from images."""
from __future__ import annotations

import csv
import math
import time
from pathlib import Path
from typing import Any, Literal, Optional, Union

import lightning.pytorch as pl
from lightning.pytorch.loggers import CSVLogger
import torch
from torch import nn

from .. import backend
from .._scene_values import _unbindable_hint
from ..functions import render
from ..derived import declare as declare_derived
from ..imageio import clipped_mask
from ..jpeg import CodecCorrection
from . import remeshing
from ._resolve import _as_config, _from_checkpoint, _load_scene, _resolve_denoiser, _resolve_loss, _resolve_sampler, _to_checkpoint
from . import resolution as coarse_to_fine
from .spp import SppSchedule
from .parameters import LargeStepsParameter, ParameterConfig, SceneParameter, is_mesh_file, large_steps_lambda, resolve_value

__all__ = ["InverseRenderingModule", "NonFiniteLossError"]

_GOLDEN = 2654435761  # Knuth's multiplicative hash: spreads base seeds far apart
OPTIMIZERS = ("adam", "adam_uniform", "sgd")
DISTANCE_SAMPLES = 20000  # surface samples per mesh of the Chamfer/Hausdorff distances (torchir.geometry's default)
DISTANCE_PREFIXES = ("chamfer/", "hausdorff/")  # metric names of the mesh distances: "chamfer/<key>"


class NonFiniteLossError(RuntimeError):
    """The loss became NaN/Inf; the run stopped before applying that step."""


class InverseRenderingModule(pl.LightningModule):
    """Optimise Mitsuba scene parameters so that renders match target views.

    ``training_step`` renders each view of its batch with :func:`torchir.functions.render`,
    applies the optional denoiser (``denoiser(images, targets)``, both ``(B, C, H, W)``) and the
    loss, and returns the loss; Lightning does the backward pass and the optimiser step. The
    optimised quantities are ``nn.Parameter``\\ s (one :class:`SceneParameter` per Mitsuba key).

    Args:
        scene: a built-in scene name (``torchir.scenes.available()``), a Mitsuba ``.xml`` path, or
            a Python factory ``"file.py:function"`` / ``"package.module:function"`` returning a
            Mitsuba scene dict, called with ``scene_options`` (and ``resolution=`` when given).
        resolution: film size of a built-in scene, ``H`` or ``[H, W]``, and of ``sensors``' rig.
        scene_options: builder options of a built-in scene, or ``$``-substitutions of an XML file.
        integrator: ``{type: name, **properties}`` replacing the scene's integrator, so that a run
            uses the cheapest one its parameters need (e.g. ``{type: prb_projective, guiding:
            none, max_depth: 3}`` for a pose) without editing the scene file.
        sensors: a sensor rig replacing the scene's sensors, ``{type: fibonacci | orbit | look_at,
            **arguments of that function of torchir.rigs}`` (e.g. ``{type: fibonacci, count: 8,
            distance: 5, fov: 45, resolution: 96}``, Mitsuba's shape tutorial); its resolution
            may come from ``resolution`` instead (giving both, they must agree).
        derived: ``{label: {type: rigid | function, ...}}``: derived parameters declared on the
            scene before ``parameters`` are read (see :mod:`torchir.derived`), e.g. a shape's
            pose ``{type: rigid, shape: bunny}`` giving ``bunny.translation``/``.rotation``/``.scale``.
        parameters: ``{Mitsuba key: ParameterConfig}``; default: the built-in scene's typical
            unknowns, initialised to 0.5.
        loss: ``"l1"``, ``"l2"``, ``"relative_l2"`` or any ``nn.Module`` ``(rendered, target) -> scalar``
            (by class path in YAML).
            A mapping ``{type: <name in torchir.modules.LOSSES>, **options}`` selects any
            registered loss with options (e.g. ``{type: loi, alphas: [1, 5]}``).
        denoiser: an optional ``nn.Module`` ``(noisy, target) -> denoised``, or
            ``{type: <name in torchir.modules.DENOISERS>, **options}``.
        sampler: an optional ``{type: <name in torchir.samplers.SAMPLERS>, **options}``, built
            as ``SAMPLERS[type](scene, **options)``. A pixel sampler (``uniform``, ``loss``,
            ``adaptive``) switches to pixel-sampling mode: each step renders only the drawn
            pixels with :func:`~torchir.functions.render_pixels` and minimises the importance-
            weighted loss, whose gradient is the pixel-sampled estimator of Eq. 4 of Yan et al. 2025,
            "Image-space Adaptive Sampling for Fast Inverse Rendering", refreshing the sampler's pmf
            on its schedule.
        spp, spp_grad: samples per pixel of the primal image and of the gradient pass. ``spp``
            may be a schedule ``{spp: first step}`` (``{8: 0, 64: 100}``: 8 from step 0, 64 from
            step 100, as Mitsuba's volume tutorial raises it with the grid's resolution);
            ``spp_grad`` (a count) defaults to the step's ``spp``.
        seed: base seed; step ``t`` renders view ``v`` with a seed derived from (seed, t, v) only,
            so runs, resumed runs and multi-process runs see the same random numbers.
        lr: learning rate (per-parameter ``lr`` overrides it).
        lr_half_life: steps over which every learning rate halves (decayed each step), or
            ``None`` for constant rates. With a constant rate the error stops falling at a
            level set by the gradient noise (a small pixel budget levels off above the full
            image's error); a decay lowers that floor over the run (measured with
            ``torchir bench scaleup``: docs/training.md, "Measurements behind the design").
        optimizer: ``adam`` (default), ``adam_uniform`` (:class:`torchir.geometry.AdamUniform`,
            for every parameter: one second-moment scale per parameter tensor, as Mitsuba's shape
            tutorial optimises a Large Steps latent; a scalar parameter steps as with Adam) or ``sgd``.
        preview_spp: samples per pixel of the images written for people (initial/current/final).
        distance_every_n_steps: how often the Chamfer/Hausdorff distances of a mesh parameter
            with a truth mesh are logged (``chamfer/<key>``, ``hausdorff/<key>``; ~0.1-0.8 s
            each time): on the first row the loggers write, then on the first written row at
            least this many steps after the last, and on the final row.
        remesh: ``{at: [steps], edge_length: 0.5, iterations: 5, project: true}``: before each
            step of ``at``, remesh every optimised mesh (``<shape>.vertex_positions``) to
            ``edge_length`` times its current mean edge and go on with the new topology (a new
            Large Steps latent, its optimiser state afresh), as Mitsuba's shape tutorial does
            (:mod:`torchir.training.remeshing`); metrics.csv then has ``vertices/<key>``.
    """

    def __init__(
        self,
        scene: str = "cbox",
        resolution: Optional[Union[int, tuple[int, int]]] = None,
        scene_options: Optional[dict[str, Any]] = None,
        integrator: Optional[dict[str, Any]] = None,
        sensors: Optional[dict[str, Any]] = None,
        derived: Optional[dict[str, dict[str, Any]]] = None,
        parameters: Optional[dict[str, ParameterConfig]] = None,
        loss: Union[str, nn.Module, dict[str, Any]] = "l2",
        denoiser: Optional[Union[nn.Module, dict[str, Any]]] = None,
        sampler: Optional[dict[str, Any]] = None,
        spp: Union[int, dict[int, int]] = 8,
        spp_grad: Optional[int] = None,
        seed: int = 0,
        lr: float = 0.05,
        lr_half_life: Optional[int] = None,
        optimizer: Literal["adam", "adam_uniform", "sgd"] = "adam",
        preview_spp: int = 64,
        distance_every_n_steps: int = 10,
        remesh: Optional[dict[str, Any]] = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["loss", "denoiser"])
        self.spp_schedule = SppSchedule.parse(spp)
        counts = {"preview_spp": preview_spp, **({} if spp_grad is None else {"spp_grad": spp_grad})}
        for name, value in counts.items():
            if value < 1:
                raise ValueError(f"model.{name} must be >= 1, got {value}")
        if not (isinstance(lr, (int, float)) and 0 < lr < float("inf")):
            raise ValueError(f"model.lr must be a finite number > 0 (gradient descent), got {lr!r}")
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"model.optimizer must be one of {list(OPTIMIZERS)}, got {optimizer!r}")
        if isinstance(distance_every_n_steps, bool) or not isinstance(distance_every_n_steps, int) or distance_every_n_steps < 1:
            raise ValueError(f"model.distance_every_n_steps must be a number of steps >= 1, got {distance_every_n_steps!r}")
        if lr_half_life is not None and (isinstance(lr_half_life, bool) or not isinstance(lr_half_life, int) or lr_half_life < 1):
            raise ValueError(f"model.lr_half_life must be a number of steps >= 1 (or null), got {lr_half_life!r}")
        self.scene = _load_scene(scene, resolution, dict(scene_options or {}), integrator, sensors)
        for label, spec in (derived or {}).items():
            declare_derived(self.scene, label, spec)
        if parameters is None:
            if not self.scene.is_builtin:
                raise ValueError("model.parameters is required for scenes loaded from files")
            from .. import scenes

            parameters = {key: ParameterConfig() for key in scenes.get(self.scene.name).parameters}
        if not parameters:
            raise ValueError("model.parameters is empty: nothing to optimise")
        self.configs = {key: _as_config(key, cfg) for key, cfg in parameters.items()}
        self.keys = list(self.configs)
        # truth meshes (``truth: mesh.ply``): (vertices (V, 3), faces (F, 3)), read once, on the host
        self.truth_meshes = {key: self._truth_mesh(key) for key, cfg in self.configs.items() if is_mesh_file(cfg.truth)}
        self.resolutions = coarse_to_fine.schedules(self.scene, self.configs)  # {key: ResolutionSchedule} of coarse-to-fine grids
        self.scene_parameters = nn.ModuleList(self._build_parameter(key) for key in self.keys)
        self.loss_fn = _resolve_loss(loss)
        self.denoiser = _resolve_denoiser(denoiser)
        self.sampler = _resolve_sampler(sampler, self.scene)
        if self.pixel_mode:
            if not getattr(self.loss_fn, "pixelwise", False) or not hasattr(self.loss_fn, "pixel_terms"):
                raise ValueError(
                    f"model.loss {type(self.loss_fn).__name__} couples pixels: it cannot be used with the pixel sampler "
                    f"{self.sampler.strategy!r}; use l1, l2 or relative_l2, or drop model.sampler"
                )
            if self.denoiser is not None:
                raise ValueError("a denoiser needs full images: it cannot be combined with a pixel sampler (model.sampler)")
        elif self.sampler is not None:
            from ..functions.render import _check_sampler

            derived = self.scene.derived
            _check_sampler(self.scene, self.sampler, frozenset(derived[k].target if k in derived else k for k in self.keys))
        self.fixed_spp_grad, self.seed, self.lr = spp_grad, seed, lr
        self.optimizer_name, self.preview_spp, self.lr_half_life = optimizer, preview_spp, lr_half_life
        self.distance_every_n_steps = distance_every_n_steps
        self._distances_at: Optional[int] = None  # the last step whose row has the mesh distances
        self._distance_cache: Optional[tuple[Any, dict[str, float]]] = None
        self.diagnostic_seconds = 0.0  # this step's time on diagnostics (mesh distances): StepTimer leaves it out
        self.nonfinite: Optional[str] = None  # set when a non-finite loss stopped the run
        self.step_metrics: dict[str, float] = {}  # the last step's scalars (loss, errors, paths, sampler/*)
        self._write_logs_at: Optional[int] = None
        self.remesh_schedule = None if remesh is None else remeshing.RemeshSchedule.from_config(remesh)
        self.topology = remeshing.TopologyRecord()  # the meshes remeshed so far (checkpointed)
        if self.remesh_schedule is not None:
            remeshing.check_remesh(self, self.remesh_schedule)

    # ------------------------------------------------------------------------ parameters
    def _build_parameter(self, key: str) -> Union[SceneParameter, LargeStepsParameter]:
        info = self.scene.info(key)  # KeyError with close matches
        if not info.bindable:
            raise TypeError(f"parameters[{key!r}]: {key!r} has type {info.type_name}, which torchir cannot optimise: {_unbindable_hint(key, info.type_name)}")
        if self.configs[key].parametrization is not None:
            return self._build_large_steps(key)
        if key in self.resolutions:  # a coarse-to-fine grid starts at its first resolution
            config, scene_value = self.configs[key], self.scene.get(key)
            initial = coarse_to_fine.initial_grid(config.init, scene_value, self.resolutions[key].first, config.bounds,
                                              config.seed, f"parameters[{key!r}].init")
        else:
            initial = self._config_value(key, self.configs[key].init, "init")
        self.scene.check_values({key: initial.requires_grad_()})  # dtype, shape, differentiable, finite
        return SceneParameter(key, initial.detach(), self.configs[key])

    def mesh_id(self, key: str) -> Optional[str]:
        """The id of the scene mesh whose ``vertex_positions`` ``key`` is, else None."""
        import mitsuba as mi

        if key in self.scene.derived or not key.endswith(".vertex_positions"):
            return None
        shape = key.removesuffix(".vertex_positions")
        return shape if any(isinstance(s, mi.Mesh) and s.id() == shape for s in self.scene.mi_scene.shapes()) else None

    def mesh_faces(self, key: str) -> torch.Tensor:
        """``(F, 3)`` int64 host faces of the scene mesh of parameter ``key``."""
        return self.scene.get(f"{self.mesh_id(key)}.faces").detach().to(torch.int64).cpu().reshape(-1, 3)

    def _build_large_steps(self, key: str) -> LargeStepsParameter:
        """The Large Steps parameter of a mesh's ``vertex_positions`` (``parametrization``)."""
        from ..geometry import LargeSteps

        config = self.configs[key]
        lambda_ = large_steps_lambda(key, config.parametrization)
        if self.mesh_id(key) is None:
            raise ValueError(f"parameters[{key!r}].parametrization (large_steps) applies to a mesh's vertex positions "
                             f"('<shape>.vertex_positions' of a mesh in the scene), not to {key!r}")
        if config.transform != "none" or config.bounds is not None:
            raise ValueError(f"parameters[{key!r}]: a large_steps parametrization takes neither transform nor bounds "
                             f"(the latent is (I + λL) x), got transform {config.transform!r}, bounds {config.bounds!r}")
        init = config.init
        if isinstance(init, (int, float)) and not isinstance(init, bool):
            if init != ParameterConfig.init:
                raise ValueError(f"parameters[{key!r}].init: a constant {init!r} would put every vertex at one point; leave "
                                 "init out (the scene's mesh), or give 'scene' or explicit positions")
            init = "scene"  # the default init of a mesh is the mesh the scene loaded
        initial = self._config_value(key, init, "init")
        self.scene.check_values({key: initial.requires_grad_()})
        return LargeStepsParameter(key, LargeSteps(self.scene, key, lambda_=lambda_), initial.detach())

    def _truth_mesh(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The truth mesh file of parameter ``key`` as host ``(vertices, faces)``."""
        from pathlib import Path

        from ..geometry import read_mesh

        path = self.configs[key].truth
        if self.mesh_id(key) is None:
            raise ValueError(f"parameters[{key!r}].truth {path!r} is a mesh file, which only a mesh's vertex positions "
                             f"('<shape>.vertex_positions') can have as truth")
        if not Path(path).is_file():
            raise FileNotFoundError(f"parameters[{key!r}].truth: mesh file not found: {path!r}")
        return read_mesh(path, device="cpu")

    def _config_value(self, key: str, spec, field: str) -> torch.Tensor:
        """A config value (``init``/``truth`` forms) of parameter ``key`` as a tensor of its shape."""
        config, scene_value = self.configs[key], self.scene.get(key)
        return resolve_value(spec, scene_value.shape, scene_value, config.bounds, config.seed, f"parameters[{key!r}].{field}")

    def scene_values(self) -> dict[str, torch.Tensor]:
        """``{Mitsuba key: current value}`` (differentiable w.r.t. the latents)."""
        return {key: p() for key, p in zip(self.keys, self.scene_parameters)}

    def ground_truth(self, explicit_only: bool = False) -> dict[str, torch.Tensor]:
        """``{key: true value}`` from ``truth`` in the config, else the loaded scene value
        (``explicit_only``: only the configured ones)."""
        truth = {}
        for key in self.keys:
            spec = self.configs[key].truth
            if spec is None and explicit_only:
                continue
            if key in self.truth_meshes:  # as positions, when the truth mesh has the scene mesh's vertex list
                vertices = self.truth_meshes[key][0]
                scene_value = self.scene.get(key)
                if vertices.numel() == scene_value.numel():
                    truth[key] = vertices.reshape(scene_value.shape).to(scene_value)
                elif not explicit_only:
                    raise ValueError(
                        f"parameters[{key!r}].truth {spec!r} has {vertices.shape[0]} vertices, the scene's mesh "
                        f"{scene_value.numel() // 3}: synthetic targets (data.targets: null) render the truth as the "
                        f"scene's vertex positions, so they need a truth mesh on the same vertex list; give data.targets images"
                    )
                continue
            truth[key] = self._config_value(key, "scene" if spec is None else spec, "truth")
        return truth

    def value_truth(self, explicit_only: bool = False) -> dict[str, torch.Tensor]:
        """:meth:`ground_truth` without the parameters whose truth is a mesh file (their error is
        their :meth:`mesh_distances`, not an RMSE over vertex lists): the parameter-error truths."""
        return {k: v for k, v in self.ground_truth(explicit_only).items() if k not in self.truth_meshes}

    @torch.no_grad()
    def mesh_distances(self, values: Optional[dict[str, torch.Tensor]] = None) -> dict[str, float]:
        """``{"chamfer/<key>": d, "hausdorff/<key>": h}`` of each parameter with a truth mesh: the
        symmetric *squared* Chamfer distance and the Hausdorff distance between the current mesh
        (``values``: the current :meth:`scene_values`, when already computed) and the truth mesh,
        from :data:`DISTANCE_SAMPLES` area-uniform samples of each (:mod:`torchir.geometry`)."""
        from ..geometry import chamfer_and_hausdorff

        if not self.truth_meshes:
            return {}
        state = (self.global_step, tuple(p.latent._version for p in self.scene_parameters), values is None)
        if values is None and self._distance_cache is not None and self._distance_cache[0] == state:
            return dict(self._distance_cache[1])
        values = self.scene_values() if values is None else values
        out = {}
        for key, truth in self.truth_meshes.items():
            mesh = (values[key].detach().reshape(-1, 3).cpu(), self.mesh_faces(key))
            out[f"chamfer/{key}"], out[f"hausdorff/{key}"] = chamfer_and_hausdorff(mesh, truth, samples=DISTANCE_SAMPLES)
        self._distance_cache = (state, dict(out))
        return out

    def distance_floors(self) -> dict[str, float]:
        """``{key: Chamfer distance of its truth mesh to itself}``: the sampling floor of
        :meth:`mesh_distances` (about ``2 S / (π n)`` for area ``S``, ``n`` samples)."""
        from ..geometry import chamfer_distance

        return {key: chamfer_distance(truth, truth, samples=DISTANCE_SAMPLES, seed=1) for key, truth in self.truth_meshes.items()}

    def _distances_due(self) -> bool:
        """Whether this step's (written) row gets the mesh distances (``distance_every_n_steps``)."""
        step = self.global_step
        if self._distances_at is not None and 0 <= step - self._distances_at < self.distance_every_n_steps:
            return False
        self._distances_at = step
        return True

    @torch.no_grad()
    def project_parameters(self) -> None:
        """Enforce every parameter's bounds (called after each optimiser step)."""
        for p in self.scene_parameters:
            p.project()

    @torch.no_grad()
    def parameter_error(self, truth: dict[str, torch.Tensor], values: Optional[dict[str, torch.Tensor]] = None) -> Optional[float]:
        """RMSE over all entries of the parameters with a known truth, pooled whatever their
        units, or None (``values``: the current :meth:`scene_values`, when already computed);
        :meth:`parameter_errors` gives each parameter's own."""
        if not truth:
            return None
        values = coarse_to_fine.on_truth_grids(self.scene_values() if values is None else values, truth)
        sq = sum(float((values[k].detach() - t.to(values[k])).square().sum()) for k, t in truth.items())
        n = sum(t.numel() for t in truth.values())
        return math.sqrt(sq / n)

    def parameter_errors(self, truth: dict[str, torch.Tensor], values: Optional[dict[str, torch.Tensor]] = None) -> dict[str, float]:
        """``{key: RMSE of that parameter's entries against its truth}`` (its own units)."""
        values = coarse_to_fine.on_truth_grids(self.scene_values() if values is None else values, truth)
        return {k: math.sqrt(float((values[k].detach() - t.to(values[k])).square().mean())) for k, t in truth.items()}

    def error_metrics(self, values: Optional[dict[str, torch.Tensor]] = None) -> dict[str, float]:
        """``param_error`` (pooled RMSE) and, with several parameters, ``param_error/<key>`` each:
        the metrics logged for the values ``values`` (default: the current ones)."""
        truth = self._truth
        if not truth:
            return {}
        values = self.scene_values() if values is None else values
        out = {"param_error": self.parameter_error(truth, values)}
        if len(truth) > 1:
            out.update({f"param_error/{k}": e for k, e in self.parameter_errors(truth, values).items()})
        return out

    @torch.no_grad()
    def final_metrics(self) -> dict[str, float]:
        """The last step's metrics with the parameter errors of the values after its update (a
        step's own ``param_error`` is of the values it rendered, before its update)."""
        return {**self.step_metrics, **self.error_metrics(), **self.mesh_distances()}

    def on_train_end(self) -> None:
        """Log the errors of the final values as one more row, at the step count (a run of N
        steps: rows 0 .. N-1 the values each step rendered, row N the values it ends with), and
        keep them in :attr:`step_metrics` for the ``finished`` line."""
        final = self.final_metrics()
        self.step_metrics = final
        errors = {k: v for k, v in final.items() if k.startswith(("param_error", *DISTANCE_PREFIXES))}
        if errors and self.trainer.world_size == 1 and self.global_step > 0:
            for logger in self.loggers:
                logger.log_metrics({**errors, "epoch": float(self.current_epoch)}, step=self.global_step)

    # ---------------------------------------------------------------------------- render
    def step_seed(self, step: int, view: int) -> int:
        """Seed of view ``view`` at optimiser step ``step``: a function of (seed, step, view) only."""
        return (self.seed * _GOLDEN + step * self.scene.sensor_count + view) % 2**32

    def spp_at(self, step: int) -> int:
        """Samples per pixel of the primal image at optimiser step ``step`` (``model.spp``)."""
        return self.spp_schedule.at(step)

    def spp_grad_at(self, step: int) -> int:
        """Samples per pixel of the gradient pass at ``step``: ``model.spp_grad``, else the step's spp."""
        return self.spp_at(step) if self.fixed_spp_grad is None else self.fixed_spp_grad

    @property
    def spp(self) -> int:
        """Samples per pixel of the primal image at the current step."""
        return self.spp_at(self.global_step)

    @property
    def spp_grad(self) -> int:
        """Samples per pixel of the gradient pass at the current step."""
        return self.spp_grad_at(self.global_step)

    def render_views(self, views: list[int], step: int) -> torch.Tensor:
        """Differentiable renders of ``views`` at ``step``, ``(B, C, H, W)`` (through the ReSTIR
        sampler when one is set)."""
        values = self.scene_values()
        extra = {} if self.sampler is None or self.pixel_mode else {"sampler": self.sampler}
        images = [
            render(self.scene, values, spp=self.spp_at(step), seed=self.step_seed(step, v), sensor=v,
                   spp_grad=self.spp_grad_at(step), **extra)
            for v in views
        ]
        return torch.stack(images)

    @torch.no_grad()
    def preview(self, view: int, values: Optional[dict[str, torch.Tensor]] = None, seed: int = 2**32 - 7) -> torch.Tensor:
        """A low-noise image of ``view`` for people, ``(C, H, W)``, not differentiated."""
        values = self.scene_values() if values is None else values
        return render(self.scene, {k: v.detach() for k, v in values.items()}, spp=self.preview_spp, seed=seed, sensor=view)

    # ------------------------------------------------------------------------- lightning
    def forward(self, views: list[int], step: int = 0) -> torch.Tensor:
        return self.render_views(views, step)

    @torch.no_grad()
    def guide_buffers(self, views: list[int], step: int) -> torch.Tensor:
        """G-buffers (albedo, normal, depth) of ``views`` for a G-buffer denoiser, ``(B, 7, H, W)``,
        rendered before the differentiable render so they never disturb its AD graph."""
        from ..functions import render_gbuffers

        values = {k: v.detach() for k, v in self.scene_values().items()}
        return torch.stack([render_gbuffers(self.scene, values, sensor=v, seed=self.step_seed(step, v)) for v in views])

    def denoise(self, images: torch.Tensor, targets: torch.Tensor, views: list[int], guide: Optional[torch.Tensor]) -> torch.Tensor:
        """Apply the denoiser, passing ``guide`` and ``views`` to denoisers that take them."""
        import inspect

        accepted = inspect.signature(self.denoiser.forward).parameters
        kwargs: dict[str, Any] = {}
        if guide is not None:
            kwargs["guide"] = guide
        if "views" in accepted:
            kwargs["views"] = views
        return self.denoiser(images, targets, **kwargs)

    def _loggers_write(self) -> bool:
        """Whether the loggers write this step's metrics (``trainer.log_every_n_steps``, the rule
        of Lightning's logger connector); :meth:`_record_step` logs only on these steps."""
        trainer = self._trainer
        if trainer is None:
            return True
        if not self.loggers:
            return False
        every = trainer.log_every_n_steps
        return every > 0 and ((self.global_step + 1) % every == 0 or trainer.should_stop)

    @property
    def pixel_mode(self) -> bool:
        """Whether steps render sampled pixels (a pixel sampler is set) instead of full images."""
        from ..samplers import PixelSampler

        return isinstance(self.sampler, PixelSampler)

    def refresh_sampler(self, step: int, values: Optional[dict[str, torch.Tensor]] = None) -> bool:
        """Run the pixel sampler's Stage 1 if it is due at ``step``; True if it ran (``values``:
        the current :meth:`scene_values`, when already computed)."""
        data = self.trainer.datamodule if self._trainer is not None else None
        if data is None or not getattr(data, "targets", None):
            raise RuntimeError("pixel sampling needs the target views of a ViewDataModule (trainer.datamodule)")
        values = self.scene_values() if values is None else values
        if not self.sampler.due(step, values, data.views):
            return False
        self.sampler.update(values, data.targets, self.loss_fn, views=data.views, step=step)
        return True

    def sampled_loss(
        self, views: list[int], targets: torch.Tensor, step: int, values: Optional[dict[str, torch.Tensor]] = None
    ) -> tuple[torch.Tensor, torch.Tensor, int]:
        """The importance-weighted loss of one pixel batch (each drawn pixel's loss weighted by its
        inverse draw probability, so that its gradient is the estimator of Yan et al. 2025, Eq. 4),
        its weighted squared error (for logging) and the number of paths traced (``values``: the
        current :meth:`scene_values`, when already computed)."""
        from ..samplers import sampled_loss

        batch = self.sampler.sample(views)
        scored = sampled_loss(
            self.scene, self.scene_values() if values is None else values, batch, targets, views, self.loss_fn,
            seed=lambda view: self.step_seed(step, view), spp=self.spp_at(step), spp_grad=self.spp_grad_at(step),
        )
        error = (scored.weight * (scored.radiance.detach() - scored.target).square().mean(-1)).sum()
        return scored.loss, error, batch.index.numel() * (self.spp_at(step) + self.spp_grad_at(step))

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> Optional[torch.Tensor]:
        views = [int(v) for v in batch["view"]]
        targets = batch["target"]
        step = self.global_step
        stage1_paths = 0.0
        values = None
        if self.pixel_mode:
            values = self.scene_values()  # one evaluation per step, shared by Stage 1, the render and the error
            if self.refresh_sampler(step, values):
                stage1_paths = self.sampler.diagnostics().get("stage1_paths", 0.0)
            loss, image_error, paths = self.sampled_loss(views, targets, step, values)
        else:
            guide = self.guide_buffers(views, step) if getattr(self.denoiser, "needs_guide", False) else None
            images = self.render_views(views, step)
            if "chroma" in batch:  # a JPEG target: add what the codec would change in the render
                tables = batch.get("quantisation", [None] * len(views))
                images = torch.stack([self.codec_correction(image, view, (h, v), bool(srgb), _tables(table))
                                      for image, view, (h, v, srgb), table in zip(images, views, batch["chroma"].tolist(), tables)])
            saturation = self.target_saturation
            if saturation is not None:
                # A clipped photo pixel only says "at least this bright": leave it out of the loss (the
                # target's own value, no gradient). Clipping the noisy render instead would be biased,
                # E[min(I, s)] < min(E[I], s), and pulls the fit (measured: a lamp of 12 fitted to ~20).
                # A pixel with any channel at the top code is left out whole: JPEG mixes codes across
                # channels, so a clipped lamp can read (254, 255, 255) (measured: R fitted to 8 of 12).
                # In a JPEG the lamp's edge also decodes below the top code, residuals of ~7 that
                # dominated the loss: clipped_mask leaves out what the codec smeared too.
                lossy = batch["lossy"].tolist() if "lossy" in batch else [False] * len(views)
                clipped = torch.stack([clipped_mask(t, saturation, lossy=flag) for t, flag in zip(targets, lossy)])
                images = torch.where(clipped, targets, images)
            # of the render itself: a target-aware denoiser's output is pulled towards the target
            image_error = (images.detach() - targets).square().mean()
            if self.denoiser is not None:
                images = self.denoise(images, targets, views, guide)
            loss = self.loss_fn(images, targets)
            h, w = self.scene.resolution
            paths = len(views) * h * w * (self.spp_at(step) + self.spp_grad_at(step))
        if not bool(torch.isfinite(loss)):
            self.nonfinite = (
                f"the loss became {loss.item()} at step {self.global_step} (views {views}); the run stopped "
                f"before applying that step"
            )
            self.trainer.should_stop = True
            return None  # Lightning skips backward and the optimiser step
        self._record_step(loss, image_error, float(paths + stage1_paths), len(views), values)
        return loss

    def _record_step(
        self, loss: torch.Tensor, image_error: torch.Tensor, paths: float, batch_size: int, values: Optional[dict[str, torch.Tensor]] = None
    ) -> None:
        """Keep this step's scalars in :attr:`step_metrics` and log them.

        One process writes them to the loggers itself on the loggers' steps
        (``trainer.log_every_n_steps``), one row per step, in ``on_train_batch_end``: Lightning's
        ``self.log`` per metric is a large part of a small pixel-sampled step (measured:
        docs/pixel-sampling.md). ``loss`` also goes through ``self.log`` (progress bar,
        ``callback_metrics``, checkpoint monitors). Under DDP every metric goes through
        ``self.log``, which reduces it across processes."""
        metrics = {"loss": float(loss.detach())}
        if not self._loss_is_image_error:  # else it would repeat the loss
            metrics["image_error"] = float(image_error)
        metrics["paths_per_step"] = paths
        if self.sampler is not None and hasattr(self.sampler, "diagnostics"):
            metrics.update({f"sampler/{name}": float(value) for name, value in self.sampler.diagnostics().items()})
        metrics.update(self.error_metrics(values))
        metrics.update(remeshing.vertex_counts(self))
        self._write_logs_at = self.global_step if self._loggers_write() else None
        if self.truth_meshes and self._write_logs_at is not None and self._distances_due():
            start = time.perf_counter()
            metrics.update(self.mesh_distances(values))  # costly: on some written rows only
            self.diagnostic_seconds += time.perf_counter() - start  # not the step's: StepTimer leaves it out
        self.step_metrics = metrics
        distributed = self.trainer.world_size > 1
        self.log("loss", loss, prog_bar=True, on_step=True, on_epoch=False, batch_size=batch_size, sync_dist=True, logger=distributed)
        if not distributed or self._write_logs_at is None:
            return
        for name, value in metrics.items():  # every rank decides alike: the reductions stay matched
            if name == "loss":
                continue
            reduce = "sum" if name == "paths_per_step" else "mean"
            self.log(name, value, on_step=True, on_epoch=False, batch_size=batch_size, reduce_fx=reduce, sync_dist=not name.startswith("sampler/"))

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        """Write this step's row (:meth:`_record_step`), after the callbacks added theirs."""
        step, self._write_logs_at = self._write_logs_at, None
        if step is None or self.trainer.world_size > 1:
            return
        row = {**self.step_metrics, "epoch": float(self.current_epoch)}
        for logger in self.loggers:
            logger.log_metrics(row, step=step)

    @property
    def codec_correction(self) -> CodecCorrection:
        """For JPEG targets: the codec's change (quantisation, chroma subsampling), from a running
        mean of each view's renders (:class:`torchir.jpeg.CodecCorrection`; kept in memory, not
        checkpointed)."""
        if getattr(self, "_codec_correction", None) is None:
            self._codec_correction = CodecCorrection()
        return self._codec_correction

    @property
    def target_saturation(self) -> Optional[float]:
        """Radiance at which the targets clipped (``ViewDataModule.saturation``), or None."""
        datamodule = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        return getattr(datamodule, "saturation", None)

    @property
    def _loss_is_image_error(self) -> bool:
        from ..modules import L2Loss

        return type(self.loss_fn) is L2Loss and getattr(self.loss_fn, "reduction", "mean") == "mean" and self.denoiser is None

    def on_train_start(self) -> None:
        """A resumed run keeps one history: the rows of the checkpoint's own ``metrics.csv``
        before the resume step lead this run's ``metrics.csv`` (the curves come back with the
        checkpoint already), so the new run folder holds the whole run from step 0."""
        ckpt = getattr(self.trainer, "ckpt_path", None)
        if not ckpt or not self.trainer.is_global_zero or self.global_step == 0:
            return
        earlier = Path(ckpt).resolve().parent.parent / "metrics.csv"
        if not earlier.is_file():
            return
        with open(earlier, newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("step") and int(float(r["step"])) < self.global_step]
        history = [{k: (int(float(v)) if k == "step" else float(v)) for k, v in r.items() if v not in ("", None)} for r in rows]
        for logger in self.loggers:
            if isinstance(logger, CSVLogger) and Path(logger.log_dir).resolve() != earlier.parent:
                logger.experiment.metrics[:0] = history

    def setup(self, stage: str) -> None:
        strategy = getattr(self.trainer, "strategy", None)  # (tests drive setup with a stand-in trainer)
        if strategy is not None:
            _check_trainer_device(strategy.root_device)
        datamodule = getattr(self.trainer, "datamodule", None)
        synthetic = datamodule is None or getattr(datamodule, "synthetic", True)
        if self.pixel_mode and getattr(datamodule, "saturation", None) is not None:
            raise ValueError(
                "pixel sampling compares unclipped pixels, but the targets clip at "
                f"{datamodule.saturation} (8/16-bit files): use EXR targets, or set data.saturation: null"
            )
        self._truth = self.value_truth(explicit_only=not synthetic)
        if self.remesh_schedule is not None:
            remeshing.check_remesh_truth(self, self._truth)
        if self.pixel_mode:  # under DDP the pixel budget and Stage 1 are shared by the processes
            self.sampler.distribute(self.trainer.global_rank, self.trainer.world_size)
        plan_run = getattr(self.sampler, "plan_run", None)  # ReSTIR "auto" charges its burn-in over the run
        if plan_run is not None and (self.trainer.max_steps or 0) > 0:
            plan_run(int(self.trainer.max_steps))
        # trainer.log_dir is a collective under DDP: resolve it here, on every rank, once.
        self._results_dir = Path(self.trainer.log_dir or self.trainer.default_root_dir)

    def configure_optimizers(self) -> Union[torch.optim.Optimizer, dict[str, Any]]:
        groups = [
            {"params": [p.latent], "lr": self.lr if self.configs[key].lr is None else self.configs[key].lr, "name": key}
            for key, p in zip(self.keys, self.scene_parameters)
        ]
        if self.optimizer_name == "sgd":
            optimizer = torch.optim.SGD(groups, lr=self.lr)
        elif self.optimizer_name == "adam_uniform":
            from ..geometry import AdamUniform

            optimizer = AdamUniform(groups, lr=self.lr)
        else:
            optimizer = torch.optim.Adam(groups, lr=self.lr)
        if self.lr_half_life is None:
            return optimizer
        decay = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=0.5 ** (1.0 / self.lr_half_life))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": decay, "interval": "step"}}

    def configure_callbacks(self) -> list[pl.Callback]:
        from .callbacks import NonFiniteLossGuard, ParameterProjection, ResultWriter, StepProgressBar, StepTimer

        from lightning.pytorch.callbacks import RichProgressBar, TQDMProgressBar

        callbacks = [ParameterProjection(), StepTimer(), NonFiniteLossGuard(), ResultWriter()]
        bar = self.trainer.progress_bar_callback if self._trainer is not None else None
        if type(bar) in (TQDMProgressBar, RichProgressBar):  # Lightning's default, per-epoch bar
            self.trainer.callbacks.remove(bar)
            callbacks.append(StepProgressBar())
        return callbacks

    def on_train_batch_start(self, batch: Any, batch_idx: int) -> None:
        """Before this step renders: remesh (``model.remesh``) and resize the coarse-to-fine grids
        whose next stage starts here (``resolution``)."""
        remeshing.apply_remesh_schedule(self, self.global_step)
        coarse_to_fine.apply_schedule(self, self.global_step)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.topology.meshes:  # the current topology: a resume rebuilds the scene from it
            checkpoint["torchir_topology"] = self.topology.state_dict()
        if self.sampler is not None and hasattr(self.sampler, "state_dict"):
            checkpoint["torchir_sampler"] = _to_checkpoint(self.sampler.state_dict())

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if "torchir_topology" in checkpoint:  # before Lightning loads the parameters' state into them
            remeshing.restore_topology(self, checkpoint["torchir_topology"])
        coarse_to_fine.match_checkpoint(self, checkpoint.get("state_dict", {}))  # grids resized before the state loads
        if self.sampler is not None and "torchir_sampler" in checkpoint:
            self.sampler.load_state_dict(_from_checkpoint(checkpoint["torchir_sampler"]))

    @property
    def results_dir(self) -> Path:
        """Where this run writes its outputs (the logger's version folder)."""
        return self._results_dir


def _tables(table: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
    """A batch entry's JPEG quantisation tables, or None where the target is not a JPEG (zeros)."""
    return None if table is None or not bool(table.any()) else table


def _check_trainer_device(device: torch.device) -> None:
    """Raise unless the trainer's device is the one the renderer reads and writes tensors on."""
    render_device = backend.device()
    if device.type != render_device:
        raise ValueError(
            f"the trainer runs on {device.type}, but torchir renders with {backend.variant()!r}, whose images "
            f"and parameters are {render_device} tensors: set trainer.accelerator: {render_device} (the default "
            f"of `torchir fit`), or choose the variant with TORCHIR_VARIANT"
        )
