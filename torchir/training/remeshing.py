"""Remeshing on a schedule in a run (``model.remesh``), as Mitsuba's shape tutorial does mid-run.

Before each scheduled step renders, every optimised mesh (a ``<shape>.vertex_positions``
parameter, Large Steps or plain) is remeshed at its current positions (Botsch-Kobbelt,
:func:`torchir.geometry.remesh`, to ``edge_length`` times its current mean edge), the run's
scene is replaced by one holding the new mesh, the parameter is rebuilt on the new topology (a
new :class:`~torchir.geometry.LargeSteps` and its latent), and the optimiser gets the new latent
with a fresh state (the other parameters' state and the lr schedule's progress stay).

The run keeps a :class:`TopologyRecord` of the meshes it remeshed (their faces and the
positions they were remeshed to) and the steps; a checkpoint holds it, and a resumed run (or
``torchir export``) rebuilds the scene and the parameters at that topology before their
state is loaded. Under DDP, process 0 remeshes and broadcasts the mesh: every process takes
the same one.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
import sys
from typing import Any, Optional

import numpy as np
import torch

__all__ = ["RemeshSchedule", "TopologyRecord", "check_remesh", "check_remesh_truth", "apply_remesh_schedule",
           "restore_topology", "vertex_counts"]

REMESH_KEYS = ("at", "edge_length", "iterations", "project")
FORM = "{at: [steps], edge_length: 0.5, iterations: 5, project: true}"


@dataclass(frozen=True)
class RemeshSchedule:
    """``model.remesh``: when and how the run's meshes are remeshed.

    Attributes:
        at: the steps before which to remesh (increasing, >= 0): ``at: [80]`` remeshes the mesh
            step 79 left, and step 80 renders the new one.
        edge_length: the target edge length as a factor of the mesh's current mean edge (the
            tutorial's 0.5 halves the edges: about 4x the vertices).
        iterations: the remesher's iterations (the tutorial's 5).
        project: project the new vertices onto the current surface (else it is smoothed too).
    """

    at: tuple[int, ...]
    edge_length: float = 0.5
    iterations: int = 5
    project: bool = True

    @classmethod
    def from_config(cls, spec: Any) -> "RemeshSchedule":
        """The checked schedule of a ``model.remesh`` mapping (``ValueError`` naming the key)."""
        if not isinstance(spec, dict):
            raise ValueError(f"model.remesh must be a mapping {FORM}, got {spec!r}")
        unknown = sorted(set(spec) - set(REMESH_KEYS))
        if unknown:
            raise ValueError(f"model.remesh has unknown key(s) {unknown}; allowed: {list(REMESH_KEYS)}")
        if "at" not in spec:
            raise ValueError(f"model.remesh.at is required: the steps before which to remesh, e.g. {FORM}")
        at = spec["at"]
        at = [at] if isinstance(at, int) and not isinstance(at, bool) else at
        if (not isinstance(at, (list, tuple)) or not at
                or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in at)):
            raise ValueError(f"model.remesh.at must be a non-empty list of steps >= 0 (e.g. [80, 160]), got {spec['at']!r}")
        if any(b <= a for a, b in zip(at, at[1:])):
            raise ValueError(f"model.remesh.at must list its steps in increasing order, each once, got {list(at)}")
        edge = spec.get("edge_length", cls.edge_length)
        if isinstance(edge, bool) or not isinstance(edge, (int, float)) or not math.isfinite(edge) or edge <= 0:
            raise ValueError(f"model.remesh.edge_length must be a finite number > 0 (a factor of the mesh's current "
                             f"mean edge length; 0.5 halves the edges), got {edge!r}")
        iterations = spec.get("iterations", cls.iterations)
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"model.remesh.iterations must be an int >= 1 (the tutorial's 5), got {iterations!r}")
        project = spec.get("project", cls.project)
        if not isinstance(project, bool):
            raise ValueError(f"model.remesh.project must be true or false, got {project!r}")
        return cls(tuple(int(s) for s in at), float(edge), iterations, project)


@dataclass
class TopologyRecord:
    """What the run's remeshes changed: per remeshed parameter key, the ``(vertices (V, 3)
    float32, faces (F, 3) int64)`` host tensors of its last remesh (the positions it was remeshed
    to: with the faces, all a resumed run needs to rebuild its scene and parameter), and the
    steps remeshed at."""

    meshes: dict[str, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)
    steps: list[int] = field(default_factory=list)

    def state_dict(self) -> dict[str, Any]:
        """A checkpoint entry (tensors and plain lists: ``torch.load(weights_only=True)`` reads it)."""
        meshes = {key: {"vertices": v, "faces": f} for key, (v, f) in self.meshes.items()}
        return {"meshes": meshes, "steps": list(self.steps)}


def mesh_keys(module: Any) -> list[str]:
    """The run's optimised mesh positions (``<shape>.vertex_positions`` of a scene mesh), in order."""
    return [key for key in module.keys if module.mesh_id(key) is not None]


