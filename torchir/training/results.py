"""The answer of a run, written for people: ``result.yaml``, parameter files and final images.

Used at the end of a run, on Ctrl-C (:class:`~torchir.training.callbacks.ResultWriter`) and by
``torchir export CKPT`` (from any checkpoint), so all three write the same thing:

- ``result.yaml``: the step, and each optimised parameter's recovered value *in its own units*
  (the scene value ``T(latent)``, not the latent): small values inline, ``(H, W, C)`` textures
  as ``parameters/<key>.exr``, other large arrays (vertex positions) as ``parameters/<key>.npy``;
  with the parameter error against the truth where one is known.
- ``meshes/<shape>.ply``: each optimised mesh (a ``<shape>.vertex_positions`` parameter) with the
  scene's faces; its ``result.yaml`` entry names the file and, with a truth mesh, holds the
  squared symmetric Chamfer and the Hausdorff distances to it and the Chamfer sampling floor.
- ``images/final_v<view>.{png,exr}``: low-noise renders of the recovered scene.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from ..imageio import write_image

__all__ = ["write_results", "parameter_entry", "INLINE_MAX"]

INLINE_MAX = 16  # values up to this many entries go into result.yaml itself


def _rounded(x: torch.Tensor) -> Any:
    """Nested lists of floats with 6 significant digits (a scalar for one entry)."""
    values = np.vectorize(lambda v: float(f"{v:.6g}"))(x.double().cpu().numpy()) if x.numel() else x.cpu().numpy()
    return values.item() if x.numel() == 1 else values.tolist()


def parameter_entry(key: str, value: torch.Tensor, folder: Path) -> Any:
    """``result.yaml``'s entry for one parameter; writes a file beside it for large values."""
    value = value.detach().float().cpu()
    if value.numel() <= INLINE_MAX:
        return _rounded(value)
    files = folder / "parameters"
    files.mkdir(parents=True, exist_ok=True)
    if value.dim() == 3 and value.shape[-1] in (1, 3):  # a texture, Mitsuba's (H, W, C)
        path = write_image(files / f"{key}.exr", value.permute(2, 0, 1))
    else:
        path = files / f"{key}.npy"
        np.save(path, value.cpu().numpy())
    return {"file": str(path.relative_to(folder)), "shape": list(value.shape), "mean": _rounded(_summary_mean(value))}


def mesh_entry(folder: Path, shape: str, vertices: torch.Tensor, faces: torch.Tensor) -> str:
    """Write ``meshes/<shape>.ply`` (binary PLY) in ``folder``; its path relative to ``folder``."""
    from ..geometry import write_mesh

    path = write_mesh(folder / "meshes" / f"{shape}.ply", vertices.detach().reshape(-1, 3).cpu(), faces)
    return str(path.relative_to(folder))


def _summary_mean(value: torch.Tensor) -> torch.Tensor:
    """Per-channel mean of a ``(..., C)`` value with few channels; one mean for a flat ``(n,)`` one."""
    if value.dim() >= 2 and value.shape[-1] <= INLINE_MAX:
        return value.reshape(-1, value.shape[-1]).mean(0)
    return value.mean()


def write_results(module, folder: str | Path, step: int, views: Optional[list[int]] = None, images: bool = True) -> Path:
    """Write ``result.yaml`` (+ parameter files, + final images of ``views``) into ``folder``.

    Args:
        module: an :class:`~torchir.training.InverseRenderingModule`.
        folder: the run folder (or any folder: ``torchir export --out``).
        step: the optimiser step the values are from.
        views: sensors to render final images of (default: up to 4 of the scene's sensors).
        images: render the final images (``preview_spp`` samples per pixel).

    Returns:
        The path of ``result.yaml``.
    """
    import yaml

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        values = {k: v.detach() for k, v in module.scene_values().items()}
        truth_meshes = getattr(module, "truth_meshes", {})  # (modules without meshes need not have these)
        truth = module.ground_truth(explicit_only=True)
        if truth and truth_meshes:  # a truth mesh's error is its distances, not an RMSE over vertices
            truth = {k: v for k, v in truth.items() if k not in truth_meshes}
        error = module.parameter_error(truth) if truth else None
        distances = module.mesh_distances() if truth_meshes else {}
        floors = module.distance_floors() if truth_meshes else {}
    result: dict[str, Any] = {"step": int(step), "scene": module.scene.name, "parameters": {}}
    for key, value in values.items():
        entry = parameter_entry(key, value, folder)
        shape = module.mesh_id(key) if hasattr(module, "mesh_id") else None
        if shape is not None:
            entry = {"mesh": mesh_entry(folder, shape, value, module.mesh_faces(key)), **entry}
            if key in truth_meshes:
                entry["truth"] = str(module.configs[key].truth)
                for name in ("chamfer", "hausdorff"):
                    entry[name] = float(f"{distances[f'{name}/{key}']:.6g}")
                entry["chamfer_floor"] = float(f"{floors[key]:.6g}")
        result["parameters"][key] = entry
    if error is not None:
        result["param_error"] = float(f"{error:.6g}")
    path = folder / "result.yaml"
    path.write_text(
        "# recovered scene parameters, in the scene's own units (torchir " + _version() + ")\n"
        + yaml.safe_dump(result, sort_keys=False, default_flow_style=None, width=100)
    )
    if images:
        views = list(range(min(4, module.scene.sensor_count))) if views is None else views
        for view in views:
            image = module.preview(view, values)
            for suffix in ("png", "exr"):
                write_image(folder / "images" / f"final_v{view}.{suffix}", image)
    return path


def _version() -> str:
    from .. import __version__

    return __version__
