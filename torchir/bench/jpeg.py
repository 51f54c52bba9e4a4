#!/usr/bin/env python
"""Colours fitted from JPEG photos against the PNG of the same photo, in units of seed noise.

A photo target saved as JPEG has been through the codec (chroma subsampling, quantised 8x8 DCT
blocks); the trainer adds the codec's change of a running mean of the renders
(:class:`torchir.jpeg.CodecCorrection`). The question is whether a JPEG then gives the PNG's
answer within the fit's own seed noise. The lamp's RGB radiance of the Cornell box is fitted
through the trainer's step (L2, Adam, from 0.9x the truth; the answer is the mean over the second
half of the steps) from a PNG and from JPEGs (Mitsuba's writer, 4:2:0) of one rendered photo,
for several render seeds, with the codec's full correction, its chroma filter only, and none.

Reported per quality and correction: the paired offset from the PNG's answer (mean over seeds,
percent) and the JPEG's mean minus the PNG's mean in PNG seed standard deviations.

The EXR of the same photo is fitted too: its offset from the PNG is what 8-bit quantisation
alone moves the answer, the scale a JPEG's offset is measured against beside the seed noise.

Usage:
    torchir bench jpeg [--quick]        (default: 64², 400 steps, 3 seeds; --quick: 32², 120 steps, 2 seeds)
    torchir bench jpeg --resolution 256 --photo-spp 1024 --corrections codec   (photos as users take them)

Writes ``<out>/results.json``, ``<out>/summary.md`` and ``<out>/jpeg_offsets.png``.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from torchir.bench import environment, write_outputs

QUALITIES = (75, 90, 95)
CORRECTIONS = ("codec", "chroma", "none")
KEY = "light.emitter.radiance.value"


def write_photos(radiance: torch.Tensor, folder: Path, qualities: Sequence[int]) -> dict[str, Path]:
    """The photo as PNG and as 4:2:0 JPEGs written by Mitsuba (8-bit sRGB of the clipped radiance)."""
    import mitsuba as mi

    from torchir.imageio import to_srgb, write_image

    write_image(folder / "photo.png", radiance)
    write_image(folder / "photo.exr", radiance)
    codes = np.rint(255 * to_srgb(radiance.clamp(0, 1)).permute(1, 2, 0).double().cpu().numpy()).astype(np.uint8)
    bitmap = mi.Bitmap(np.ascontiguousarray(codes), mi.Bitmap.PixelFormat.RGB)
    bitmap.set_srgb_gamma(True)
    out = {"png": folder / "photo.png", "exr": folder / "photo.exr"}
    for quality in qualities:
        out[f"q{quality}"] = folder / f"q{quality}.jpg"
        bitmap.write(str(out[f"q{quality}"]), quality=quality)
    return out


def _corrected(correction: str):
    """The module's codec correction with only the chroma filter, or none (for the comparison)."""
    from torchir.jpeg import CodecCorrection

    class Partial(CodecCorrection):
        def __call__(self, image, view, factors, srgb=True, tables=None):
            return image if correction == "none" else super().__call__(image, view, factors, srgb, None)

    return CodecCorrection() if correction == "codec" else Partial()


def fit(module: Any, target: Path, steps: int, correction: str) -> torch.Tensor:
    """The lamp's radiance fitted to ``target`` through the trainer's step (mean of the second half)."""
    from torchir.training import ViewDataModule

    datamodule = ViewDataModule(targets=[str(target)])
    datamodule.trainer = SimpleNamespace(lightning_module=module, world_size=1)
    datamodule.setup("fit")
    batch = next(iter(datamodule.train_dataloader()))
    latent = module.scene_parameters[0].latent
    latent.data.copy_(module.scene.get(KEY) * 0.9)
    module._codec_correction = _corrected(correction)
    optimiser = torch.optim.Adam([latent], lr=0.1)
    trail = []
    for step in range(steps):
        module._trainer = SimpleNamespace(world_size=1, global_step=step, current_epoch=0, log_every_n_steps=1, loggers=[],
                                          should_stop=False, datamodule=datamodule)
        optimiser.zero_grad()
        module.training_step(batch, 0).backward()
        optimiser.step()
        if step >= steps // 2:
            trail.append(latent.detach().clone())
    return torch.stack(trail).mean(0)


