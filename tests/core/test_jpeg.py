"""JPEG photo targets: the codec's chroma subsampling read from the file, emulated, and corrected
for in a fit (``torchir.jpeg``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import torchir
from torchir.imageio import read_image, to_srgb, write_image
from torchir.jpeg import CodecCorrection, chroma_sampling, jpeg_round_trip, quantization_tables, subsample_chroma

from tests.helpers import DEVICE, file_target_step


def _srgb_bytes(image: torch.Tensor) -> np.ndarray:
    return np.rint(255 * to_srgb(image).permute(1, 2, 0).double().cpu().numpy()).astype(np.uint8)


def _write_jpeg_with_mitsuba(path: Path, image: torch.Tensor, quality: int) -> Path:
    import mitsuba as mi

    bitmap = mi.Bitmap(np.ascontiguousarray(_srgb_bytes(image)), mi.Bitmap.PixelFormat.RGB)
    bitmap.set_srgb_gamma(True)
    bitmap.write(str(path), quality=quality)
    return path


@pytest.fixture(scope="module")
def room() -> torch.Tensor:
    """A 48² Cornell box, lamp clipped below the top code (colour edges at the walls)."""
    scene = torchir.Scene.builtin("cbox", resolution=48)
    return torchir.functions.render(scene, {}, spp=64, seed=1).clamp(0, 0.99)


def test_chroma_sampling_reads_the_frame_header(tmp_path, room):
    rgb = Image.fromarray(_srgb_bytes(room))
    for subsampling, expected in ((0, (1, 1)), (1, (2, 1)), (2, (2, 2))):  # PIL: 4:4:4, 4:2:2, 4:2:0
        rgb.save(tmp_path / f"pil{subsampling}.jpg", quality=90, subsampling=subsampling)
        assert chroma_sampling(tmp_path / f"pil{subsampling}.jpg") == expected
    assert chroma_sampling(_write_jpeg_with_mitsuba(tmp_path / "mitsuba.jpg", room, 90)) == (2, 2)
    rgb.convert("L").save(tmp_path / "grey.jpg")
    write_image(tmp_path / "photo.png", room)
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "pil2.jpg").read_bytes()[:40])
    for name in ("grey.jpg", "photo.png", "cut.jpg"):
        assert chroma_sampling(tmp_path / name) == (1, 1), name


@pytest.mark.parametrize("quality", [90, 95])
def test_the_filter_is_what_the_codec_did(tmp_path, room, quality):
    """The decoded JPEG is closer to the filtered image than to the image itself (the rest is the
    DCT's quantisation; measured rms 0.0106 -> 0.0060 at q90, 0.0093 -> 0.0042 at q95)."""
    decoded = read_image(_write_jpeg_with_mitsuba(tmp_path / "photo.jpg", room, quality)).to(DEVICE)
    rms = lambda a: float((decoded - a).square().mean().sqrt())  # noqa: E731
    assert rms(subsample_chroma(room, (2, 2))) < 0.7 * rms(room)
    assert torch.equal(subsample_chroma(room, (1, 1)), room)


# libjpeg's tables at quality 50 are the JPEG standard's (ITU T.81 Annex K), in natural order: rows 0 and 1
ANNEX_K_LUMA = ([16, 11, 10, 16, 24, 40, 51, 61], [12, 12, 14, 19, 26, 58, 60, 55])
ANNEX_K_CHROMA = ([17, 18, 24, 47, 99, 99, 99, 99], [18, 21, 26, 66, 99, 99, 99, 99])


def test_quantisation_tables_are_read_in_natural_order(tmp_path, room):
    rgb = Image.fromarray(_srgb_bytes(room))
    rgb.save(tmp_path / "q50.jpg", quality=50, subsampling=2)
    tables = quantization_tables(tmp_path / "q50.jpg")
    assert tables.shape == (3, 8, 8)
    assert tables[0, :2].tolist() == [list(map(float, r)) for r in ANNEX_K_LUMA]
    for k in (1, 2):
        assert tables[k, :2].tolist() == [list(map(float, r)) for r in ANNEX_K_CHROMA]
    rgb.convert("L").save(tmp_path / "grey.jpg")
    write_image(tmp_path / "photo.png", room)
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "q50.jpg").read_bytes()[:100])
    for name in ("grey.jpg", "photo.png", "cut.jpg"):
        assert quantization_tables(tmp_path / name) is None, name


