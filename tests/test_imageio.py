"""Image files <-> linear radiance: every format reads back like the EXR of the same image, once
decoded (a PNG used to be sRGB-decoded twice: 0.508 read back as 0.222)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchir
from torchir.training import load_image  # how targets are read (it existed before read_image)

# Largest slope of the sRGB decoding curve, d(linear)/d(encoded), reached at encoded = 1:
# (2.4 / 1.055) * ((1 + 0.055) / 1.055) ** 1.4 = 2.275. Half a code step of an n-bit file is
# 0.5 / (2^n - 1) in encoded units, so the linear value read back is off by at most
# 2.275 * 0.5 / (2^n - 1): 0.0045 for 8 bits, 1.7e-5 for 16 bits.
SRGB_SLOPE = 2.275


def _bound(bits: int) -> float:
    return SRGB_SLOPE * 0.5 / (2**bits - 1) + 1e-6


@pytest.fixture()
def ramp() -> torch.Tensor:
    """(3, 4, 64) linear radiance: a ramp 0..1 in x, different per channel."""
    x = torch.linspace(0, 1, 64)
    return torch.stack([x, x.flip(0), 0.25 + 0.5 * x]).unsqueeze(1).expand(3, 4, 64).contiguous()


def _write_png(path, image: torch.Tensor, bits: int = 8) -> None:
    """An sRGB PNG written independently of torchir: the exact curve, rounded to the nearest code
    (Mitsuba's own float -> integer conversion is off by up to a code)."""
    import mitsuba as mi

    x = image.permute(1, 2, 0).double().numpy()
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    dtype = np.uint8 if bits == 8 else np.uint16
    bitmap = mi.Bitmap(np.ascontiguousarray(np.rint(encoded * (2**bits - 1)).astype(dtype)), mi.Bitmap.PixelFormat.RGB)
    bitmap.set_srgb_gamma(True)
    bitmap.write(str(path))


def _write_exr(path, image: torch.Tensor) -> None:
    import mitsuba as mi

    mi.Bitmap(np.ascontiguousarray(image.permute(1, 2, 0).numpy()), mi.Bitmap.PixelFormat.RGB).write(str(path))


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
    expected = load_image(texture_files / name).permute(1, 2, 0)
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
