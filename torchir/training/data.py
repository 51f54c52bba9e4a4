"""ViewDataModule: the target images, one per sensor, served as batches of views."""
from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path
from typing import Optional, Union

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader, Dataset
from torch.utils.data.distributed import DistributedSampler

from .. import backend
from ..functions import render
from ..imageio import COLORSPACES, ENCODED_SUFFIXES, ColorSpace, is_lossy, read_image
from ..jpeg import chroma_sampling, quantization_tables

__all__ = ["ViewDataModule", "ViewDataset", "load_image"]

_ON_DEVICE = ("target", "quantisation")  # a batch's entries that meet the renders; the rest is host bookkeeping


def load_image(path: str | Path, colorspace: ColorSpace = "auto") -> torch.Tensor:
    """Read an image file as linear radiance ``(C, H, W)`` float32 (see :func:`torchir.imageio.read_image`)."""
    return read_image(path, colorspace)


def _resolve_saturation(saturation: Union[float, str, None], files: Optional[list[str]]) -> Optional[float]:
    """The radiance at which the targets clip: 1.0 for 8/16-bit files under ``"auto"``."""
    if saturation == "auto":
        encoded = files is not None and any(Path(f).suffix.lower() in ENCODED_SUFFIXES for f in files)
        return 1.0 if encoded else None
    if saturation is None:
        return None
    if isinstance(saturation, str) or not saturation > 0:
        raise ValueError(f"data.saturation must be 'auto', null or a number > 0, got {saturation!r}")
    return float(saturation)


class ViewDataset(Dataset):
    """Item ``i``: ``{"view": sensor index, "target": (C, H, W) image, "lossy": bool, "chroma":
    (h, v, srgb), "quantisation": (3, 8, 8)}``.

    ``lossy``: whether each target was read from a lossy file (JPEG), for
    :func:`torchir.imageio.clipped_mask` (default: none was). ``chroma``: the file's chroma
    subsampling and whether it stores sRGB values, for :func:`torchir.jpeg.subsample_chroma`
    (default ``(1, 1, 1)``: none). ``quantisation``: the file's JPEG quantisation tables for
    :func:`torchir.jpeg.jpeg_round_trip` (zeros, the default: not a JPEG)."""

    def __init__(self, views: list[int], targets: list[torch.Tensor], lossy: Optional[list[bool]] = None,
                 chroma: Optional[list[tuple[int, int, bool]]] = None,
                 quantisation: Optional[list[Optional[torch.Tensor]]] = None) -> None:
        self.views, self.targets = views, targets
        self.quantisation = [None] * len(views) if quantisation is None else list(quantisation)
        self.lossy = [False] * len(views) if lossy is None else list(lossy)
        self.chroma = [(1, 1, True)] * len(views) if chroma is None else list(chroma)
        if len(self.lossy) != len(views):
            raise ValueError(f"lossy has {len(self.lossy)} flag(s) for {len(views)} view(s)")
        if len(self.chroma) != len(views):
            raise ValueError(f"chroma has {len(self.chroma)} entr(ies) for {len(views)} view(s)")
        if len(self.quantisation) != len(views):
            raise ValueError(f"quantisation has {len(self.quantisation)} entr(ies) for {len(views)} view(s)")

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        target, tables = self.targets[i], self.quantisation[i]
        return {"view": torch.tensor(self.views[i], device="cpu"), "target": target,
                "lossy": torch.tensor(self.lossy[i], device="cpu"),
                "chroma": torch.tensor([int(c) for c in self.chroma[i]], device="cpu"),
                "quantisation": torch.zeros(3, 8, 8, device=target.device) if tables is None else tables.float().to(target.device)}


