"""Image files <-> linear radiance: every format reads back like the EXR of the same image, once
decoded (a PNG used to be sRGB-decoded twice: 0.508 read back as 0.222)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchir
from torchir.training import load_image  # how targets are read (it existed before read_image)

from tests.helpers import DEVICE

# Largest slope of the sRGB decoding curve, d(linear)/d(encoded), reached at encoded = 1:
# (2.4 / 1.055) * ((1 + 0.055) / 1.055) ** 1.4 = 2.275. Half a code step of an n-bit file is
# 0.5 / (2^n - 1) in encoded units, so the linear value read back is off by at most
# 2.275 * 0.5 / (2^n - 1): 0.0045 for 8 bits, 1.7e-5 for 16 bits.
SRGB_SLOPE = 2.275


def _bound(bits: int) -> float:
    return SRGB_SLOPE * 0.5 / (2**bits - 1) + 1e-6


@pytest.fixture()
def ramp() -> torch.Tensor:
    """(3, 4, 64) linear radiance: a ramp 0..1 in x, different per channel; on the host, where
    read_image gives the images it reads."""
    x = torch.linspace(0, 1, 64, device="cpu")
    return torch.stack([x, x.flip(0), 0.25 + 0.5 * x]).unsqueeze(1).expand(3, 4, 64).contiguous()


def _write_png(path, image: torch.Tensor, bits: int = 8) -> None:
    """An sRGB PNG written independently of torchir: the exact curve, rounded to the nearest code
    (Mitsuba's own float -> integer conversion is off by up to a code)."""
    import mitsuba as mi

    x = image.permute(1, 2, 0).double().cpu().numpy()
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    dtype = np.uint8 if bits == 8 else np.uint16
    bitmap = mi.Bitmap(np.ascontiguousarray(np.rint(encoded * (2**bits - 1)).astype(dtype)), mi.Bitmap.PixelFormat.RGB)
    bitmap.set_srgb_gamma(True)
    bitmap.write(str(path))


def _write_exr(path, image: torch.Tensor) -> None:
    import mitsuba as mi

    mi.Bitmap(np.ascontiguousarray(image.permute(1, 2, 0).cpu().numpy()), mi.Bitmap.PixelFormat.RGB).write(str(path))


def test_png_16bit_png_and_exr_targets_read_back_as_the_same_linear_image(tmp_path, ramp):
    _write_exr(tmp_path / "ramp.exr", ramp)
    _write_png(tmp_path / "ramp.png", ramp, bits=8)
    _write_png(tmp_path / "ramp16.png", ramp, bits=16)
    exr, png, png16 = (load_image(tmp_path / f) for f in ("ramp.exr", "ramp.png", "ramp16.png"))
    assert torch.equal(exr, ramp)  # float files hold the values as they are
    assert (png - exr).abs().max() <= _bound(8)
    assert (png16 - exr).abs().max() <= _bound(16)
    # the value the issue reported: linear 0.508 must not come back as 0.222
    i = int((ramp[0, 0] - 0.508).abs().argmin())
    assert png[0, 0, i] == pytest.approx(float(ramp[0, 0, i]), abs=_bound(8))


def test_write_image_round_trips_within_half_a_code(tmp_path, ramp):
    from torchir.imageio import read_image, write_image

    assert torch.equal(read_image(write_image(tmp_path / "ramp.exr", ramp)), ramp)
    assert (read_image(write_image(tmp_path / "ramp.png", ramp)) - ramp).abs().max() <= _bound(8)


def test_jpeg_reads_back_like_the_exr_within_its_compression(tmp_path, ramp):
    from torchir.imageio import read_image, write_image

    exr = read_image(write_image(tmp_path / "ramp.exr", ramp))
    jpg = read_image(write_image(tmp_path / "ramp.jpg", ramp))
    # JPEG is lossy on top of the 8-bit quantisation: a smooth ramp stays within a few codes;
    # the double decoding it replaced was off by 0.29 at 0.5.
    assert (jpg - exr).abs().mean() <= 4 * _bound(8)
    assert (jpg - exr).abs().max() <= 0.03


def test_colorspace_override(tmp_path, ramp):
    from torchir.imageio import read_image, write_image

    write_image(tmp_path / "ramp.png", ramp)
    raw = read_image(tmp_path / "ramp.png", colorspace="linear")  # the stored (encoded) values / 255
    encoded = torch.where(ramp <= 0.0031308, 12.92 * ramp, 1.055 * ramp.pow(1 / 2.4) - 0.055)
    assert (raw - encoded).abs().max() <= 0.5 / 255 + 1e-6
    # a PNG written without encoding and read as linear gives the values back
    back = read_image(write_image(tmp_path / "data.png", ramp, colorspace="linear"), colorspace="linear")
    assert (back - ramp).abs().max() <= 0.5 / 255 + 1e-6
    # an EXR whose values are sRGB-encoded, read with colorspace='srgb', is decoded
    write_image(tmp_path / "encoded.exr", encoded)
    assert (read_image(tmp_path / "encoded.exr", colorspace="srgb") - ramp).abs().max() <= 1e-4
    with pytest.raises(ValueError, match="colorspace must be one of"):
        read_image(tmp_path / "ramp.png", colorspace="rec709")


def test_alpha_and_grey(tmp_path):
    import mitsuba as mi

    from torchir.imageio import read_image, write_image

    rgba = np.full((4, 4, 4), 0.5, np.float32)
    mi.Bitmap(rgba, mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "opaque.exr"))
    rgba[..., 3] = 1.0
    mi.Bitmap(rgba, mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "opaque.exr"))
    image = read_image(tmp_path / "opaque.exr")
    assert image.shape == (3, 4, 4) and torch.allclose(image, torch.full_like(image, 0.5))
    rgba[0, 0, 3] = 0.2
    mi.Bitmap(rgba, mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "transparent.exr"))
    with pytest.raises(ValueError, match="alpha channel with transparent pixels"):
        read_image(tmp_path / "transparent.exr")
    grey = read_image(write_image(tmp_path / "grey.png", torch.full((1, 4, 4), 0.5)))
    assert grey.shape == (1, 4, 4) and grey.sub(0.5).abs().max() <= _bound(8)
    # channels=3: a target for an RGB render instead of a (1, H, W) image that broadcasts silently
    as_rgb = read_image(tmp_path / "grey.png", channels=3)
    assert as_rgb.shape == (3, 4, 4) and torch.equal(as_rgb, grey.expand(3, 4, 4))
    assert read_image(tmp_path / "opaque.exr", channels=3).shape == (3, 4, 4)  # colour files unchanged
    with pytest.raises(ValueError, match="has 3 colour channels; channels=1 asks for a greyscale image"):
        read_image(tmp_path / "opaque.exr", channels=1)
    with pytest.raises(ValueError, match="channels must be None, 1 or 3, got 2"):
        read_image(tmp_path / "grey.png", channels=2)