def run(resolution: int, steps: int, seeds: Sequence[int], qualities: Sequence[int], photo_spp: int,
        corrections: Sequence[str] = CORRECTIONS) -> dict[str, Any]:
    """Every seed's fitted radiance from the PNG, the EXR and each JPEG under each of ``corrections``."""
    import torchir
    from torchir.training import InverseRenderingModule

    folder = Path(tempfile.mkdtemp())
    answers: dict[str, list[list[float]]] = {}
    started = time.perf_counter()
    for n, seed in enumerate(seeds):
        module = InverseRenderingModule(scene="cbox", resolution=resolution, spp=8, loss="l2", seed=seed,
                                        parameters={KEY: {"init": 1.0, "transform": "none"}})
        module.log = lambda *a, **k: None
        module._truth = {}
        if n == 0:
            photos = write_photos(torchir.functions.render(module.scene, {}, spp=photo_spp, seed=2), folder, qualities)
        answers.setdefault("png", []).append(fit(module, photos["png"], steps, "none").tolist())
        answers.setdefault("exr", []).append(fit(module, photos["exr"], steps, "none").tolist())
        for quality in qualities:
            for correction in corrections:
                answer = fit(module, photos[f"q{quality}"], steps, correction)
                answers.setdefault(f"q{quality} {correction}", []).append(answer.tolist())
        print(f"seed {seed} done ({n + 1}/{len(seeds)}, {time.perf_counter() - started:.0f} s)", flush=True)
    return {"answers": answers, "truth": module.scene.get(KEY).tolist()}


def offsets(answers: dict[str, list[list[float]]]) -> dict[str, dict[str, list[float]]]:
    """Per JPEG row: paired offset from the PNG (percent, mean over seeds) and the offset of the
    means in PNG seed standard deviations (R, G, B)."""
    png = torch.tensor(answers["png"], dtype=torch.float64)
    spread = png.std(0) if len(png) > 1 else torch.full((3,), float("nan"), dtype=torch.float64)
    out = {}
    for name, rows in answers.items():
        if name == "png":
            continue
        jpeg = torch.tensor(rows, dtype=torch.float64)
        out[name] = {"percent": (100 * ((jpeg - png) / png).mean(0)).tolist(),
                     "in_seed_sd": ((jpeg.mean(0) - png.mean(0)) / spread).tolist()}
    return out


def table(results: dict[str, Any]) -> str:
    png = torch.tensor(results["answers"]["png"], dtype=torch.float64)
    spread = 100 * png.std(0) / png.mean(0) if len(png) > 1 else torch.full((3,), float("nan"))
    lines = [f"PNG answer's seed spread (R, G, B): {', '.join(f'{s:.2f} %' for s in spread.tolist())}", "",
             "| JPEG | correction | offset from PNG (R, G, B) | in PNG seed sd (R, G, B) |", "|---|---|---|---|"]
    for name, row in offsets(results["answers"]).items():
        quality, correction = name.split() if " " in name else (name, "(8-bit quantisation)")
        lines.append(f"| {quality} | {correction} | {', '.join(f'{p:+.2f} %' for p in row['percent'])} | "
                     f"{', '.join(f'{z:+.1f}' for z in row['in_seed_sd'])} |")
    return "\n".join(lines) + "\n"


def summary(results: dict[str, Any]) -> str:
    """The suite's Markdown, from its ``results.json`` alone (the docs' results page uses it)."""
    s = results["settings"]
    return (f"## JPEG targets: the lamp's colour against the PNG's ({s['resolution']}², {s['steps']} steps, "
            f"{s['seeds']} seeds, photo at {s['photo_spp']} spp)\n\n" + table(results))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("bench_results/jpeg"))
    parser.add_argument("--seeds", type=int, default=None)
    parser.add_argument("--resolution", type=int, default=None, help="image side (default 64; --quick 32)")
    parser.add_argument("--steps", type=int, default=None, help="Adam steps a fit (default 400; --quick 120)")
    parser.add_argument("--photo-spp", type=int, default=64, help="samples per pixel of the photo")
    parser.add_argument("--corrections", nargs="+", choices=CORRECTIONS, default=list(CORRECTIONS))
    args = parser.parse_args(argv)
    resolution, steps, seeds = (32, 120, 2) if args.quick else (64, 400, 3)
    resolution, steps, seeds = args.resolution or resolution, args.steps or steps, args.seeds or seeds
    args.out.mkdir(parents=True, exist_ok=True)
    results = run(resolution, steps, range(seeds), QUALITIES, photo_spp=args.photo_spp, corrections=args.corrections)
    results["settings"] = {"resolution": resolution, "steps": steps, "seeds": seeds, "photo_spp": args.photo_spp, "spp": 8,
                           "corrections": list(args.corrections)}
    results["environment"] = environment()
    rows = offsets(results["answers"])

    def draw(ax) -> None:
        for correction, marker in zip(args.corrections, "os^"):
            for channel, colour in enumerate("rgb"):
                ys = [abs(rows[f"q{q} {correction}"]["in_seed_sd"][channel]) for q in QUALITIES]
                ax.plot(QUALITIES, ys, marker=marker, color=colour, label=f"{correction} ({'RGB'[channel]})",
                        linestyle="-" if correction == "codec" else ":")
        ax.axhline(2.0, color="grey", linewidth=0.8)

    write_outputs(args.out, summary(results), results, draw, "jpeg_offsets.png", "JPEG quality", "|JPEG - PNG| in PNG seed sd", log_y=True)


if __name__ == "__main__":
    main()
