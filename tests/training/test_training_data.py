"""Fast, exact tests of :mod:`torchir.training.data` (ViewDataModule), written for the mutation
audit: a stand-in trainer / module / scene (namespaces with the attributes data.py reads) and a
torch stand-in for ``render``; target files are tiny ``.npy`` payloads under image names, read
by a stand-in for ``read_image`` (imageio has its own tests; a Mitsuba call in a mutmut child
forked from a process that already ran Mitsuba hangs, so none is made here). No Lightning
``Trainer`` runs here.
"""
from __future__ import annotations

import re
from types import SimpleNamespace

import torchir  # noqa: F401  (before torch: sets the OpenMP policy)

import pytest
import torch

import torchir.training.data as data
import numpy as np
from torchir.training.data import ViewDataModule, ViewDataset, _resolve_saturation, load_image


class FakeScene:
    def __init__(self, sensors=2, resolution=(2, 3), builtin=True) -> None:
        self.sensor_count = sensors
        self.resolution = resolution  # (H, W)
        self.is_builtin = builtin
        self.asked: list[int] = []

    def sensor_resolution(self, view):
        self.asked.append(view)
        return self.resolution


def attach(dm: ViewDataModule, scene: FakeScene, truth=None, world=1) -> SimpleNamespace:
    module = SimpleNamespace(scene=scene, ground_truth=lambda: truth if truth is not None else {"k": torch.tensor(0.5)})
    trainer = SimpleNamespace(lightning_module=module, world_size=world)
    dm.trainer = trainer
    return trainer


def write_image(path, tensor):
    """A stand-in image file: the tensor's values as ``.npy`` bytes under an image name."""
    with open(path, "wb") as f:
        np.save(f, tensor.cpu().numpy())
    return path


@pytest.fixture(autouse=True)
def reads(monkeypatch):
    calls = []

    def read_image(path, colorspace):
        calls.append((str(path), colorspace))
        return torch.from_numpy(np.load(path))

    monkeypatch.setattr(data, "read_image", read_image)
    return calls


def image(h=2, w=3, value=0.25, channels=3) -> torch.Tensor:
    return torch.full((channels, h, w), value)


# ---------------------------------------------------------------- saturation


@pytest.mark.parametrize(
    "files, expected",
    [
        (None, None),
        (["a.exr"], None),
        (["a.exr", "b.hdr"], None),
        (["a.png"], 1.0),
        (["a.exr", "b.PNG"], 1.0),
        (["x/a.JPG"], 1.0),
        (["a.jpeg"], 1.0),
    ],
)
def test_resolve_saturation_auto(files, expected):
    result = _resolve_saturation("auto", files)
    assert result == expected
    if expected is not None:
        assert type(result) is float


def test_resolve_saturation_values():
    assert _resolve_saturation(None, ["a.png"]) is None
    value = _resolve_saturation(2, None)
    assert value == 2.0 and type(value) is float
    assert _resolve_saturation(0.5, ["a.png"]) == 0.5
    assert _resolve_saturation(1e-9, None) == 1e-9


@pytest.mark.parametrize("bad", [0, 0.0, -1.0, "high", float("nan")])
def test_resolve_saturation_rejects(bad):
    msg = f"data.saturation must be 'auto', null or a number > 0, got {bad!r}"
    with pytest.raises(ValueError, match="^" + re.escape(msg) + "$"):
        _resolve_saturation(bad, None)


# ---------------------------------------------------------------- constructor


def test_constructor_defaults():
    dm = ViewDataModule()
    assert dm.target_files is None and dm.requested_views is None
    assert dm.views_per_step is None and dm.target_spp == 256 and dm.target_seed == 1_000_003
    assert dm.synthetic is True and dm.colorspace == "auto" and dm.saturation is None
    assert dm.views == [] and dm.targets == []


def test_constructor_files():
    dm = ViewDataModule(targets=["a.png"], views=[1], views_per_step=1, target_spp=1, target_seed=7, colorspace="linear")
    assert dm.target_files == ["a.png"] and dm.requested_views == [1]
    assert dm.views_per_step == 1 and dm.target_spp == 1 and dm.target_seed == 7
    assert dm.synthetic is False and dm.colorspace == "linear" and dm.saturation == 1.0
    assert ViewDataModule(targets=["a.exr"]).saturation is None
    assert ViewDataModule(targets=["a.png"], saturation=None).saturation is None
    assert ViewDataModule(targets=["a.png"], saturation=3).saturation == 3.0


def test_constructor_errors():
    with pytest.raises(ValueError, match=r"^data\.views is empty: give at least one sensor index, or null for all sensors$"):
        ViewDataModule(views=[])
    with pytest.raises(ValueError, match=r"^data\.targets is empty: give one image per view, or null for synthetic targets$"):
        ViewDataModule(targets=[])
    with pytest.raises(ValueError, match=r"^data\.target_spp must be >= 1, got 0$"):
        ViewDataModule(target_spp=0)
    msg = "data.colorspace must be one of ('auto', 'srgb', 'linear'), got 'rgb'"
    with pytest.raises(ValueError, match="^" + re.escape(msg) + "$"):
        ViewDataModule(colorspace="rgb")
    with pytest.raises(ValueError, match=r"^data\.saturation must be"):
        ViewDataModule(saturation=-2.0)
    for cs in ("auto", "srgb", "linear"):
        assert ViewDataModule(colorspace=cs).colorspace == cs


# ---------------------------------------------------------------- dataset


def test_view_dataset():
    targets = [image(value=1.0), image(value=2.0)]
    ds = ViewDataset([3, 5], targets)
    assert len(ds) == 2
    item = ds[1]
    assert set(item) == {"view", "target", "lossy", "chroma", "quantisation"}
    assert item["chroma"].tolist() == [1, 1, 1]  # no chroma subsampling, sRGB values
    assert item["quantisation"].shape == (3, 8, 8) and not bool(item["quantisation"].any())  # not a JPEG
    tables = torch.arange(192.0).reshape(3, 8, 8)
    assert torch.equal(ViewDataset([3, 5], targets, quantisation=[None, tables])[1]["quantisation"], tables)
    with pytest.raises(ValueError, match="quantisation has 1"):
        ViewDataset([3, 5], targets, quantisation=[None])
    assert item["view"].dtype == torch.int64 and int(item["view"]) == 5 and item["view"].dim() == 0
    assert item["target"] is targets[1]
    assert item["lossy"].dtype == torch.bool and item["lossy"].dim() == 0 and not bool(item["lossy"])
    flagged = ViewDataset([3, 5], targets, lossy=[True, False])
    assert bool(flagged[0]["lossy"]) and not bool(flagged[1]["lossy"])
    with pytest.raises(ValueError, match=r"^lossy has 1 flag\(s\) for 2 view\(s\)$"):
        ViewDataset([3, 5], targets, lossy=[True])
    subsampled = ViewDataset([3, 5], targets, lossy=[True, False], chroma=[(2, 2, True), (1, 1, True)])
    assert subsampled[0]["chroma"].tolist() == [2, 2, 1] and subsampled[1]["chroma"].tolist() == [1, 1, 1]
    with pytest.raises(ValueError, match=r"^chroma has 1 entr\(ies\) for 2 view\(s\)$"):
        ViewDataset([3, 5], targets, chroma=[(2, 2, True)])


def test_load_image(tmp_path, reads):
    path = write_image(tmp_path / "a.exr", image(value=0.75))
    loaded = load_image(path)
    assert torch.equal(loaded, torch.full((3, 2, 3), 0.75, device="cpu"))  # read_image gives host tensors
    load_image(path, "linear")
    assert reads == [(str(path), "auto"), (str(path), "linear")]


# ---------------------------------------------------------------- setup, synthetic


