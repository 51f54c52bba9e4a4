"""A mesh render leaves nothing grad-enabled behind. Mitsuba's symbolic calls trace every shape
registered in the process, so a mesh whose bound positions stayed grad-enabled (after a
render's backward, or after a forward-only render of a tensor that requires grad) made the next
``prbvolpath`` backward of *another* scene fail LLVM's verifier ("Instruction does not dominate
all uses") and abort the process: a shape test followed by a volume test killed a CI worker.

Each case runs in a fresh process (:func:`tests.helpers.run_in_fresh_process`): without the fix
the process aborts, and the module's own scenes must be the only ones alive."""
from __future__ import annotations

import pytest

from tests.helpers import ROOT, run_in_fresh_process

PROGRAM = f"""
import sys
import mitsuba as mi
import torch
import torchir
from torchir.derived import load_callable
from torchir.functions import render

torchir.backend.set_variant("auto")
mode = sys.argv[1] if len(sys.argv) > 1 else MODE
mesh = torchir.Scene.from_dict({{
    "type": "scene", "integrator": {{"type": "prb", "max_depth": 2}},
    "sensor": {{"type": "perspective", "fov": 40,
               "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
               "film": {{"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {{"type": "box"}}}}}},
    "cube": {{"type": "cube"}},
    "light": {{"type": "point", "position": [0, 0, 3], "intensity": {{"type": "rgb", "value": 5.0}}}},
}})
key = "cube.vertex_positions"
v = mesh.get(key).requires_grad_(True)
image = render(mesh, {{key: v}}, spp=2, seed=0)
if mode == "backward":
    image.sum().backward()
volume = torchir.Scene.from_dict(load_callable("{ROOT}/configs/examples/volume_from_views.py:build")(
    resolution=8, grid=4, views=1, max_depth=3))
name = "object.interior_medium.sigma_t.data"
density = volume.get(name).requires_grad_(True)
render(volume, {{name: density}}, spp=1, seed=0).sum().backward()
assert density.grad is not None and torch.isfinite(density.grad).all() and float(density.grad.abs().sum()) > 0
if mode == "forward":  # the mesh render's backward, after the volume's, re-binds its own values
    image.sum().backward()
    late = v.grad.clone()
    v.grad = None
    render(mesh, {{key: v}}, spp=2, seed=0).sum().backward()
    assert float(late.abs().sum()) > 0
    torch.testing.assert_close(late, v.grad, rtol=1e-5, atol=1e-7)
print("ok")
"""


@pytest.mark.parametrize("mode", ["backward", "forward"])
def test_a_volume_backward_after_a_mesh_render_runs_and_the_mesh_gradient_stays_right(mode):
    """``backward``: mesh render and backward, then a volume render and backward. ``forward``: a
    mesh render (no backward yet), then the volume's render and backward, then the mesh render's
    backward, which equals the same render's backward run at once."""
    out = run_in_fresh_process(f"MODE = {mode!r}\n" + PROGRAM)
    assert out.split()[-1] == "ok"
