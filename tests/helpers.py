"""What more than one test module uses: small modules the training tests refer to by class path,
shared checks and constants, the training runs' paths, and the "wall" scene of the
``torchir.functions`` tests. Test modules import from here (``from tests.helpers import ...``),
never from one another; fixtures live in the conftest.py files."""
from __future__ import annotations

import math
import os
import re
from pathlib import Path
from types import SimpleNamespace

import mitsuba as mi
import pytest
import torch
from torch import nn

import torchir
from torchir.scenes import _common

ROOT = Path(__file__).resolve().parents[1]  # the repository
DEVICE = torch.device(torchir.backend.device())  # where renders are and tests' own tensors are made (tests/conftest.py)
RES = 16  # every render test uses 16x16 so the kernels compile once


def raised_message(exc, fn, *args, **kw) -> str:
    """The message of the ``exc`` that ``fn(*args, **kw)`` raises (the call must raise it)."""
    with pytest.raises(exc) as info:
        fn(*args, **kw)
    return str(info.value)


def assert_warned_at(record, test_file: str) -> None:
    """Each warning of ``record`` names ``test_file`` (the caller's line). Under mutmut
    (``MUTANT_UNDER_TEST`` set) its trampolines add frames between the caller and torchir, so
    there only a frame outside torchir is asked."""
    files = [w.filename for w in record]
    if "MUTANT_UNDER_TEST" in os.environ:
        assert files and all(os.path.join("torchir", "modules") not in f for f in files), files
    else:
        assert files == [test_file], [(w.filename, w.lineno) for w in record]


def file_target_step(module, target: Path):
    """``(batch, step)`` for driving ``module.training_step`` by hand on one target file, without
    a Trainer: the batch its ``ViewDataModule`` gives (the file read and flagged as the trainer
    reads it), and ``step(i)``, which stands in the trainer the step reads at global step ``i``."""
    from torchir.training import ViewDataModule

    datamodule = ViewDataModule(targets=[str(target)])
    datamodule.trainer = SimpleNamespace(lightning_module=module, world_size=1)  # what setup reads
    datamodule.setup("fit")
    batch = next(iter(datamodule.train_dataloader()))
    module.log = lambda *args, **kwargs: None
    module._truth = {}

    def step(i: int) -> torch.Tensor:
        module._trainer = SimpleNamespace(world_size=1, global_step=i, current_epoch=0, log_every_n_steps=1,
                                          loggers=[], should_stop=False, datamodule=datamodule)
        return module.training_step(batch, 0)

    return batch, step