def test_bad_input(tmp_path):
    from torchir.imageio import read_image, save_png, write_image

    with pytest.raises(FileNotFoundError, match="image not found"):
        read_image(tmp_path / "none.png")
    with pytest.raises(ValueError, match="unsupported image type '.tif'"):
        write_image(tmp_path / "x.tif", torch.zeros(3, 2, 2))
    with pytest.raises(ValueError, match=r"expected an image \(C, H, W\)"):
        write_image(tmp_path / "x.png", torch.zeros(2, 2, 3))
    with pytest.raises(ValueError, match="NaN/Inf"):
        write_image(tmp_path / "x.exr", torch.full((3, 2, 2), float("nan")))
    with pytest.raises(ValueError, match="writes .png files"):
        save_png(tmp_path / "x.exr", torch.zeros(3, 2, 2))


# ------------------------------------------------------------------ textures as Mitsuba stores them
SCENE_XML = """<scene version="3.0.0">
    <integrator type="prb"><integer name="max_depth" value="2"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 2.2" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/><rfilter type="box"/></film>
    </sensor>
    <shape type="rectangle" id="wall">
        <bsdf type="diffuse"><texture type="bitmap" name="reflectance">
            <string name="filename" value="$texture"/><string name="filter_type" value="nearest"/>
        </texture></bsdf>
    </shape>
    <emitter type="constant"/>
</scene>
"""