@pytest.fixture()
def fake_render(monkeypatch):
    calls = []

    def render(scene, values, spp, seed, sensor):
        calls.append({"scene": scene, "values": values, "spp": spp, "seed": seed, "sensor": sensor,
                      "grad": torch.is_grad_enabled()})
        return torch.full((3, *scene.resolution), float(sensor))

    monkeypatch.setattr(data, "render", render)
    return calls


def test_setup_synthetic_all_views(fake_render):
    scene = FakeScene(sensors=3)
    truth = {"k": torch.tensor(0.9)}
    dm = ViewDataModule(target_spp=5, target_seed=100)
    attach(dm, scene, truth)
    dm.setup("fit")
    assert dm.views == [0, 1, 2]
    assert [c["sensor"] for c in fake_render] == [0, 1, 2]
    assert [c["seed"] for c in fake_render] == [100, 101, 102]
    assert all(c["spp"] == 5 and c["scene"] is scene and c["values"] is truth for c in fake_render)
    assert not any(c["grad"] for c in fake_render)
    assert [float(t[0, 0, 0]) for t in dm.targets] == [0.0, 1.0, 2.0]
    # a second setup keeps the targets (no re-render)
    dm.setup("fit")
    assert len(fake_render) == 3


def test_setup_synthetic_requested_views(fake_render):
    scene = FakeScene(sensors=3)
    requested = (2, 0)
    dm = ViewDataModule(views=requested, target_seed=10)
    attach(dm, scene)
    dm.setup("fit")
    assert dm.views == [2, 0] and type(dm.views) is list
    assert [c["seed"] for c in fake_render] == [12, 10]


@pytest.mark.parametrize("view", [-1, 2, 5])
def test_setup_view_out_of_range(fake_render, view):
    dm = ViewDataModule(views=[0, view])
    attach(dm, FakeScene(sensors=2))
    with pytest.raises(ValueError, match=rf"^data\.views has sensor {view}, but the scene has 2 sensor\(s\)$"):
        dm.setup("fit")


def test_setup_last_view_in_range(fake_render):
    dm = ViewDataModule(views=[1, 0])
    attach(dm, FakeScene(sensors=2))
    dm.setup("fit")
    assert dm.views == [1, 0]


# ---------------------------------------------------------------- setup, files


def test_setup_files(tmp_path, fake_render):
    a = write_image(tmp_path / "a.exr", image(value=0.5))
    b = write_image(tmp_path / "b.exr", image(value=2.0))
    scene = FakeScene(sensors=3)
    dm = ViewDataModule(targets=[str(a), str(b)], views=[2, 0])
    attach(dm, scene)
    dm.setup("fit")
    assert fake_render == []
    assert dm.views == [2, 0]
    assert scene.asked == [2, 0]
    assert len(dm.targets) == 2
    assert torch.allclose(dm.targets[0], torch.full((3, 2, 3), 0.5))
    assert torch.allclose(dm.targets[1], torch.full((3, 2, 3), 2.0))


def test_setup_pairs_files_with_views_in_the_listed_order(tmp_path, fake_render):
    """``targets[i]`` is the target of ``views[i]``, whatever the files' names: names that sort the
    other way from the list (as a photographer's ``front``/``back`` do) keep their listed views,
    and so does a view order that is not sorted."""
    front = write_image(tmp_path / "z_front.exr", image(value=0.25))
    back = write_image(tmp_path / "a_back.exr", image(value=4.0))
    side = write_image(tmp_path / "m_side.exr", image(value=1.0))
    dm = ViewDataModule(targets=[str(front), str(back), str(side)], views=[0, 2, 1])
    attach(dm, FakeScene(sensors=3))
    dm.setup("fit")
    assert [float(t.mean()) for t in dm.targets] == [0.25, 4.0, 1.0]
    items = ViewDataset(dm.views, dm.targets)
    assert [(int(items[i]["view"]), float(items[i]["target"].mean())) for i in range(3)] == [(0, 0.25), (2, 4.0), (1, 1.0)]


