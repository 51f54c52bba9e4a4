"""torchir._frozen: a frozen call leaves every live scene's buffers as they were.

Dr.Jit 1.5's frozen functions assign the registry's variables back after a call and sometimes
hand a mesh a new variable aliasing its old one's memory without owning it (a use-after-free:
a session scene's vertices changed under a later test). The guard holds each live scene's
buffers during the call and puts back any that changed."""
from __future__ import annotations

import gc
import pathlib
import re

import torchir  # noqa: I001  (before torch)
import drjit as dr
import mitsuba as mi
import numpy as np

from torchir import _frozen
from torchir.scene import live_scenes

KEY = "large-box.vertex_positions"


def _reassign(scene: torchir.Scene, key: str, value) -> None:
    """Give ``key`` another variable, as Dr.Jit's assignment after a frozen call does (no update)."""
    handle, value_type, _node, _flags = scene.params.properties[key]
    scene.params.set_property(handle, value_type, value)


def test_a_buffer_reassigned_inside_a_frozen_call_is_put_back():
    rendered, bystander = torchir.Scene.builtin("cbox", resolution=8), torchir.Scene.builtin("painting", resolution=8)
    texture = "canvas.bsdf.reflectance.data"
    before = {s: {k: s.params[k] for k in (KEY, texture) if k in s.params} for s in (rendered, bystander)}
    indices = {s: {k: (v.array.index if dr.is_tensor_v(v) else v.index) for k, v in d.items()} for s, d in before.items()}
    values = {s: {k: np.array(v).copy() for k, v in d.items()} for s, d in before.items()}
    repairs = _frozen.repairs()
    with _frozen.replay_guard():
        _reassign(rendered, KEY, mi.Float(np.array(rendered.params[KEY])))   # same values, a new variable
        _reassign(bystander, texture, mi.TensorXf(np.array(bystander.params[texture]) + 1.0))
        assert rendered.params[KEY].index != indices[rendered][KEY]
    assert _frozen.repairs() == repairs + 2
    for scene in (rendered, bystander):
        for key, value in values[scene].items():
            now = scene.params[key]
            assert (now.array.index if dr.is_tensor_v(now) else now.index) == indices[scene][key]
            np.testing.assert_array_equal(np.array(now), value)


def _buffer_state(scenes) -> list:
    return [(index, np.array(value).tobytes()) for scene in scenes for _entry, value in _frozen._buffers(scene.params)
            for index in [value.array.index if dr.is_tensor_v(value) else value.index]]


def test_frozen_renders_leave_every_live_scene_in_place():
    """Recordings and replays with other scenes alive, created and freed between the calls (as in a
    test run or a notebook): every scene's buffers keep their variables and values. (In one CI
    order, three such renders needed 3 repairs.)"""
    from torchir.functions import render

    scene, bystanders = torchir.Scene.builtin("cbox", resolution=8), [torchir.Scene.builtin("cbox", resolution=8),
                                                                       torchir.Scene.builtin("painting", resolution=8)]
    before = _buffer_state([scene, *bystanders])
    x = scene.get("red.reflectance.value").requires_grad_()
    for seed in range(4):
        render(scene, {"red.reflectance.value": x}, spp=1, seed=seed).sum().backward()
        torchir.Scene.builtin("cbox", resolution=8)  # freed at once: the registry changes between calls
        gc.collect()
        assert _buffer_state([scene, *bystanders]) == before


def test_freed_scenes_are_not_held():
    scene = torchir.Scene.builtin("cbox", resolution=8)
    kept = len(live_scenes())
    torchir.Scene.builtin("cbox", resolution=8)  # dropped at once
    gc.collect()
    assert len(live_scenes()) == kept and scene in live_scenes()


def test_every_frozen_function_in_torchir_is_guarded():
    root = pathlib.Path(torchir.__file__).parent
    unguarded = [f"{p.relative_to(root)}:{n}" for p in root.rglob("*.py") if p.name != "_frozen.py"
                 for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
                 if re.search(r"\bdr\.freeze\(", line) and not line.lstrip().startswith("#")]
    assert unguarded == []