@pytest.mark.parametrize("writer, quality", [("mitsuba", 75), ("mitsuba", 90), ("pil444", 75), ("pil422", 60)])
def test_the_round_trip_is_what_the_codec_did(tmp_path, room, writer, quality):
    """Re-encoding with the file's own tables and subsampling gives back the decoded file exactly
    (the image itself is 4.5-6 codes off on average)."""
    if writer == "mitsuba":
        path = _write_jpeg_with_mitsuba(tmp_path / "photo.jpg", room, quality)
    else:
        path = tmp_path / "photo.jpg"
        Image.fromarray(_srgb_bytes(room)).save(path, quality=quality, subsampling={"pil444": 0, "pil422": 1}[writer])
    decoded = read_image(path).to(DEVICE)
    codes = lambda a: torch.round(255 * to_srgb(a.clamp(0, 1)))  # noqa: E731
    emulated = jpeg_round_trip(room, quantization_tables(path), chroma_sampling(path))
    assert torch.equal(codes(emulated), codes(decoded))
    assert float((codes(room) - codes(decoded)).abs().mean()) > 3.0  # the codec did change the photo
    assert emulated.dtype == room.dtype and jpeg_round_trip(room[None], quantization_tables(path), (2, 2)).shape == (1, *room.shape)
    bright = room.clone()
    bright[:, :4, :4] = 7.0
    assert torch.equal(jpeg_round_trip(bright, quantization_tables(path), (2, 2))[:, :4, :4], bright[:, :4, :4])  # HDR kept
    with pytest.raises(ValueError, match="tables"):
        jpeg_round_trip(room, torch.ones(2, 8, 8))
    with pytest.raises(ValueError, match="subsampling"):
        jpeg_round_trip(room, quantization_tables(path), (4, 1))


def test_separate_chroma_tables_are_kept(tmp_path, room):
    """A file whose Cr table differs from its Cb table (three tables) is re-encoded with all three."""
    luma, cb, cr = ([int(3 + (k % 8) + offset) for k in range(64)] for offset in (0, 10, 20))
    path = tmp_path / "three.jpg"
    Image.fromarray(_srgb_bytes(room)).save(path, qtables=[luma, cb, cr], subsampling=2)
    tables = quantization_tables(path)
    assert not torch.equal(tables[1], tables[2])
    codes = lambda a: torch.round(255 * to_srgb(a.clamp(0, 1)))  # noqa: E731
    assert torch.equal(codes(jpeg_round_trip(room, tables, (2, 2))), codes(read_image(path).to(DEVICE)))