class ViewDataModule(pl.LightningDataModule):
    """Target views for :class:`~torchir.training.InverseRenderingModule`.

    Targets are either rendered from the model's scene at ``target_spp`` with the parameters'
    ground-truth values (``targets: null``: synthetic experiments, parameter error known), or
    read from image files, one per view (``targets: [a.exr, b.png, ...]``), as linear radiance
    by each file's own encoding (EXR/HDR linear; 8/16-bit PNG and JPEG sRGB; ``colorspace``
    overrides). A batch is a set of views; with several processes (DDP) each process renders
    its share of the batch.

    Args:
        targets: image files, one per entry of ``views``; ``None`` for synthetic targets.
            Relative paths are relative to the config file under ``torchir fit``.
        colorspace: ``auto`` (each file's own encoding), ``srgb`` or ``linear`` (see
            :func:`torchir.imageio.read_image`).
        saturation: radiance at which the targets clipped. A target pixel with any channel
            there (an over-exposed lamp in a photo) only bounds the radiance from below, so it
            is left out of the loss; in a JPEG target so are the bright pixels next to it that
            the codec smeared (:func:`torchir.imageio.clipped_mask`). ``auto``: 1.0 for 8/16-bit
            files, none for EXR and synthetic targets.
        views: sensor indices to fit (default: every sensor of the scene).
        views_per_step: views per optimiser step over all processes (default: all views).
        target_spp: samples per pixel of synthetic targets.
        target_seed: seed of synthetic targets (view ``v`` uses ``target_seed + v``).
    """

    def __init__(
        self,
        targets: Optional[list[str]] = None,
        views: Optional[list[int]] = None,
        views_per_step: Optional[int] = None,
        target_spp: int = 256,
        target_seed: int = 1_000_003,
        colorspace: ColorSpace = "auto",
        saturation: Union[float, str, None] = "auto",
    ) -> None:
        super().__init__()
        if views is not None and len(views) == 0:
            raise ValueError("data.views is empty: give at least one sensor index, or null for all sensors")
        if targets is not None and len(targets) == 0:
            raise ValueError("data.targets is empty: give one image per view, or null for synthetic targets")
        if target_spp < 1:
            raise ValueError(f"data.target_spp must be >= 1, got {target_spp}")
        self.target_files, self.requested_views = targets, views
        self.views_per_step, self.target_spp, self.target_seed = views_per_step, target_spp, target_seed
        self.synthetic = targets is None
        if colorspace not in COLORSPACES:
            raise ValueError(f"data.colorspace must be one of {COLORSPACES}, got {colorspace!r}")
        self.colorspace = colorspace
        self.saturation = _resolve_saturation(saturation, targets)
        self.views: list[int] = []
        self.targets: list[torch.Tensor] = []
        self.lossy: list[bool] = []  # per entry of views: its target file is lossy (JPEG)
        self.chroma: list[tuple[int, int, bool]] = []  # per entry of views: its file's chroma subsampling, sRGB values
        self.quantisation: list[Optional[torch.Tensor]] = []  # per entry of views: its JPEG's quantisation tables

    def setup(self, stage: str) -> None:
        if self.targets:
            return
        module = self.trainer.lightning_module
        scene = module.scene
        self.views = list(range(scene.sensor_count)) if self.requested_views is None else list(self.requested_views)
        for v in self.views:
            if not 0 <= v < scene.sensor_count:
                raise ValueError(f"data.views has sensor {v}, but the scene has {scene.sensor_count} sensor(s)")
        if self.synthetic:
            truth = module.ground_truth()
            with torch.no_grad():
                self.targets = [
                    render(scene, truth, spp=self.target_spp, seed=self.target_seed + v, sensor=v) for v in self.views
                ]
        else:
            if len(self.target_files) != len(self.views):
                raise ValueError(f"data.targets has {len(self.target_files)} file(s) for {len(self.views)} view(s) {self.views}")
            missing = [f for f in self.target_files if not Path(f).is_file()]
            if missing:
                raise FileNotFoundError(f"target image(s) not found: {', '.join(repr(m) for m in missing)}")
            strategy = getattr(self.trainer, "strategy", None)  # moved once here, not in every step's batch
            device = strategy.root_device if strategy is not None else torch.device(backend.device())
            self.targets = [self._read_target(path, v, scene).to(device) for v, path in zip(self.views, self.target_files)]
            self.lossy = [is_lossy(path) for path in self.target_files]
            srgb = self.colorspace != "linear"
            self.chroma = [(*chroma_sampling(path), srgb) if lossy else (1, 1, srgb) for path, lossy in zip(self.target_files, self.lossy)]
            tables = [quantization_tables(path) if lossy else None for path, lossy in zip(self.target_files, self.lossy)]
            self.quantisation = [None if t is None else t.to(device) for t in tables]

    def _read_target(self, path: str, view: int, scene) -> torch.Tensor:
        """One target file as ``(3, H, W)`` linear radiance, checked against sensor ``view``."""
        image = read_image(path, self.colorspace)
        if image.shape[0] != 3:
            raise ValueError(
                f"target {path!r} is greyscale (1 channel), but the scene renders RGB: save it as an RGB image"
            )
        h, w = scene.sensor_resolution(view)
        if tuple(image.shape[1:]) != (h, w):
            fix = (
                "set model.resolution"
                if scene.is_builtin
                else "set the film's width/height in the scene file (or pass them as model.scene_options if the file "
                "declares them with <default>)"
            )
            raise ValueError(
                f"target {path!r} is {image.shape[2]}x{image.shape[1]} (W x H), but sensor {view} renders {w}x{h}: "
                f"resize the image or {fix}"
            )
        if not bool(torch.isfinite(image).all()):
            raise ValueError(f"target {path!r} contains NaN/Inf pixels")
        return image

    def transfer_batch_to_device(self, batch: dict[str, torch.Tensor], device: torch.device, dataloader_idx: int) -> dict[str, torch.Tensor]:
        """The images to ``device`` (already there since :meth:`setup`: no copy a step); the views'
        indices and flags stay on the host, where the step reads them (no device-to-host sync)."""
        return {key: value.to(device) if key in _ON_DEVICE else value for key, value in batch.items()}

    def train_dataloader(self) -> DataLoader:
        world = self.trainer.world_size if self.trainer is not None else 1
        per_step = self.views_per_step or len(self.views)
        if per_step < 1 or per_step > len(self.views):
            raise ValueError(f"data.views_per_step must be in [1, {len(self.views)}], got {per_step}")
        if per_step % world:
            raise ValueError(f"data.views_per_step ({per_step}) must be divisible by the number of processes ({world})")
        dataset = ViewDataset(self.views, self.targets, self.lossy or None, self.chroma or None, self.quantisation or None)
        rank = self.trainer.global_rank if world > 1 else 0
        return _view_loader(dataset, per_step, world, rank)


