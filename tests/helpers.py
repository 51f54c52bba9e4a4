"""Small modules the training tests refer to by class path, and shared test checks."""
from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import torch
from torch import nn


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
    In a fresh process only the test's own scenes exist."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout
