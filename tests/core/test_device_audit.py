"""What would leave the GPU in a step, found on any machine (``torchir.device_audit``).

On the CPU every tensor is on the host, so a torch factory without a ``device`` or a ``.cpu()``
in a training step runs unnoticed; on a GPU the first is a device mismatch and the second a copy
and a wait every step. The audit records both; these tests run each technique's step under it
(on LLVM in CI, on CUDA in ``scripts/gpu_check.sh``) and fail on any such call torchir makes.
"""
from __future__ import annotations

import importlib.util
import textwrap

import drjit as dr
import lightning.pytorch as pl
import pytest
import torch
from PIL import Image

import torchir
from torchir import backend
from torchir.device_audit import device_audit
from torchir.functions import render
from torchir.modules import CrossBilateralDenoiser, L2Loss, LOILoss, TargetAwareDenoiser
from torchir.modules._banded import native_products
from torchir.samplers import AdaptivePixelSampler, ReSTIRSampler, sampled_loss
from torchir.training import InverseRenderingModule, ViewDataModule

_AUDITED_MODULE = """
import kornia
import mitsuba as mi
import torch

def make(x):
    a = torch.zeros(3)
    b = torch.zeros(3, device=x.device)
    c = torch.ones_like(x)
    moved = x.cpu()
    scalar = float(x.sum())
    host = mi.TensorXf(mi.Float(1.0, 2.0, 3.0, 4.0, 5.0, 6.0), (2, 3)).numpy()  # host: a Dr.Jit array
    blurred = kornia.filters.gaussian_blur2d(x.reshape(1, 1, 1, -1).expand(1, 1, 5, 5), (3, 3), (1.0, 1.0))
    indices = torch.arange(4, device="cpu") * 2
    listed = indices.tolist()
    on_device = indices.to(x.device)
    back = on_device.tolist()
    return a, b, c, moved, scalar, host, blurred, listed, back


def reads(x, scalar):
    cube = x.reshape(2, 3, 4)
    moved = cube.cpu()
    array = moved.numpy()  # host: moved is .cpu()'s result
    listed = cube.tolist()
    value = scalar.item()
    return moved, array, listed, value
"""