class _ViewOrder(DistributedSampler):
    """This process's views in epoch order, in batches of ``batch_size``, from batch ``start`` on
    (set by a resume); ``served`` counts the batches of the current pass handed out.

    Each view stays with one process (its rank: position mod world). Lightning's own sampler
    reshuffles the training views over the processes every epoch, so a view's ReSTIR chain or
    carried-over store was split between processes (every process burnt in every view); with
    this one the processes' batches of a step together are the single process's batch. Being a
    ``DistributedSampler``, Lightning leaves it in place under DDP."""

    def __init__(self, dataset: ViewDataset, world: int, rank: int, batch_size: int) -> None:
        super().__init__(dataset, num_replicas=world, rank=rank, shuffle=False)
        self.batch_size, self.start, self.served = batch_size, 0, 0

    def __iter__(self) -> Iterator[int]:
        start, self.start = self.start, 0
        self.served = start
        # consecutive indices make a batch: skip whole batches, count a batch at its first index
        for k, index in enumerate(itertools.islice(super().__iter__(), start * self.batch_size, None)):
            if k % self.batch_size == 0:
                self.served += 1
            yield index


class _ResumableViewLoader(DataLoader):
    """A DataLoader that Lightning can resume mid-epoch (its ``_Stateful`` protocol: the fit loop
    saves :meth:`state_dict` in checkpoints and calls :meth:`load_state_dict` before the resumed
    epoch's first ``iter``). The state is the number of batches this epoch has served: resumed
    after batch ``k`` the epoch goes on with batch ``k + 1`` of the same order (a plain
    DataLoader restarts the epoch's order, and Lightning, counting the batches already done,
    ends that epoch early). Every process serves its batches in lockstep, so the state that
    process 0 checkpoints is every process's. The counting lives in the sampler: an ``__iter__``
    here would put torchir's frame under the DataLoader's own host tensors (its base seed)."""

    def state_dict(self) -> dict[str, int]:
        return {"batches_served": self.sampler.served}

    def load_state_dict(self, state: dict[str, int]) -> None:
        served = int(state["batches_served"])
        self.sampler.start = served if served < len(self) else 0  # an epoch that was over: the next starts whole


def _view_loader(dataset: ViewDataset, per_step: int, world: int, rank: int) -> _ResumableViewLoader:
    """Process ``rank``'s loader: ``per_step // world`` of its views a batch, in a fixed order."""
    return _ResumableViewLoader(dataset, batch_size=per_step // world, shuffle=False,
                                sampler=_ViewOrder(dataset, world, rank, per_step // world), num_workers=0)
