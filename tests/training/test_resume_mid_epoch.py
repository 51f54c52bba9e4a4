"""A run resumed from a checkpoint taken in the middle of an epoch (``data.views_per_step`` below
the number of views) continues with the next batch of that epoch's view order, and the
following epochs are those of the uninterrupted run."""
from __future__ import annotations

import warnings
from pathlib import Path
from types import SimpleNamespace

import torch
from torch.utils.data import DataLoader

from torchir import cli
from torchir.training import ViewDataModule

from tests.helpers import ROOT, _latents, _run_dir

MULTIVIEW = str(ROOT / "configs" / "multiview.yaml")


def _fit(tmp_path: Path, *overrides: str) -> int:
    # 3 views, one per step (3 steps an epoch), every step checkpointed, 8² pixels, a 4² texture
    return cli.main(
        ["fit", "--config", MULTIVIEW, "--model.resolution", "8", "--model.scene_options", "{views: 3, texture: 4}",
         "--model.spp", "1", "--data.views_per_step", "1", "--trainer.max_steps", "7",
         "--checkpoint.every_n_train_steps", "1", "--trainer.enable_progress_bar", "false",
         "--trainer.enable_model_summary", "false", "--trainer.logger.init_args.save_dir", str(tmp_path), *overrides]
    )


def test_resume_mid_epoch_reproduces_the_uninterrupted_run(tmp_path):
    """Resuming after step 2 of a 3-step epoch (views 0, 1 done) renders view 2 next, then the
    epochs 0 1 2, 0 of the uninterrupted run: the final latent matches it to rtol 1e-5 (float32
    atomics, see test_training). A loader that restarts the epoch renders view 0 instead (and
    then a one-batch epoch), which lands far outside the bound."""
    assert _fit(tmp_path / "a") == 0
    folder = _run_dir(tmp_path / "a", name="multiview") / "checkpoints"
    middle = folder / "epoch=0-step=2.ckpt"
    assert middle.is_file(), sorted(p.name for p in folder.iterdir())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _fit(tmp_path / "b", "--ckpt_path", str(middle)) == 0
    uninterrupted = _latents(folder / "last.ckpt")
    resumed = _latents(_run_dir(tmp_path / "b", name="multiview") / "checkpoints" / "last.ckpt")
    assert uninterrupted.keys() == resumed.keys() and uninterrupted
    for key in uninterrupted:
        torch.testing.assert_close(resumed[key], uninterrupted[key], rtol=1e-5, atol=1e-6)
        assert not torch.equal(_latents(middle)[key], uninterrupted[key])  # it really resumed mid-way
    assert not [w for w in caught if "not resumable" in str(w.message)]  # Lightning sees a resumable loader


def _order(loader: DataLoader, batches: int | None = None) -> list[list[int]]:
    """The views of the loader's next ``batches`` batches (one pass when ``None``)."""
    out: list[list[int]] = []
    if batches == 0:
        return out
    for batch in loader:
        out.append(batch["view"].tolist())
        if batches is not None and len(out) == batches:
            break
    return out


def _loaders(views: int, per_step: int, world: int) -> list[DataLoader]:
    """Each process's training loader, as ViewDataModule builds it under ``world`` processes."""
    loaders = []
    for rank in range(world):
        data = ViewDataModule(views_per_step=per_step)
        data.views, data.targets = list(range(views)), [torch.zeros(3, 1, 1)] * views
        data.trainer = SimpleNamespace(world_size=world, global_rank=rank)
        loaders.append(data.train_dataloader())
    return loaders


def test_loader_state_resumes_each_process_at_the_next_batch_of_its_own_share():
    """Under DDP every process loads process 0's checkpointed loader state: each then serves
    the rest of its own share of the epoch (the views it renders in the uninterrupted run), and
    the next epoch whole; a state taken when the epoch was over starts the next epoch whole
    (no empty epoch)."""
    for views, per_step, world in [(4, 2, 1), (3, 1, 1), (3, 2, 1), (8, 4, 2), (6, 2, 2)]:
        fresh = _loaders(views, per_step, world)
        epochs = [_order(loader) for loader in fresh]  # the uninterrupted order of each process
        assert sorted(v for rank in epochs for batch in rank for v in batch) == list(range(views))
        steps = len(epochs[0])
        for done in range(steps + 1):
            running = _loaders(views, per_step, world)
            for rank, loader in enumerate(running):
                assert _order(loader, done) == epochs[rank][:done]
            state = running[0].state_dict()  # Lightning checkpoints process 0's state
            for rank, loader in enumerate(_loaders(views, per_step, world)):
                loader.load_state_dict(state)
                rest = epochs[rank][done:] if done < steps else epochs[rank]
                assert _order(loader) == rest, (views, per_step, world, done, rank)
                assert _order(loader) == epochs[rank]  # the following epoch: the uninterrupted one