class NaNAfterLoss(nn.Module):
    """L2 loss that turns NaN from its ``steps``-th call on (to test the NaN guard)."""

    def __init__(self, steps: int = 3) -> None:
        super().__init__()
        self.steps, self.calls = steps, 0

    def forward(self, rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        loss = (rendered - target).square().mean()
        return loss * float("nan") if self.calls > self.steps else loss


def run_in_fresh_process(code: str, timeout: float = 300.0) -> str:
    """Run ``code`` (a Python program that asserts what it checks) in a new interpreter and
    return its stdout; fails the calling test with the program's stderr if it did.

    For tests of frozen render passes that count recordings or compare replays on scenes of
    their own: Dr.Jit 1.5 traverses, and after a frozen call assigns, every instance in its
    registry, so other tests' live scenes are part of each recording (and of its key).
    In a fresh process only the test's own scenes exist. There as here (tests/conftest.py),
    torch's factories make their tensors on the renderer's device."""
    import subprocess
    import sys

    preamble = "import torchir, torch\nif torchir.backend.device() != 'cpu':\n    torch.set_default_device(torchir.backend.device())\n"
    out = subprocess.run([sys.executable, "-c", preamble + code], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


# ------------------------------------------------------------------------------ training runs
def _run_dir(tmp_path: Path, name: str = "quickstart", version: int = 0) -> Path:
    return tmp_path / name / f"version_{version}"


def _latents(ckpt: Path) -> dict[str, torch.Tensor]:
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    return {k: v for k, v in state.items() if k.endswith("latent")}


# ------------------------------------------------------------------ the wall (tests/functions)
# The zero-variance "wall" scene of tests/functions/test_functions_core.py and
# test_functions_pixels.py (its fixtures: tests/functions/conftest.py).
H, W = 4, 6
TEX = "wall.bsdf.reflectance.data"
SUN = "sun.irradiance.value"


def albedo_texture(h: int = H, w: int = W) -> torch.Tensor:
    """(h, w, 3): every texel distinct in R, columns in G, rows in B, all in (0, 1)."""
    y, x = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack([(y * w + x + 1) / (h * w + 1), (x + 1) / (w + 1), (y + 1) / (h + 1)], -1).float()


def wall_dict(rfilter: str = "box", integrator: str = "prb", channels: int = 3, sensors: int = 1) -> dict:
    """The wall; ``sensors=2`` adds sensor 1, the same camera rolled by 180 degrees (pixel (y, x)
    sees texel (y, W-1-x))."""
    tex = albedo_texture()
    if channels == 1:
        tex = tex[..., :1].contiguous()
    film = _common.film(H, W)
    film["rfilter"] = {"type": rfilter}
    scene = {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": 3},
        "sensor": {
            "type": "perspective",
            "fov": 2 * math.degrees(math.atan(1 / 5)),  # half-width 1 at distance 5
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
            "film": film,
            "sampler": {"type": "independent"},
        },
        "wall": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().scale([1.0, H / W, 1.0]),
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "bitmap", "data": mi.TensorXf(tex.cpu().numpy()), "filter_type": "nearest", "raw": True},
            },
        },
        "sun": {"type": "directional", "direction": [0, 0, -1], "irradiance": {"type": "rgb", "value": math.pi}},
    }
    if sensors == 2:
        rolled = dict(scene["sensor"], film=dict(film), sampler={"type": "independent"})
        rolled["to_world"] = mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, -1, 0])
        scene["sensor_1"] = rolled
    return scene


def as_image(texture: torch.Tensor) -> torch.Tensor:
    """(C, H, W) image of the wall with albedo ``texture`` (H, W, C): rows flipped."""
    return texture.flip(0).permute(2, 0, 1)


def as_image1(texture: torch.Tensor) -> torch.Tensor:
    """(C, H, W) image of the wall seen by the rolled sensor 1: columns flipped."""
    return texture.flip(1).permute(2, 0, 1)


def weights(seed: int = 0, shape=(3, H, W)) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator(device=DEVICE).manual_seed(seed)) + 0.5


def tea(v0: int, v1: int, rounds: int = 4) -> tuple[int, int]:
    """The TEA hash (Wheeler & Needham; Zafar et al. 2010) as Mitsuba's sample_tea_32, in Python."""
    mask, total = 0xFFFFFFFF, 0
    for _ in range(rounds):
        total = (total + 0x9E3779B9) & mask
        v0 = (v0 + ((((v1 << 4) & mask) + 0xA341316C) ^ ((v1 + total) & mask) ^ ((v1 >> 5) + 0xC8013EA4))) & mask
        v1 = (v1 + ((((v0 << 4) & mask) + 0xAD90777D) ^ ((v0 + total) & mask) ^ ((v0 >> 5) + 0x7E95761E))) & mask
    return v0, v1


def raises(error: type[Exception], message: str):
    """pytest.raises matching the whole message."""
    if error is KeyError:  # str(KeyError) quotes its argument
        return pytest.raises(error, match="^" + re.escape(repr(message)) + "$")
    return pytest.raises(error, match="^" + re.escape(message) + "$")


def close(a: torch.Tensor, b: torch.Tensor, tol: float = 2e-6) -> None:
    torch.testing.assert_close(a, b, rtol=tol, atol=tol)