def check_remesh(module: Any, schedule: RemeshSchedule) -> None:
    """Refuse a ``model.remesh`` the run cannot follow (called once the module has its
    parameters and sampler): no mesh parameter, an emissive mesh, a truth or bounds given per
    vertex, a sampler that cannot move to a new scene."""
    from ..geometry._mesh import scene_mesh
    from ..samplers import PixelSampler, ReSTIRSampler

    keys = mesh_keys(module)
    if not keys:
        raise ValueError(f"model.remesh: no mesh to remesh; it applies to optimised mesh vertex positions "
                         f"('<shape>.vertex_positions' of a mesh in the scene), the parameters are {module.keys}")
    for key in keys:
        config = module.configs[key]
        if scene_mesh(module.scene, key).emitter() is not None:
            raise ValueError(f"model.remesh: mesh {module.mesh_id(key)!r} ({key!r}) is an area light, which cannot be remeshed")
        truth = config.truth
        if truth is not None and key not in module.truth_meshes:
            raise ValueError(f"model.remesh: parameters[{key!r}].truth is a vertex list ({_short(truth)}), whose per-vertex "
                             f"error means nothing once the mesh is remeshed: give the true mesh as a file, truth: file.ply")
        if config.bounds is not None and any(isinstance(b, (list, tuple)) for b in config.bounds):
            raise ValueError(f"model.remesh: parameters[{key!r}].bounds are given per entry, which a remesh does not keep "
                             f"(the vertex count changes): give scalar bounds [lo, hi], or none")
    sampler = module.sampler
    if sampler is not None and not isinstance(sampler, (PixelSampler, ReSTIRSampler)):
        raise ValueError(f"model.remesh: the sampler {type(sampler).__name__} cannot be moved to the remeshed scene "
                         f"(pixel samplers and restir can): drop model.sampler or model.remesh")


def check_remesh_truth(module: Any, truth: dict[str, torch.Tensor]) -> None:
    """Refuse a remeshed parameter among the run's per-vertex error truths (``module._truth``):
    a synthetic run's default truth is the loaded mesh's vertex list."""
    for key in mesh_keys(module):
        if key in truth:
            raise ValueError(f"model.remesh: parameters[{key!r}] has no truth mesh, so this synthetic run would measure "
                             f"its error per vertex against the loaded mesh, which means nothing once it is remeshed: "
                             f"give the true mesh as a file, truth: file.ply")


def apply_remesh_schedule(module: Any, step: int) -> bool:
    """Remesh every mesh parameter if ``step`` is scheduled (and not done yet); True if it did."""
    schedule: Optional[RemeshSchedule] = module.remesh_schedule
    record: TopologyRecord = module.topology
    if schedule is None or step not in schedule.at or step in record.steps:
        return False
    trainer = module.trainer
    strategy = trainer.strategy
    values = {k: v.detach() for k, v in module.scene_values().items()}
    for key in mesh_keys(module):
        vertices, faces, edge = None, None, 0.0
        if trainer.is_global_zero:  # one process remeshes, the others take its mesh
            vertices, faces, edge = _remesh(values[key], module.mesh_faces(key), schedule)
        vertices, faces, edge = strategy.broadcast((vertices, faces, edge), src=0)
        before = values[key].numel() // 3
        _replace(module, key, vertices, faces, trainer.optimizers)
        record.meshes[key] = (vertices, faces)
        if trainer.is_global_zero:
            sys.stdout.write(f"[torchir] step {step}: remeshed {key}: {before} -> {len(vertices)} vertices, "
                             f"{len(faces)} faces (edges {edge:.4g}: {schedule.edge_length:g} x the mean)\n")
            sys.stdout.flush()
    record.steps.append(step)
    from .param_swap import rewrap_distributed

    rewrap_distributed(trainer)
    return True