def test_setup_files_lossy_flags_reach_the_batch(tmp_path, fake_render):
    """Each view's batch item says whether its file is a JPEG (the trainer's clipped-pixel
    mask grows for those); synthetic targets are not lossy."""
    files = [write_image(tmp_path / name, image(value=0.5)) for name in ("a.jpg", "b.png", "c.JPEG")]
    dm = ViewDataModule(targets=[str(f) for f in files], views=[2, 0, 1])
    attach(dm, FakeScene(sensors=3))
    dm.setup("fit")
    assert dm.lossy == [True, False, True]
    batch = next(iter(dm.train_dataloader()))
    assert batch["view"].tolist() == [2, 0, 1] and batch["lossy"].tolist() == [True, False, True]
    synthetic = ViewDataModule()
    attach(synthetic, FakeScene(sensors=2))
    synthetic.setup("fit")
    assert synthetic.lossy == [] and next(iter(synthetic.train_dataloader()))["lossy"].tolist() == [False, False]


def test_setup_files_colorspace(tmp_path, reads):
    a = write_image(tmp_path / "a.png", image(value=0.5))
    dm = ViewDataModule(targets=[str(a)], views=[0], colorspace="linear")
    attach(dm, FakeScene(sensors=1))
    dm.setup("fit")
    assert reads == [(str(a), "linear")]
    dm = ViewDataModule(targets=[str(a)], views=[0])
    attach(dm, FakeScene(sensors=1))
    dm.setup("fit")
    assert reads[-1] == (str(a), "auto")


def test_setup_files_count_mismatch(tmp_path):
    a = write_image(tmp_path / "a.exr", image())
    dm = ViewDataModule(targets=[str(a)])
    attach(dm, FakeScene(sensors=2))
    with pytest.raises(ValueError, match=r"^data\.targets has 1 file\(s\) for 2 view\(s\) \[0, 1\]$"):
        dm.setup("fit")


def test_setup_files_missing(tmp_path):
    a = write_image(tmp_path / "a.exr", image())
    m1, m2 = str(tmp_path / "m1.exr"), str(tmp_path / "m2.png")
    dm = ViewDataModule(targets=[m1, str(a), m2])
    attach(dm, FakeScene(sensors=3))
    msg = f"target image(s) not found: {m1!r}, {m2!r}"
    with pytest.raises(FileNotFoundError, match="^" + re.escape(msg) + "$"):
        dm.setup("fit")
    # a directory is not a file
    dm = ViewDataModule(targets=[str(tmp_path)])
    attach(dm, FakeScene(sensors=1))
    with pytest.raises(FileNotFoundError, match=re.escape(f"not found: {str(tmp_path)!r}") + "$"):
        dm.setup("fit")


def test_read_target_greyscale(tmp_path):
    grey = write_image(tmp_path / "g.exr", image(channels=1))
    dm = ViewDataModule(targets=[str(grey)])
    attach(dm, FakeScene(sensors=1))
    msg = f"target {str(grey)!r} is greyscale (1 channel), but the scene renders RGB: save it as an RGB image"
    with pytest.raises(ValueError, match="^" + re.escape(msg) + "$"):
        dm.setup("fit")


@pytest.mark.parametrize("builtin", [True, False])
def test_read_target_wrong_size(tmp_path, builtin):
    path = str(write_image(tmp_path / "a.exr", image(h=4, w=5)))
    scene = FakeScene(sensors=2, resolution=(2, 3), builtin=builtin)
    dm = ViewDataModule(targets=[path], views=[1])
    attach(dm, scene)
    fix = (
        "set model.resolution" if builtin
        else "set the film's width/height in the scene file (or pass them as model.scene_options if the file "
        "declares them with <default>)"
    )
    msg = f"target {path!r} is 5x4 (W x H), but sensor 1 renders 3x2: resize the image or {fix}"
    with pytest.raises(ValueError, match="^" + re.escape(msg) + "$"):
        dm.setup("fit")