def test_filter_gradcheck_and_shapes():
    x = (torch.rand(2, 3, 5, 7, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: subsample_chroma(t, (2, 2)), (x,))
    assert torch.autograd.gradcheck(lambda t: subsample_chroma(t, (2, 1), srgb=False), (x,))
    assert subsample_chroma(x[0], (2, 2)).shape == (3, 5, 7)
    with pytest.raises(ValueError, match="RGB image"):
        subsample_chroma(torch.zeros(1, 4, 4), (2, 2))


def test_correction_is_linear_in_the_render_and_uses_the_running_mean():
    torch.manual_seed(0)
    clean = torch.rand(3, 8, 8, dtype=torch.float64) * 0.8 + 0.1
    correct = CodecCorrection(window=64)
    for _ in range(200):  # noisy renders: the correction comes from their mean, not from one of them
        out = correct(clean + 0.2 * torch.randn_like(clean), view=3, factors=(2, 2))
    mean = correct.means[3][0]
    torch.testing.assert_close(mean, clean, atol=0.1, rtol=0)
    render = (clean + 0.2 * torch.randn_like(clean)).requires_grad_()
    out = correct(render, view=3, factors=(2, 2))
    grad, = torch.autograd.grad((out * torch.arange(out.numel()).reshape(out.shape)).sum(), render)
    torch.testing.assert_close(grad, torch.arange(out.numel(), dtype=grad.dtype).reshape(out.shape))  # d out / d render = I
    assert correct(render, view=4, factors=(1, 1)) is render
    with pytest.raises(ValueError, match="window"):
        CodecCorrection(window=0)


def _fit_lamp(module, target: Path, steps: int = 200) -> torch.Tensor:
    """Adam on the lamp's radiance through the trainer's step, averaged over the second half."""
    _, step = file_target_step(module, target)
    truth = module.scene.get("light.emitter.radiance.value")
    latent = module.scene_parameters[0].latent
    latent.data.copy_(truth * 0.9)
    module._codec_correction = None
    optimiser = torch.optim.Adam([latent], lr=0.1)
    trail = []
    for i in range(steps):
        optimiser.zero_grad()
        step(i).backward()
        optimiser.step()
        if i >= steps // 2:
            trail.append(latent.detach().clone())
    return torch.stack(trail).mean(0)


def test_a_jpeg_target_gives_the_pngs_colour(tmp_path, monkeypatch):
    """The lamp's colour fitted through the trainer (32², 8 spp, same seeds) from a PNG and from a
    4:2:0 JPEG (q95) of the same photo. Without the correction the JPEG's blue came out 3.7 % and
    its red 2.5 % off the PNG's; with it every channel is within 1.5 % (the PNG's own answer is
    0.7 % off the truth at these seeds: the bound is twice the fit's own noise)."""
    from torchir.training import InverseRenderingModule

    module = InverseRenderingModule(scene="cbox", resolution=32, spp=8, loss="l2",
                                    parameters={"light.emitter.radiance.value": {"init": 1.0, "transform": "none"}})
    photo = torchir.functions.render(module.scene, {}, spp=64, seed=2)
    write_image(tmp_path / "photo.png", photo)
    jpeg = _write_jpeg_with_mitsuba(tmp_path / "photo.jpg", photo, 95)
    png = _fit_lamp(module, tmp_path / "photo.png")
    corrected = (_fit_lamp(module, jpeg) - png) / png
    monkeypatch.setattr(CodecCorrection, "__call__", lambda self, image, view, factors, srgb=True, tables=None: image)
    uncorrected = (_fit_lamp(module, jpeg) - png) / png
    assert float(corrected.abs().max()) < 0.015, corrected
    assert float(uncorrected.abs().max()) > 0.015, uncorrected  # the codec's shift is there to correct


def test_the_jpeg_benchmark_reports_offsets_in_seed_noise():
    """``torchir bench jpeg``'s table from known answers: the paired offset in percent and the
    offset of the means in the PNG's seed standard deviations."""
    from torchir.bench.jpeg import offsets, table

    answers = {"png": [[10.0, 5.0, 2.0], [10.2, 5.0, 2.2]], "q75 codec": [[10.1, 5.5, 2.0], [10.3, 5.5, 2.2]]}
    row = offsets(answers)["q75 codec"]
    sd = torch.tensor([10.0, 10.2]).std().item()
    assert row["percent"][1] == pytest.approx(10.0) and row["percent"][2] == pytest.approx(0.0, abs=1e-9)
    assert row["in_seed_sd"][0] == pytest.approx(0.1 / sd)
    text = table({"answers": answers})
    assert "| q75 | codec | +0.99 %, +10.00 %, +0.00 % |" in text