@pytest.fixture()
def texture_files(tmp_path, ramp):
    (tmp_path / "scene.xml").write_text(SCENE_XML)
    _write_png(tmp_path / "tex8.png", ramp, bits=8)
    _write_png(tmp_path / "tex16.png", ramp, bits=16)
    _write_exr(tmp_path / "tex.exr", ramp)
    return tmp_path


@pytest.mark.parametrize("name", ["tex8.png", "tex16.png", "tex.jpg", "tex.exr"])
def test_every_texture_storage_binds_as_float(texture_files, ramp, name):
    if name == "tex.jpg":
        import mitsuba as mi

        mi.Bitmap(str(texture_files / "tex8.png")).write(str(texture_files / name))
    scene = torchir.Scene.from_file(texture_files / "scene.xml", texture=name)
    key = "wall.bsdf.reflectance.data"
    info = scene.info(key)
    assert info.type_name == "TensorXf" and info.bindable and info.differentiable
    # the float texture holds the file's linear values, as read_image reads them
    expected = load_image(texture_files / name).permute(1, 2, 0).to(DEVICE)
    assert torch.allclose(scene.get(key), expected, atol=1e-6)
    texture = scene.get(key).requires_grad_()
    image = torchir.functions.render(scene, {key: texture}, spp=2, seed=0)
    image.mean().backward()
    assert texture.grad is not None and float(texture.grad.abs().sum()) > 0


def test_file_storage_is_refused_with_the_fix(texture_files):
    scene = torchir.Scene.from_file(texture_files / "scene.xml", texture="tex8.png", texture_storage="file")
    key = "wall.bsdf.reflectance.data"
    assert scene.info(key).type_name == "TensorXu8" and not scene.info(key).bindable
    with pytest.raises(TypeError, match="texture_storage='float'"):
        torchir.functions.render(scene, {key: torch.zeros(4, 64, 3)}, spp=1)
    with pytest.raises(ValueError, match="texture_storage must be"):
        torchir.Scene.from_file(texture_files / "scene.xml", texture="tex8.png", texture_storage="u8")


def test_dict_scenes_bind_8bit_textures_too(texture_files):
    scene = torchir.Scene.from_dict({
        "type": "scene",
        "wall": {"type": "rectangle", "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": str(texture_files / "tex8.png")}}},
    })
    assert scene.info("wall.bsdf.reflectance.data").type_name == "TensorXf"


# ------------------------------------------------------------------ clipped pixels of photos
def _old_rule(image: torch.Tensor, saturation: float = 1.0) -> torch.Tensor:
    """The trainer's rule before lossy files had their own: any channel at the top code."""
    return (image >= 0.995 * saturation).any(dim=-3, keepdim=True)


def _photo(size: int = 64) -> torch.Tensor:
    """(3, size, size) linear radiance of a made-up photo: a dim textured background, an
    over-exposed warm lamp (off the 8x8 block grid), a white disc and a 2-pixel red bar (both
    clipped), a bright patch that did not clip, and a 3x3 box filter so edges hold mixed pixels,
    as a render's pixel filter leaves them. On the host, as read_image gives the photo."""
    y, x = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32), indexing="ij")
    base = 0.03 + 0.3 * (x / size) * (1 - y / size) + 0.05 * torch.sin(x / 3) * torch.cos(y / 5) ** 2
    image = torch.stack([base, 0.8 * base, 0.6 * base + 0.02])
    image[:, 5:9, 19:33] = torch.tensor([20.0, 15.0, 5.0])[:, None, None]
    image[:, (x - 44.5) ** 2 + (y - 40.5) ** 2 <= 5.5**2] = torch.tensor([3.0, 3.0, 3.2])[:, None]
    image[:, 50:62, 13:15] = torch.tensor([8.0, 2.0, 1.0])[:, None, None]
    image[:, 30:38, 4:12] = 0.8
    return torch.nn.functional.avg_pool2d(image[None], 3, 1, 1, count_include_pad=False)[0].cpu()