def test_read_target_transposed_size(tmp_path):
    path = str(write_image(tmp_path / "a.exr", image(h=3, w=2)))
    dm = ViewDataModule(targets=[path])
    attach(dm, FakeScene(sensors=1, resolution=(2, 3)))
    with pytest.raises(ValueError, match=re.escape(f"target {path!r} is 2x3 (W x H), but sensor 0 renders 3x2")):
        dm.setup("fit")


@pytest.mark.parametrize("bad_value", [float("inf"), float("nan")])
def test_read_target_nonfinite(tmp_path, bad_value):
    bad = image()
    bad[1, 0, 2] = bad_value
    path = str(write_image(tmp_path / "a.exr", bad))
    dm = ViewDataModule(targets=[path])
    attach(dm, FakeScene(sensors=1))
    with pytest.raises(ValueError, match="^" + re.escape(f"target {path!r} contains NaN/Inf pixels") + "$"):
        dm.setup("fit")


# ---------------------------------------------------------------- dataloader


def loader_for(views, per_step=None, world=1, trainer=True, rank=0):
    dm = ViewDataModule(views_per_step=per_step)
    dm.views = list(views)
    dm.targets = [image(value=float(v)) for v in views]
    if trainer:
        dm.trainer = SimpleNamespace(world_size=world, global_rank=rank)
    return dm


def test_train_dataloader_default_all_views():
    dm = loader_for([0, 1, 2])
    loader = dm.train_dataloader()
    assert loader.batch_size == 3 and loader.num_workers == 0
    batches = list(loader)
    assert len(batches) == 1
    assert batches[0]["view"].tolist() == [0, 1, 2]
    assert batches[0]["target"].shape == (3, 3, 2, 3)


def test_train_dataloader_in_order_and_per_process():
    """Under DDP a view stays with one process (position mod world), epoch after epoch, and the
    processes' batches of a step together are the single process's batch of that step."""
    single = [b["view"].tolist() for b in loader_for([4, 1, 3, 0], per_step=2).train_dataloader()]
    assert single == [[4, 1], [3, 0]]  # in order, not shuffled
    for per_step, want in ((4, ([[4, 3]], [[1, 0]])), (2, ([[4], [3]], [[1], [0]]))):
        for rank in (0, 1):
            loader = loader_for([4, 1, 3, 0], per_step=per_step, world=2, rank=rank).train_dataloader()
            assert loader.batch_size == per_step // 2
            assert [b["view"].tolist() for b in loader] == want[rank]
            assert [b["view"].tolist() for b in loader] == want[rank]  # the next epoch: the same views
    per_process = zip(*([b["view"].tolist() for b in loader_for([4, 1, 3, 0], per_step=2, world=2, rank=r).train_dataloader()]
                        for r in (0, 1)))
    assert [sorted(a + b) for a, b in per_process] == [sorted(s) for s in single]


def test_train_dataloader_no_trainer():
    dm = loader_for([0, 1], per_step=1, trainer=False)
    dm.trainer = None
    assert dm.train_dataloader().batch_size == 1


@pytest.mark.parametrize("per_step", [-1, 4])
def test_train_dataloader_per_step_range(per_step):
    dm = loader_for([0, 1, 2], per_step=per_step)
    with pytest.raises(ValueError, match=rf"^data\.views_per_step must be in \[1, 3\], got {per_step}$"):
        dm.train_dataloader()


def test_train_dataloader_per_step_bounds_ok():
    assert loader_for([0, 1, 2], per_step=1).train_dataloader().batch_size == 1
    assert loader_for([0, 1, 2], per_step=3).train_dataloader().batch_size == 3
    assert loader_for([0, 1, 2], per_step=0).train_dataloader().batch_size == 3  # 0: all views


def test_train_dataloader_world_divides():
    dm = loader_for([0, 1, 2], per_step=3, world=2)
    with pytest.raises(ValueError, match=r"^data\.views_per_step \(3\) must be divisible by the number of processes \(2\)$"):
        dm.train_dataloader()
    assert loader_for([0, 1, 2, 3, 4, 5], per_step=6, world=3).train_dataloader().batch_size == 2
