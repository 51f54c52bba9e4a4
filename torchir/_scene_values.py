"""How torch values map onto Mitsuba's parameter types (shapes, layouts), and what to say about
a parameter that cannot be bound."""
from __future__ import annotations

import math
from typing import Any

import drjit as dr

__all__: list[str] = []


def _is_vector_array(value: Any) -> bool:
    """A dynamic Dr.Jit array of fixed-size float vectors (Color3f, Point3f, Vector2f, ...)."""
    return (
        dr.is_array_v(value)
        and dr.depth_v(value) == 2
        and dr.size_v(value) != dr.Dynamic
        and dr.is_dynamic_v(value)
        and dr.type_v(value) == dr.VarType.Float32
        and not dr.is_matrix_v(value)
    )


def _is_flat_float(value: Any) -> bool:
    return (
        dr.is_array_v(value)
        and dr.depth_v(value) == 1
        and dr.is_dynamic_v(value)
        and dr.type_v(value) == dr.VarType.Float32
        and not dr.is_tensor_v(value)
    )


def _is_transform(value: Any) -> bool:
    """A 4x4 (affine) transform such as a shape's ``to_world``, bound from torch as ``(4, 4)``."""
    return type(value).__name__ in ("Transform4f", "AffineTransform4f")


def _torch_shape(value: Any) -> tuple[tuple[int, ...], bool]:
    """(torch shape, bindable) of a Mitsuba parameter value."""
    if _is_transform(value):
        return (4, 4), dr.width(value.matrix) == 1
    if dr.is_tensor_v(value):
        return tuple(value.shape), dr.type_v(value) == dr.VarType.Float32
    if _is_flat_float(value):
        return (dr.width(value),), True
    if _is_vector_array(value):
        n, k = dr.width(value), dr.size_v(value)
        return ((k,) if n == 1 else (n, k)), True
    if isinstance(value, (int, float, bool)):
        return (), False
    try:
        import numpy as np

        return tuple(np.array(value).shape), False
    except Exception:  # noqa: BLE001 - some Mitsuba values have no array form
        return (), False


def _same_layout(got: tuple[int, ...], expected: tuple[int, ...]) -> bool:
    """Shapes match, up to leading/trailing singleton axes ((3,) vs (1, 3), () vs (1,))."""
    squeeze = lambda s: tuple(d for d in s if d != 1)  # noqa: E731
    return got == expected or (squeeze(got) == squeeze(expected) and math.prod(got) == math.prod(expected))



def _unbindable_hint(name: str, type_name: str) -> str:
    """What to do instead of binding parameter ``name`` of Mitsuba type ``type_name``."""
    if type_name in ("TensorXu8", "TensorXf16"):
        return (
            f"it is a texture stored as {type_name[7:]} (an 8/16-bit image file): load the scene with "
            f"texture_storage='float' (the default of Scene.from_file/from_dict; torchir fit uses it), or give "
            f"the bitmap format=\"variant\" in the scene"
        )
    if name.endswith(".faces") or type_name.startswith(("UInt", "Int")) or "Xu" in type_name or "Xi" in type_name:
        return "it holds integers (e.g. mesh faces or indices), which have no gradient: optimise vertex_positions or a pose instead"
    return "torchir binds float textures/tensors, float arrays, colours, points, vectors and 4x4 transforms"
