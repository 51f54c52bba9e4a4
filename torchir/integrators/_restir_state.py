"""What ReSTIR direct illumination keeps between steps: each sensor's reservoir chain, a step's
cache for its backward pass, the multi-view store, and their checkpoint form (numpy arrays)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from . import _light_guide
from ._light import Reservoirs
from ._scene_watch import as_tuples

__all__ = ["STORE", "LOADED", "SensorState", "StepCache", "PassStats", "chain", "chain_to_dict", "chain_from_dict",
           "project", "seen_by", "carry_over", "reservoir_stats"]

STORE = -1  # the state key of the one reservoir store of multiview="carry_over"
LOADED = ("loaded",)  # SensorState.geometry of reservoirs loaded from a state dict


def _signature(scene: mi.Scene) -> tuple:
    """Changes when the topology or the emitter count changes (automatic reset)."""
    return len(scene.emitters()), tuple(int(s.primitive_count()) for s in scene.shapes())


@dataclass
class SensorState:
    """One reservoir chain: the image's, or the gradient's own, of a sensor (or of the store)."""

    prev: Any = None  # Reservoirs of the last step (or None)
    radius: float = 0.0  # resolved neighbour radius
    window: int = 2  # screen-space search half-width in pixels (radius / small footprint)
    steps: int = 0
    signature: tuple = ()
    camera: tuple | None = None  # (sensor matrix, width, height, spp) of ``prev``
    lights: tuple | None = None  # EmitterWatch state when ``prev`` was made
    geometry: tuple | None = None  # GeometryWatch state when ``prev`` was made
    guide: Any = None  # the lanes' light guides (_light_guide.LightGuide; light_guide > 0)


@dataclass
class StepCache:
    """What a step's backward needs: its paths and the reservoirs it reused."""

    sensor: int
    spp: int
    lanes: Any  # Reservoirs of the step (y, W, shading point)
    ray_weight: Any
    prev: Any  # the reservoirs the step combined with (for the decorrelated pass)
    prev_camera: tuple | None = None  # the camera that rendered ``prev``
    zero: Any = None  # (LightSample y0, Float w0): the p̂ = 0 remainder of the gradient


@dataclass
class PassStats:
    """What a pass reports besides its image and reservoirs."""

    neighbor_count: Any = None  # UInt32 per lane: neighbours combined (None: no reuse)
    k: int = 0
    camera: tuple | None = None  # the pass's (sensor matrix, width, height, spp)
    geometry: tuple | None = None  # the scene's geometry (GeometryWatch) during the pass
    zero: Any = None  # (LightSample y0, Float w0) per lane: the p̂ = 0 remainder (restir_di's docstring)
    guide: Any = None  # the lanes' light guides after the pass (light_guide), or None
    timings: dict = field(default_factory=dict)


def project(sensor_obj: mi.Sensor, r) -> tuple[mi.Bool, mi.UInt32]:
    """``(inside, pixel)`` of reservoirs ``r`` in a sensor's film: ``inside`` where the shading
    point projects into the film and faces the camera (its side of the surface: a two-sided
    sheet seen from behind is another reservoir's), ``pixel`` its row-major pixel index."""
    w, h = (int(v) for v in sensor_obj.film().crop_size())
    it = dr.zeros(mi.SurfaceInteraction3f, dr.width(r.valid))
    it.p, it.n = r.p, r.n
    ds, _ = sensor_obj.sample_direction(it, mi.Point2f(0.5), r.valid)
    inside = r.valid & (ds.pdf > 0) & (ds.uv.x >= 0) & (ds.uv.x < w) & (ds.uv.y >= 0) & (ds.uv.y < h)
    inside &= dr.dot(r.n, ds.d) > 0
    pixel = mi.UInt32(dr.clip(mi.Int32(ds.uv.y), 0, h - 1)) * w + mi.UInt32(dr.clip(mi.Int32(ds.uv.x), 0, w - 1))
    return inside, pixel


def seen_by(scene: mi.Scene, sensor: int, r) -> mi.Bool:
    """Which reservoirs ``r`` sensor ``sensor`` sees: they project into its film facing it
    (:func:`project`) and nothing lies between them and the camera (one shadow ray each)."""
    sensor_obj = scene.sensors()[sensor]
    inside, _ = project(sensor_obj, r)
    it = dr.zeros(mi.SurfaceInteraction3f, dr.width(r.valid))
    it.p, it.n = r.p, r.n
    ds, _ = sensor_obj.sample_direction(it, mi.Point2f(0.5), inside)
    return inside & ~scene.ray_test(it.spawn_ray_to(ds.p), inside)