@pytest.fixture(scope="module")
def audited(tmp_path_factory):
    folder = tmp_path_factory.mktemp("audited")
    path = folder / "audited_code.py"
    path.write_text(textwrap.dedent(_AUDITED_MODULE))
    spec = importlib.util.spec_from_file_location("audited_code", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module, str(folder)


def _lines(findings) -> list[tuple[str, int]]:
    return [(f.call, int(f.site.split(":")[1].split()[0])) for f in findings]


def test_audit_finds_factories_without_device_and_host_transfers(audited):
    module, folder = audited
    with device_audit(roots=[folder]) as audit:
        module.make(torch.ones(5))
    assert _lines(audit.factories()) == [("torch.zeros", 7)]  # not line 8 (a device), nor ones_like
    # not line 15: host bookkeeping by intent (device="cpu"); line 17: the same values moved to x's device
    assert sorted(_lines(audit.transfers(min_elements=2))) == [("Tensor.cpu", 10), ("Tensor.tolist", 17), ("drjit.numpy", 12)]
    assert {(f.call, f.elements) for f in audit.transfers(min_elements=2)} == {("drjit.numpy", 6), ("Tensor.cpu", 5), ("Tensor.tolist", 4)}  # every entry of a tensor, not its rows
    assert ("Tensor.__float__", 11) in _lines(audit.transfers())  # a scalar read: a sync on a GPU
    library = [f for f in audit.findings("factory") if f.origin != f.site]  # kornia's own sigma tensor
    assert library and all(f.origin.startswith("kornia") and f.site.endswith("make") for f in library)
    assert set(audit.transfers(own=True)) <= set(audit.transfers(own=False))


def test_transfers_count_every_entry_of_a_multidimensional_tensor(audited):
    """A torch transfer's ``elements`` is the tensor's entry count (``numel``), whatever its
    shape: a (2, 3, 4) tensor's ``cpu``, ``numpy`` and ``tolist`` calls move 24 entries (its
    ``len`` is 2), a 0-d tensor's ``.item()`` one (it has no ``len``)."""
    module, folder = audited
    lines = textwrap.dedent(_AUDITED_MODULE).splitlines()
    line = {call: next(i for i, text in enumerate(lines, 1) if f"= {what}" in text)
            for call, what in (("cpu", "cube.cpu()"), ("numpy", "moved." + "numpy()"), ("tolist", "cube.tolist()"), ("item", "scalar.item()"))}
    with device_audit(roots=[folder]) as audit:
        module.reads(torch.arange(24.0), torch.tensor(2.5))
    assert sorted((f.call, int(f.site.split(":")[1].split()[0]), f.elements) for f in audit.transfers()) == sorted(
        [("Tensor.cpu", line["cpu"], 24), ("Tensor.numpy", line["numpy"], 24), ("Tensor.tolist", line["tolist"], 24),
         ("Tensor.item", line["item"], 1)]), str(audit)


def test_audit_sees_nothing_outside_its_roots_or_its_block(audited):
    module, folder = audited
    numpy_before = dr.ArrayBase.__dict__["numpy"]
    with device_audit(roots=[folder + "_elsewhere"]) as audit:
        module.make(torch.ones(5))
    assert audit.findings() == [] and str(audit).startswith("no factory")
    assert dr.ArrayBase.__dict__["numpy"] is numpy_before  # Dr.Jit's methods are restored
    with device_audit(roots=[folder]) as audit:
        pass
    module.make(torch.ones(5))
    assert audit.findings() == []


SMALL = 16  # elements: a 4x4 transform or a camera's matrix row; an image, texture, map or batch is more


def _clean(audit, what: str, per_step: int = 1) -> None:
    """No factory without a device, and no host transfer of more than ``SMALL`` elements made
    ``per_step`` or more times (once per step of a ``per_step``-step run). Smaller reads (a
    finiteness check, a light's transform for ReSTIR's scene watch) are syncs, not copies of
    images: ``scripts/gpu_check.sh`` measures what they cost."""
    transfers = [f for f in audit.transfers(min_elements=SMALL + 1) if f.count >= per_step]
    assert not audit.factories() and not transfers, f"{what}:\n{audit}"


def test_render_and_its_gradient_stay_on_the_device():
    scene = torchir.Scene.builtin("cbox", resolution=16)
    red = scene.get("red.reflectance.value").requires_grad_()
    target = render(scene, {}, spp=4, seed=1)
    with device_audit() as audit:
        loss = (render(scene, {"red.reflectance.value": red}, spp=4, seed=0) - target).square().mean()
        loss.backward()
    _clean(audit, "render + backward")
    assert red.grad.device == target.device == torch.device(backend.device())


def test_restir_render_stays_on_the_device():
    scene = torchir.Scene.builtin("painting", resolution=16)
    name = next(n for n in scene.parameter_names(differentiable_only=True) if "reflectance" in n)
    value = scene.get(name).requires_grad_()
    sampler = ReSTIRSampler(scene, preset="restir")
    render(scene, {name: value}, spp=1, seed=0, sampler=sampler).mean().backward()  # sizes its search radius once
    with device_audit() as audit:
        for step in (1, 2):  # each reuses the step before's reservoirs
            render(scene, {name: value}, spp=1, seed=step, sampler=sampler).mean().backward()
    _clean(audit, "ReSTIR render + backward", per_step=2)
    # the scene watches and the camera check read a light's, shape's or camera's transform only
    # when its variables changed: none did, so none was read (each a sync on a GPU)
    assert not [f for f in audit.transfers() if f.site.startswith("torchir/integrators/")], str(audit)


def test_adaptive_pixel_step_stays_on_the_device():
    scene = torchir.Scene.builtin("cbox", resolution=16)
    key = "red.reflectance.value"
    params = {key: scene.get(key).requires_grad_()}
    target = render(scene, {}, spp=16, seed=3)
    sampler = AdaptivePixelSampler(scene, budget=64, seed=0)
    with device_audit() as audit:
        for step in range(3):
            if step % 2 == 0:
                sampler.update({key: params[key].detach()}, [target], L2Loss(), step=step)
            batch = sampler.sample()
            sampled_loss(scene, params, batch, [target], [0], L2Loss(), seed=lambda v: step, spp=2).loss.backward()
    _clean(audit, "pixel sampler update + sample + loss", per_step=3)


def test_loi_loss_and_denoisers_stay_on_the_device():
    torch.manual_seed(0)
    image = torch.rand(1, 3, 24, 24, requires_grad=True)
    target = torch.rand(1, 3, 24, 24)
    with native_products(False), device_audit() as audit:  # the torch path: what a GPU runs
        LOILoss()(image, target).backward()
        TargetAwareDenoiser()(image, target).sum().backward()
        guide = torch.rand(1, 7, 24, 24)  # albedo, normal, depth
        CrossBilateralDenoiser()(image, target, guide=guide).sum().backward()
    _clean(audit, "LOI loss, target-aware and cross-bilateral denoisers")


def test_training_steps_on_a_photo_stay_on_the_device(tmp_path):
    scene = torchir.Scene.builtin("cbox", resolution=8)
    photo = render(scene, {}, spp=16, seed=5).clamp(0, 1).pow(1 / 2.2).mul(255).round().byte()
    Image.fromarray(photo.permute(1, 2, 0).cpu().numpy()).save(tmp_path / "photo.png")  # as a camera app writes it
    module = InverseRenderingModule(scene="cbox", resolution=8, spp=1, parameters={"red.reflectance.value": {}})
    trainer = pl.Trainer(accelerator=backend.device(), max_steps=4, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    with device_audit() as audit:
        trainer.fit(module, ViewDataModule(targets=[str(tmp_path / "photo.png")], saturation=None))
    assert trainer.global_step == 4
    _clean(audit, "four training steps on a PNG target", per_step=4)


def test_trainer_on_another_device_than_the_renderer_names_the_fix(monkeypatch):
    monkeypatch.setattr(backend, "device", lambda: "cuda")
    from torchir.training.module import _check_trainer_device

    with pytest.raises(ValueError, match="trainer runs on cpu.*cuda tensors.*trainer.accelerator: cuda"):
        _check_trainer_device(torch.device("cpu"))
    _check_trainer_device(torch.device("cuda", 0))


def test_pixel_maps_are_reduced_where_the_process_group_can_reduce(monkeypatch):
    from torchir.samplers.pixel import _reduction_device

    assert _reduction_device("gloo") == torch.device("cpu")  # the host maps as they are
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 1)
    assert _reduction_device("nccl") == torch.device("cuda", 1)  # NCCL reduces CUDA tensors only


def test_batches_keep_their_bookkeeping_on_the_host():
    device = torch.device(backend.device())
    batch = {"view": torch.tensor([0], device="cpu"), "lossy": torch.tensor([False], device="cpu"),
             "chroma": torch.tensor([[1, 1, 1]], device="cpu"), "target": torch.zeros(1, 3, 4, 4, device=device),
             "quantisation": torch.zeros(1, 3, 8, 8, device=device)}
    moved = ViewDataModule().transfer_batch_to_device(batch, device, 0)
    assert all(moved[key] is batch[key] for key in ("view", "lossy", "chroma"))  # read by the step on the host
    assert moved["target"].device == moved["quantisation"].device == device