def _write_jpeg(path, image: torch.Tensor, quality: int) -> None:
    """An 8-bit sRGB JPEG at ``quality``, as a camera or an image editor saves a photo."""
    import mitsuba as mi

    x = image.clamp(0, 1).permute(1, 2, 0).double().cpu().numpy()
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    bitmap = mi.Bitmap(np.ascontiguousarray(np.rint(encoded * 255).astype(np.uint8)), mi.Bitmap.PixelFormat.RGB)
    bitmap.set_srgb_gamma(True)
    bitmap.write(str(path), quality=quality)


@pytest.mark.parametrize("quality", [50, 75, 90, 95])
def test_clipped_mask_of_a_jpeg_leaves_out_what_the_codec_smeared(tmp_path, quality):
    """JPEG pulls a clipped lamp's edge pixels below the top code (true radiance 3-20, target
    ~0.9: the old rule kept 52-110 of them here). The lossy mask leaves out every pixel that
    clipped, so no kept pixel is off by more than 1 from the true radiance the render converges
    to, and it leaves out few others: not the dark pixels around the lamp nor a bright patch
    away from it."""
    from torchir.imageio import clipped_mask, read_image

    radiance = _photo()
    clipped = (radiance >= 1.0).any(0)
    _write_jpeg(tmp_path / "photo.jpg", radiance, quality)
    photo = read_image(tmp_path / "photo.jpg")
    mask = clipped_mask(photo, lossy=True)
    assert mask.shape == (1, 64, 64) and mask.dtype == torch.bool
    assert not bool((clipped & ~mask[0]).any()), f"{int((clipped & ~mask[0]).sum())} clipped pixels kept"
    residual = (photo - radiance).abs().amax(0)
    assert float(residual[~mask[0]].max()) < 1.0
    assert int(mask.sum()) <= int(clipped.sum()) + 20
    assert not bool(mask[0, 30:38, 4:12].any())  # bright (0.8) but far from a clipped pixel
    assert not bool(mask[0, 12:15, 19:33].any())  # dark ceiling 4-6 px under the lamp


def test_clipped_mask_of_a_png_is_the_top_code(tmp_path):
    """Lossless files keep the trainer's old rule exactly: the top code, nothing else."""
    from torchir.imageio import clipped_mask, read_image, write_image

    radiance = _photo()
    png = read_image(write_image(tmp_path / "photo.png", radiance))
    mask = clipped_mask(png)
    assert torch.equal(mask, _old_rule(png))
    assert torch.equal(mask[0], (radiance >= 1.0).any(0))  # exactly the pixels that clipped
    noise = torch.rand(2, 3, 16, 16, generator=torch.Generator(device=DEVICE).manual_seed(0)) * 2.2
    for saturation in (1.0, 2.0):
        assert torch.equal(clipped_mask(noise, saturation), _old_rule(noise, saturation))
        assert torch.equal(clipped_mask(noise[0], saturation), _old_rule(noise[0], saturation))