def carry_over(scene: mi.Scene, sensor: int, new, store):
    """The multi-view store (Wang et al. 2023, Alg. 8) after sensor ``sensor`` rendered reservoirs ``new``: ``new`` plus the
    valid reservoirs of ``store`` that the sensor does not see (other views' surfaces, or
    surfaces hidden from this view); the ones it sees are replaced by ``new``."""
    if store is None:
        return new
    keep = dr.compress(store.valid & ~seen_by(scene, sensor, store))
    carried = dr.gather(Reservoirs(), store, keep)
    n_new, n_old = dr.width(new.valid), dr.width(keep)
    merged = dr.zeros(Reservoirs(), n_new + n_old)
    dr.scatter(merged, new, dr.arange(mi.UInt32, n_new))
    if n_old:
        dr.scatter(merged, carried, n_new + dr.arange(mi.UInt32, n_old))
    dr.eval(merged)
    return merged


def chain_to_dict(st: SensorState) -> dict:
    """``st`` as plain values and numpy arrays (a checkpoint's form)."""
    return {
        "radius": st.radius,
        "window": st.window,
        "steps": st.steps,
        "signature": st.signature,
        "camera": st.camera,
        "lights": st.lights,
        "reservoirs": None if st.prev is None else _struct_to_numpy(st.prev),
        "guide": None if st.guide is None else _struct_to_numpy(st.guide),
    }


def chain_from_dict(d: dict) -> SensorState:
    """The chain saved by :func:`chain_to_dict` (older checkpoints' missing entries filled in)."""
    data = d["reservoirs"]
    if data is not None and "offset" not in data:  # older checkpoints: offsets are redrawn
        data = {**data, "offset": np.full((len(data["W"]), 2), np.nan, np.float32)}
    camera = d.get("camera")  # absent in older checkpoints: the first step searches in world space
    return SensorState(
        prev=None if data is None else _struct_from_numpy(Reservoirs(), data), radius=float(d["radius"]),
        window=int(d.get("window", 2)), steps=int(d["steps"]), signature=tuple(d["signature"]),
        camera=None if camera is None else (tuple(camera[0]), *(int(v) for v in camera[1:])),
        lights=as_tuples(d.get("lights")),  # absent: the first step does not reuse
        geometry=LOADED,
        # absent (older checkpoints): relearned
        guide=None if d.get("guide") is None else _struct_from_numpy(_light_guide.LightGuide, d["guide"]),
    )


def chain(states: dict[int, SensorState], scene: mi.Scene, sensor: int) -> SensorState:
    """``states[sensor]``, made afresh when missing or when the scene's topology changed."""
    sig = _signature(scene)
    st = states.get(sensor)
    if st is None or st.signature != sig:
        st = states[sensor] = SensorState(signature=sig)
    return st


def reservoir_stats(r, stats: PassStats) -> dict[str, float]:
    """Mean and max ``M``, share of ``W = 0``, max ``W`` and the share of neighbours combined (host syncs)."""
    v = r.valid
    nv = int(dr.count(v)[0])
    if nv == 0:
        return {"mean_M": 0.0, "max_M": 0.0, "frac_W0": 0.0, "max_W": 0.0, "valid_neighbors": 0.0}
    valid_neighbors = 0.0
    if stats.neighbor_count is not None:
        valid_neighbors = float(dr.sum(stats.neighbor_count)[0]) / (stats.k * nv)
    m = dr.select(v, r.M, 0.0)
    wv = dr.select(v, r.W, 0.0)
    return {
        "mean_M": float(dr.sum(m)[0]) / nv,
        "max_M": float(dr.max(m)[0]),
        "frac_W0": float(dr.count(v & (r.W <= 0))[0]) / nv,
        "max_W": float(dr.max(wv)[0]),
        "valid_neighbors": float(valid_neighbors),
    }


def _leaves(struct_type, prefix=""):
    for name, tp in struct_type.DRJIT_STRUCT.items():
        if hasattr(tp, "DRJIT_STRUCT"):
            yield from _leaves(tp, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", tp


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _set(obj, path: str, value) -> None:
    parts = path.split(".")
    for part in parts[:-1]:
        obj = getattr(obj, part)
    setattr(obj, parts[-1], value)


def _struct_to_numpy(s) -> dict[str, np.ndarray]:
    out = {}
    for path, tp in _leaves(type(s)):
        v = _get(s, path)
        out[path] = np.array(v, copy=True)
        if dr.size_v(tp) != dr.Dynamic and dr.size_v(tp) > 1:
            out[path] = np.stack([np.array(v[i], copy=True) for i in range(dr.size_v(tp))], 1)
    return out


def _struct_from_numpy(struct_type, data: dict[str, np.ndarray]):
    n = len(next(iter(data.values())))
    s = dr.zeros(struct_type, n)
    for path, tp in _leaves(struct_type):
        arr = data[path]
        if arr.ndim == 2:
            value = tp(*[dr.value_t(tp)(np.ascontiguousarray(arr[:, i])) for i in range(arr.shape[1])])
        else:
            value = tp(np.ascontiguousarray(arr))
        _set(s, path, value)
    dr.eval(s)
    return s