def restore_topology(module: Any, state: dict[str, Any]) -> None:
    """Rebuild ``module``'s scene and parameters at a checkpoint's topology (``on_load_checkpoint``,
    before Lightning loads the parameters' state into them and builds the optimiser)."""
    steps = [int(s) for s in state.get("steps", [])]
    for key, mesh in state.get("meshes", {}).items():
        if key not in module.keys or module.mesh_id(key) is None:
            raise ValueError(f"the checkpoint remeshed {key!r}, which is no mesh parameter of this run: resume with its config")
        vertices, faces = mesh["vertices"].cpu(), mesh["faces"].cpu()
        _replace(module, key, vertices, faces, optimizers=[])
        module.topology.meshes[key] = (vertices, faces)
    module.topology.steps = steps


def vertex_counts(module: Any) -> dict[str, float]:
    """``{"vertices/<key>": V}`` of each mesh parameter of a run with ``model.remesh`` (else ``{}``)."""
    if module.remesh_schedule is None:
        return {}
    keys = mesh_keys(module)
    return {f"vertices/{p.key}": float(_vertex_count(p)) for p in module.scene_parameters if p.key in keys}


# ----------------------------------------------------------------------------- internals
def _remesh(positions: torch.Tensor, faces: torch.Tensor, schedule: RemeshSchedule) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Remesh one mesh (flat ``(3V,)`` positions, ``(F, 3)`` faces) to ``edge_length`` times its
    welded mean edge: host ``(vertices (V', 3) float32, faces (F', 3) int64)`` and that length."""
    from ..geometry._mesh import host_positions, mean_edge_length, weld_positions
    from ..geometry.remesh import _remesh_arrays

    p = host_positions(positions.reshape(-1, 3))
    f = faces.cpu().numpy().astype(np.int64)
    welded = weld_positions(p, f)
    edge = schedule.edge_length * mean_edge_length(p[welded.representative], welded.faces)
    v_new, f_new = _remesh_arrays(p, f, edge, schedule.iterations, schedule.project)
    return torch.from_numpy(v_new.astype(np.float32)), torch.from_numpy(f_new.astype(np.int64)), edge


def _replace(module: Any, key: str, vertices: torch.Tensor, faces: torch.Tensor, optimizers: list) -> None:
    """Put the mesh ``(vertices, faces)`` into ``module.scene`` under ``key``'s shape, rebuild the
    parameter at those positions, give ``optimizers`` its new latent (fresh state) and move the
    sampler to the new scene."""
    from ..geometry import LargeSteps, replace_mesh
    from .param_swap import swap_parameter
    from .parameters import LargeStepsParameter, SceneParameter

    index = module.keys.index(key)
    old = module.scene_parameters[index]
    warned = set(module.scene._warned)
    module.scene = replace_mesh(module.scene, module.mesh_id(key), vertices, faces)
    module.scene._warned |= warned  # the run has shown its scene's warnings once: not again after each remesh
    positions = module.scene.get(key).detach().to(old.latent.device)
    if isinstance(old, LargeStepsParameter):
        new = LargeStepsParameter(key, LargeSteps(module.scene, key, lambda_=old.large_steps.lambda_), positions)
    else:
        new = SceneParameter(key, positions, module.configs[key])
    module.scene_parameters[index] = new
    for optimizer in optimizers:
        swap_parameter(optimizer, old.latent, new.latent)
    _move_sampler(module.sampler, module.scene)
    module._distance_cache = None


def _move_sampler(sampler: Any, scene: Any) -> None:
    """Point the run's sampler at the new scene: a pixel sampler's pmf is per pixel (the views
    stay; Stage 1 refreshes itself on the parameters' new shape); ReSTIR's reservoirs are per
    scene, so they are dropped (its chosen options stay)."""
    from ..samplers import ReSTIRSampler

    if sampler is None:
        return
    if isinstance(sampler, ReSTIRSampler):
        from ..integrators.restir_di import check_scene

        check_scene(scene.mi_scene)
        sampler.reset()
    sampler.scene = scene


def _vertex_count(parameter: Any) -> int:
    """The vertices ``V`` of a mesh parameter (a Large Steps latent holds the welded ones only)."""
    large_steps = getattr(parameter, "large_steps", None)
    return large_steps.vertex_count if large_steps is not None else parameter.latent.numel() // 3


def _short(value: Any) -> str:
    """A config value, shortened for a message."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