def test_clipped_mask_lossy_reach_and_floor():
    """Lossy rule: the top code, plus pixels with a channel >= 0.5 s within 8 px (Chebyshev)
    of a top-code pixel; per image of a batch; any channel count."""
    from torchir.imageio import clipped_mask

    image = torch.full((3, 32, 32), 0.1)
    image[1, 10, 10] = 0.995  # one channel at the top code
    image[0, 10, 18] = 0.6  # 8 px away, bright: left out
    image[2, 18, 2] = 0.5  # 8 px away diagonally, at the floor: left out
    image[:, 10, 19] = 0.9  # 9 px away: kept
    image[:, 11, 11] = 0.49  # next to it but below the floor: kept
    mask = clipped_mask(image, lossy=True)[0]
    assert mask.nonzero().tolist() == [[10, 10], [10, 18], [18, 2]]
    assert clipped_mask(image)[0].nonzero().tolist() == [[10, 10]]
    # saturation scales both thresholds
    assert torch.equal(clipped_mask(2 * image, saturation=2.0, lossy=True)[0], mask)
    assert not bool(clipped_mask(image, saturation=2.0, lossy=True).any())
    # a batch: each image on its own (the second has the bright pixels but no clipped one)
    batch = torch.stack([image, image.clone().fill_(0.1)])
    batch[1, :, 10, 18] = 0.9
    masks = clipped_mask(batch, lossy=True)
    assert masks.shape == (2, 1, 32, 32) and torch.equal(masks[0, 0], mask) and not bool(masks[1].any())
    # greyscale (read_image gives 1 channel for a grey file)
    grey = image.amax(0, keepdim=True)
    assert torch.equal(clipped_mask(grey, lossy=True), mask[None])
    # nothing clipped: nothing left out, whatever is bright
    assert not bool(clipped_mask(torch.full((3, 8, 8), 0.9), lossy=True).any())


def test_clipped_mask_bad_input():
    from torchir.imageio import clipped_mask

    with pytest.raises(ValueError, match=r"expected an image \(C, H, W\) or a batch \(B, C, H, W\), got \(4, 4\)"):
        clipped_mask(torch.zeros(4, 4))
    with pytest.raises(ValueError, match=r"got \(1, 1, 3, 4, 4\)"):
        clipped_mask(torch.zeros(1, 1, 3, 4, 4))
    with pytest.raises(ValueError, match=r"got ndarray"):
        clipped_mask(np.zeros((3, 4, 4)))
    with pytest.raises(TypeError, match="floating-point tensor, got torch.uint8"):
        clipped_mask(torch.zeros(3, 4, 4, dtype=torch.uint8))
    for bad in (0, -1.0, float("nan"), float("inf"), "1", True):
        with pytest.raises(ValueError, match="saturation must be a finite number > 0"):
            clipped_mask(torch.zeros(3, 4, 4), saturation=bad)
    with pytest.raises(TypeError, match="lossy must be True or False, got 'jpg'"):
        clipped_mask(torch.zeros(3, 4, 4), lossy="jpg")


def test_is_lossy():
    from torchir.imageio import is_lossy

    assert is_lossy("a.jpg") and is_lossy("x/b.JPEG")
    assert not any(is_lossy(f) for f in ("a.png", "a.exr", "a.hdr", "a.pfm", "jpg"))


def test_exr_files_are_written_and_read_with_a_one_thread_drjit_pool(tmp_path):
    """Mitsuba's OpenEXR reader and writer never return when Dr.Jit's pool has one thread (as
    users set it for determinism): torchir widens the pool for the file and restores it. A
    fresh process, so that resizing the pool cannot disturb this one; the timeout is the failure."""
    import subprocess
    import sys

    code = (
        "import torch, drjit as dr, torchir; torchir.backend.set_variant('auto');"
        "from torchir.imageio import write_image, read_image; dr.set_thread_count(1);"
        f"x = torch.rand(3, 8, 8); p = write_image({str(tmp_path / 'a.exr')!r}, x);"
        "y = read_image(p); print(dr.thread_count(), float((y - x).abs().max()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    threads, error = out.stdout.split()
    assert threads == "1" and float(error) == 0.0  # the pool as the user set it; the pixels exact (float EXR)
