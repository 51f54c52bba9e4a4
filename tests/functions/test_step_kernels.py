"""A shape step on a mesh as exporters write it compiles no kernel after warm-up.

A projective integrator's boundary pass runs on welded faces (:mod:`torchir.welding`). Those
index arrays were made from NumPy afresh every step; Dr.Jit maps a NumPy array without copying
and compiles its loads as aligned or not by where the data happens to start, so the weld's
kernels flipped between variants and a step of Mitsuba's shape tutorial compiled 1-3 kernels
after warm-up (seconds each on LLVM). The weld now keeps one aligned Dr.Jit array per topology.
"""
from __future__ import annotations

import mitsuba as mi
import pytest
import torch

import torchir
from torchir.functions import render
from torchir.geometry import AdamUniform, LargeSteps

KEY = "shape.vertex_positions"
STEPS = 8  # each step makes the weld's arrays anew: a new allocation, its alignment by chance


@pytest.fixture(scope="module")
def seamed_sphere_scene(tmp_path_factory):
    """A UV sphere as an exporter writes it (seam and poles repeated; 64 x 32, so that its index
    arrays come from the system allocator, 16-byte aligned by chance, not from NumPy's cache of
    small blocks), diffuse, under a constant environment, rendered by ``direct_projective`` at
    16² (the shape tutorial's setting in small)."""
    from torchir.bench.exported_meshes import uv_sphere, write_ply
    from torchir.scenes._common import perspective

    path = tmp_path_factory.mktemp("seamed") / "uv_sphere.ply"
    write_ply(uv_sphere(segments=64, rings=32), path)

    sensor = perspective([0.3, 0.4, 3.0], [0, 0, 0], [0, 1, 0], 40.0, 16, 16)
    sensor["film"]["sample_border"] = True
    return torchir.Scene.from_dict({
        "type": "scene", "integrator": {"type": "direct_projective", "sppi": 0}, "sensor": sensor,
        "shape": {"type": "ply", "filename": str(path), "bsdf": {"type": "diffuse"}},
        "light": {"type": "constant"},
    })


def test_a_seamed_mesh_step_compiles_nothing_after_warm_up(seamed_sphere_scene):
    scene = seamed_sphere_scene
    large_steps = LargeSteps(scene, "shape", 25.0)
    assert large_steps.welded_count < large_steps.vertex_count  # the weld is in play
    u = large_steps.to_differential(scene.get(KEY)).requires_grad_()
    opt = AdamUniform([u], lr=0.01)
    target = torch.full((3, 16, 16), 0.3)

    def step(seed: int) -> None:
        opt.zero_grad()
        image = render(scene, {KEY: large_steps.from_differential(u)}, spp=2, seed=seed)
        (image - target).abs().mean().backward()
        opt.step()

    for seed in range(2):
        step(seed)
    with torchir.backend.count_kernels() as stats:
        for seed in range(100, 100 + STEPS):
            step(seed)
    assert stats.launched > 0
    assert stats.compiled == 0, f"{stats.compiled} kernels compiled in {STEPS} steps after warm-up"
    assert torch.isfinite(u.grad).all() and u.grad.abs().sum() > 0
